/* edgemodbus: the state of one open link (emb_link), which Python allocates zeroed with
 * its context and every link kind (csrc/emb_rtu.c, csrc/emb_stream.c) reads and writes;
 * includes nothing of ours. */
#ifndef EMB_LINK_H
#define EMB_LINK_H

#include <stdint.h>

#define EMB_HB_MAX 64       /* longest heartbeat pattern */
#define EMB_RX_SIZE 512     /* stream links: bytes received and not framed yet */
#define EMB_RING_SIZE 4096  /* stream links: reports waiting (a 2-byte length each) */
#define EMB_REPORT_MAX 261  /* a wrapped frame: FF AA, address, RTU frame (<= 256), 0D */
#define EMB_DROP_SHOW 32    /* bytes of the last dropped wrapped frame kept for the log */
#define EMB_TRACE_SIZE 8192 /* the frame trace ring (emb_trace) */
#define EMB_TRACE_HEAD 11   /* per traced frame: direction (1), length (2), time (8) */
#define EMB_TRACE_TX 1      /* a frame we sent */
#define EMB_TRACE_RX 2      /* a frame we received (a reply, also one refused) */
#define EMB_TRACE_FLUSH_NS 1000000000LL /* the engine hands frames to Python this soon */

/* The receive buffer of a DTU stream link (emb_link.sb): bytes received and not framed
 * yet.  The caller allocates it, for stream links only.  The report ring (emb_link.ring,
 * EMB_RING_SIZE bytes) is apart: only a wrapped link queues reports, so a plain DTU does
 * without its 4 kB (docs/scale.md "Memory per DTU"). */
typedef struct {
    uint8_t rx[EMB_RX_SIZE];
} emb_stream_buf;

/* The frame trace of a link (on while the line's logger is at DEBUG): every frame the
 * transactions send and receive, with its direction and CLOCK_MONOTONIC time, written by
 * csrc/emb_io.c (also inside the line engine, without the GIL) and taken by the worker
 * (emb_trace_take), which formats and logs them.  A full ring loses the newest frames,
 * counted.  The caller allocates it zeroed, for traced links only. */
typedef struct {
    uint8_t buf[EMB_TRACE_SIZE];
    uint32_t head;  /* the oldest record's first byte */
    uint32_t used;  /* bytes of the records waiting */
    uint32_t n;     /* records waiting */
    int64_t first_ns; /* when the oldest of them was traced */
    long lost;      /* frames the full ring could not take; the caller reads and resets */
} emb_trace;

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
    long syscalls;  /* system calls of the plain RTU and Modbus TCP transactions
                     * (csrc/emb_rtu.c: stale input dropped, request sent, waits, reads,
                     * the pending check); the caller reads it */
    int rx_drained; /* private to csrc/emb_rtu.c: the socket reader's last read came
                     * back short, so nothing more was waiting behind the reply */
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
    uint8_t *ring;          /* the reports waiting, EMB_RING_SIZE bytes (required with
                             * wrapped; NULL on other links) */
    emb_trace *trace;       /* the frame trace, NULL: off */
    /* private to csrc/emb_stream.c */
    int32_t absorb;         /* bytes of the last dropped frame still to skip, -1: up to the
                             * next header */
    uint32_t rx_len;
    uint32_t ring_head;
    uint32_t ring_used;
} emb_link;

#endif
