/* edgemodbus: one C call per Modbus transaction (and per line clean-up), so that a bus
 * worker re-takes the GIL once per request instead of once per libmodbus call. */
#ifndef EMB_IO_H
#define EMB_IO_H

#include <stdint.h>
#include <modbus.h>

/* State of one line kept between transactions; the caller allocates it with the
 * context and sets mbap and echo once. */
typedef struct {
    int mbap;       /* Modbus TCP: MBAP header (we send it ourselves, with our own tid) */
    int echo;       /* RTU: the line echoes every request; read it back before the reply */
    unsigned tid;   /* Modbus TCP: transaction id of the last request sent */
    long discarded; /* bytes thrown away (stale input, echoes, superseded frames); the
                     * caller reads and resets it */
    int rsp_len;    /* length of the reply ADU left in rsp by the last call, else 0 */
    uint32_t char_ns; /* serial lines: nanoseconds per character on the wire (start, data,
                       * parity and stop bits at the baud rate); 0 on sockets.  The
                       * reader then sleeps while the rest of a frame is on its way
                       * instead of waking for every byte. */
} emb_link;

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

int emb_read(modbus_t *ctx, emb_link *lk, int slave, int function, int addr, int nb,
             void *dest, uint8_t *rsp);
int emb_transact(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                 uint8_t *rsp);
int emb_send(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len);
long emb_discard_input(int fd, int total_ms, int quiet_ms, int limit_ms);

#endif
