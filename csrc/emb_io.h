/* edgemodbus: one C call per Modbus transaction (and per line clean-up), so that a bus
 * worker re-takes the GIL once per request instead of once per libmodbus call. */
#ifndef EMB_IO_H
#define EMB_IO_H

#include <stdint.h>
#include <modbus.h>

#define EMB_HB_MAX 64       /* longest heartbeat pattern */
#define EMB_RX_SIZE 512     /* stream links: bytes received and not framed yet */
#define EMB_RING_SIZE 4096  /* stream links: reports waiting (a 2-byte length each) */
#define EMB_REPORT_MAX 261  /* a wrapped frame: FF AA, address, RTU frame (<= 256), 0D */
#define EMB_DROP_SHOW 32    /* bytes of the last dropped wrapped frame kept for the log */

/* The buffers of a DTU stream link (emb_link.sb): bytes received and not framed yet, and
 * the reports waiting.  The caller allocates them, for stream links only. */
typedef struct {
    uint8_t rx[EMB_RX_SIZE];
    uint8_t ring[EMB_RING_SIZE];
} emb_stream_buf;

/* State of one line kept between transactions; the caller allocates it zeroed with the
 * context and sets mbap, echo, char_ns, and for a DTU stream wrapped, the heartbeat and
 * sb, once. */
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
    /* DTU streams (RTU over a socket; csrc/emb_stream.c frames them byte for byte) */
    int wrapped;            /* edge-MCU frames: FF AA | register address | RTU frame | 0D;
                             * frames other than the reply are unsolicited reports */
    uint32_t hb_len;        /* the heartbeat a DTU sends on an idle link (0: none), */
    uint8_t hb[EMB_HB_MAX]; /* skipped wherever a frame could begin, and counted */
    long heartbeats;        /* heartbeats skipped; the caller reads and resets */
    long dropped;           /* wrapped frames dropped (bad header, length, tail, CRC, noise) */
    long reports_lost;      /* reports the full ring could not take */
    uint8_t last_drop[EMB_DROP_SHOW]; /* the first bytes of the last frame dropped */
    int last_drop_len;
    uint32_t n_reports;     /* reports waiting in the ring (emb_report_take) */
    uint32_t n_before;      /* the first n_before of them came before the last reply: the
                             * caller applies them first, the others after the reply */
    emb_stream_buf *sb;     /* a stream link's buffers (required with wrapped or hb_len) */
    /* private to csrc/emb_stream.c */
    int32_t absorb;         /* bytes of the last dropped frame still to skip, -1: up to the
                             * next header */
    uint32_t rx_len;
    uint32_t ring_head;
    uint32_t ring_used;
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
long emb_link_discard(modbus_t *ctx, emb_link *lk, int total_ms, int quiet_ms, int limit_ms);
long emb_pump(modbus_t *ctx, emb_link *lk);
long emb_feed(emb_link *lk, const uint8_t *data, int n);
int emb_report_take(emb_link *lk, uint8_t *out);

#endif
