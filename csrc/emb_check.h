/* edgemodbus: the one reply check (pure bytes, no I/O; includes nothing of ours).  Every
 * reply the master takes, to a polled read, a write or a forwarded request, on every
 * link kind, is checked by emb_check_reply (after libmodbus's check_confirmation, which
 * 3.1.6 makes for its own requests only, and leaves out write echoes). */
#ifndef EMB_CHECK_H
#define EMB_CHECK_H

#include <stdint.h>
#include <modbus.h>

#define EMB_MAX_ADU 260 /* MODBUS_TCP_MAX_ADU_LENGTH: rsp holds at least this much */
#define EMB_MAX_RTU 256 /* an RTU ADU: address + PDU + CRC (Modbus over Serial Line 2.5.1) */
#define EMB_MBAP 7      /* MBAP header (Modbus Messaging on TCP/IP v1.0b, 3.1.3) */

/* errno values of our own reply checks (libmodbus's own errnos are kept as they are). */
#define EMB_EBASE (MODBUS_ENOBASE + 1000)
#define EMB_EEXCEPTION (EMB_EBASE)        /* + exception code 0..255: exception response */
#define EMB_EPARTIAL (EMB_EBASE + 256)    /* the reply stopped short: byte timeout */
#define EMB_EECHO (EMB_EBASE + 257)       /* echo option: the echo differs from the request */
#define EMB_EECHOSEEN (EMB_EBASE + 258)   /* a reply starting with our own request: echo */
#define EMB_ESLAVE (EMB_EBASE + 259)      /* reply from another slave / unit id */
#define EMB_EFUNCTION (EMB_EBASE + 260)   /* function code is not the request's */
#define EMB_EOTHEREXC (EMB_EBASE + 261)   /* exception response for another function code */
#define EMB_ECOUNT (EMB_EBASE + 262)      /* byte count does not match the request */
#define EMB_ETID (EMB_EBASE + 263)        /* MBAP transaction id is not the request's */
#define EMB_EPROTOID (EMB_EBASE + 264)    /* MBAP protocol id is not 0 */
#define EMB_EMBAPLEN (EMB_EBASE + 265)    /* MBAP length disagrees with the frame */
#define EMB_EWECHO (EMB_EBASE + 266)      /* a write's reply does not echo the request */
#define EMB_ELENGTH (EMB_EBASE + 267)     /* reply length is not what the request needs */

int emb_reply_length(const uint8_t *p, int got, int mbap);
int emb_check_reply(const uint8_t *req, int req_len, const uint8_t *rsp, int rsp_len,
                    int *exc);
int emb_check_mbap(const uint8_t *adu, int len, long tid);
int emb_check_adu(int mbap, long tid, int slave, const uint8_t *pdu, int pdu_len,
                  const uint8_t *adu, int adu_len, int *exc);

#endif
