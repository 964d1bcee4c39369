/* edgemodbus: a loop link's state (emb_loop_link: csrc/emb_loop_link.h runs it as a
 * state machine) and its non-blocking I/O in csrc/emb_loop_io.c: the request put on the
 * wire of the link's kind and sent (the rest once the socket is writable again), what
 * comes while no reply is awaited, the reply framed and, behind it, a second answer
 * ("the last answer wins").  The link kind is its emb_link's (mbap, wrapped, echo), as
 * for the blocking engine's backends (csrc/emb_backend.h). */
#ifndef EMB_LOOP_IO_H
#define EMB_LOOP_IO_H

#include "emb_check.h" /* EMB_MAX_ADU */
#include "emb_fault.h"
#include "emb_loop.h"

#define EMB_LS_IDLE 0   /* between requests: the next due block, pacing */
#define EMB_LS_AWAIT 1  /* a request is out: its reply, or the reply timeout */
#define EMB_LS_SETTLE 2 /* after a failure: wait out a late reply, or drain a bad frame */
#define EMB_LS_FAILED 3 /* the link failed (event_errno): Python closes it */
#define EMB_LS_SEND 4   /* a request went out in part (a full send buffer): the rest when
                         * the socket is writable, within the reply timeout */
#define EMB_LS_NEXT 5   /* a reply came with another frame arriving behind it: the rest
                         * of that one, within the byte timeout (the last answer wins) */
#define EMB_LL_WIRE 264 /* the longest request on the wire: FF AA, address, RTU, 0D */

typedef struct {
    emb_engine *e;   /* devices, counters, link (with stream buffers), rsp, regs, bits,
                      * pacing and cleaning; e->ctx is not used */
    int fd;          /* the link's socket (non-blocking) */
    uint32_t slot;   /* its slot on the loop */
    int state;       /* EMB_LS_* */
    int jobs;        /* Python has jobs queued for it: once idle, emb_loop_link_run comes
                      * back EMB_EV_WAKE before the next request (Python clears it) */
    int owed;        /* a job ran since the last read: with jobs set, the link sends its
                      * next due read first (the fairness rule of csrc/emb_engine.c) */
    int held;        /* it came back with an event Python has not taken yet
                      * (csrc/emb_loop_turn.c runs it no more until Python clears it) */
    int which;       /* the device in its pass, -1: none */
    int tries;       /* retries left for the block under way */
    int first;       /* ... of emb_fault_tries */
    int retrying;    /* the next request is a retry of the block under way */
    int byte_ms;     /* the longest gap inside a reply (0: the whole reply within the
                      * response timeout) */
    int kind, code, err; /* the failure being cleaned */
    int clean_total_ms, clean_limit_ms;
    int64_t start_ns;    /* the request went out (or the cleaning began) */
    int64_t last_ns;     /* the last bytes of the reply or of the cleaning came (0: none) */
    long dropped;        /* bytes dropped by the cleaning under way */
    int req_len;
    uint8_t req[8];      /* the unit id and the PDU sent (a read: 6 bytes) */
    int echo_left;       /* the echo option: the request's own bytes still to come back */
    int skipped;         /* Modbus TCP: replies to other transaction ids skipped */
    int got;             /* Modbus TCP: bytes of the reply read into e->rsp so far */
    int want_out;        /* the socket is watched for EPOLLOUT (EMB_LS_SEND) */
    int wire_len, sent;  /* the request on the wire, and how much of it went out */
    uint8_t wire[EMB_LL_WIRE];
    int first_len;       /* the reply taken (in e->rsp) while a second frame arrives */
    int got2;            /* Modbus TCP: bytes of that second frame in next so far */
    uint8_t next[EMB_MAX_ADU]; /* the second frame */
} emb_loop_link;

int emb_ll_header(const emb_link *lk);
int emb_ll_trailer(const emb_link *lk);
int emb_ll_frame(emb_loop_link *k);
int emb_ll_push(emb_loop *lp, emb_loop_link *k, int64_t now);
long emb_ll_absorb(emb_loop_link *k, int *came);
int emb_ll_take(emb_loop_link *k, int64_t now, int *got);
int emb_ll_pending(emb_loop_link *k);
int64_t emb_ll_reply_due(emb_loop_link *k);
int emb_ll_last_answer(emb_loop *lp, emb_loop_link *k, int64_t now);

#endif
