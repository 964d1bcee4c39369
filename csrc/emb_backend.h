/* edgemodbus: what a link kind does, as one table of functions (after libmodbus's
 * modbus_backend_t in its modbus-private.h: send, receive and check as one interface).
 * One instance per kind: plain RTU over a serial port or a socket (emb_rtu_backend) and
 * Modbus TCP (emb_mbap_backend) in csrc/emb_rtu.c; DTU streams with heartbeats
 * (emb_stream_backend) and with wrapped report frames (emb_wrapped_backend) in
 * csrc/emb_stream.c.  csrc/emb_io.c runs every transaction through the table of the link
 * (emb_backend_of) and checks every reply with emb_check_reply (csrc/emb_check.c); a
 * backend never calls emb_io.c. */
#ifndef EMB_BACKEND_H
#define EMB_BACKEND_H

#include <stdint.h>
#include <modbus.h>

#include "emb_link.h"

/* The request a reply must answer, as a receiver needs it: the slave (an RTU frame from
 * another one is skipped), and for a wrapped link the function, the register address
 * and, for a read, the byte count (-1: any). */
typedef struct {
    int slave, function, address, count;
} emb_want;

typedef struct emb_backend {
    const char *name;
    int header;   /* bytes of a reply ADU before its function code: 1 (address), 7 (MBAP) */
    int trailer;  /* bytes after the PDU: 2 (CRC), 0 */
    int min_next; /* bytes waiting behind a reply that make another whole frame worth
                   * reading ("the last answer wins"); 0: the first answer is taken */
    /* Before a request: take in or drop what came since the last one (RTU frames carry
     * no transaction id, Modbus over Serial Line v1.02, 2.5.1).  0, or -1 with errno
     * when the link is found closed. */
    int (*prepare)(emb_link *lk, int fd);
    /* Frame pdu for slave and send it; sent: the ADU on the wire (the RTU frame inside a
     * wrapped one), at least EMB_MAX_ADU bytes.  0, or -1 with errno. */
    int (*send)(modbus_t *ctx, emb_link *lk, int slave, const uint8_t *pdu, int pdu_len,
                uint8_t *sent, int *sent_len);
    /* Read back the request's own bytes (the echo option); NULL: not on this kind, and
     * no reply is taken for an echo (EMB_EECHOSEEN) either. */
    int (*skip_echo)(emb_link *lk, int fd, const uint8_t *sent, int sent_len, int first_ms,
                     int byte_ms);
    /* Receive one reply frame into rsp (EMB_MAX_ADU bytes), its integrity checked (CRC):
     * its length, 0 for an RTU frame from another slave, -1 with errno (ETIMEDOUT,
     * EMB_EPARTIAL, EMBBADDATA, EMBBADCRC, the link's).  *got: the bytes taken, which a
     * receiver that reads past the frame (plain RTU and Modbus TCP on a socket,
     * csrc/emb_rtu.c) leaves in rsp behind it; on entry, the bytes of such a read that
     * the caller put back at rsp's start (0 else; the others ignore it). */
    int (*recv)(emb_link *lk, int fd, const emb_want *want, int first_ms, int byte_ms,
                uint8_t *rsp, int *got);
    /* The header fields of a reply that are not in the PDU (MBAP: transaction id,
     * protocol id, length); NULL: none.  0 or the EMB_E* errno. */
    int (*check_header)(const emb_link *lk, const uint8_t *rsp, int len);
    /* Bytes received and not framed yet (heartbeats aside). */
    int (*pending)(emb_link *lk, int fd);
    /* Settle or drain (emb_discard_input's timing): the bytes dropped, or -1 with errno. */
    long (*discard)(emb_link *lk, int fd, int total_ms, int quiet_ms, int limit_ms);
    /* What is readable now, nothing asked: the reports waiting, or -1 with errno. */
    long (*pump)(emb_link *lk, int fd);
    /* Bytes that came before the link, taken as if received now: the reports waiting. */
    long (*feed)(emb_link *lk, const uint8_t *data, int n);
} emb_backend;

#endif
