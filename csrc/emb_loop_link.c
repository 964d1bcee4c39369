/* edgemodbus: one link of the loop engine as a state machine (see emb_loop_link.h).
 *
 * emb_loop_link_run() takes the link as far as it goes without waiting: it reads what
 * the socket holds, frames and checks a reply, runs the fault policy's pure steps
 * (csrc/emb_fault.c) and the device passes (csrc/emb_engine.c's emb_dev_begin_pass /
 * emb_dev_end_pass), sends the next request (its rest once the socket is writable again,
 * EMB_LS_SEND), and sets the link's one deadline on the loop's heap for what it waits
 * for next.  The framing is the blocking backends' (csrc/emb_backend.h), on reads that
 * never wait: a DTU stream's bytes go into its buffer and are framed there
 * (csrc/emb_stream.c: plain RTU with heartbeats, the request's own bytes first with the
 * echo option; wrapped frames, every frame but the reply queued as a report and handed
 * to Python as the blocking engine hands them, emb_engine_reports); a Modbus TCP reply is
 * read as far as its header tells (emb_reply_length) and its MBAP header checked, a reply
 * to another transaction id skipped (Modbus Messaging on TCP/IP v1.0b, 3.1.3).  A late
 * reply during a settle is dropped (RTU frames carry no transaction id: Modbus over
 * Serial Line v1.02, 2.5.1.1).  Every frame sent and received goes to the link's trace
 * ring (csrc/emb_io.c emb_trace_put), as in the blocking engine. */
#include "emb_loop_link.h"

#include <errno.h>
#include <string.h>
#include <sys/socket.h>

#include "emb_check.h"
#include "emb_engine.h"
#include "emb_io.h" /* emb_trace_put */
#include "emb_rtu.h"
#include "emb_stream.h"

#define EMB_LL_WRAP 4 /* a wrapped request: FF AA and the register address before the RTU
                       * frame, 0D after it (csrc/emb_stream.c) */

/* Bytes of a reply ADU before its function code, and after its PDU (emb_backend.h). */
static int emb_ll_header(const emb_link *lk)
{
    return lk->mbap ? EMB_MBAP : 1;
}

static int emb_ll_trailer(const emb_link *lk)
{
    return lk->mbap ? 0 : 2;
}

/* Put the request in k->req on the wire format of the link (k->wire): an RTU frame, a
 * wrapped one, or an MBAP header with the link's next transaction id.  0, or -1. */
static int emb_ll_frame(emb_loop_link *k)
{
    emb_link *lk = k->e->lk;
    int len = 0;

    if (lk->mbap) {
        lk->tid = (lk->tid + 1U) & 0xFFFFU;
        k->wire[0] = (uint8_t)(lk->tid >> 8);
        k->wire[1] = (uint8_t)(lk->tid & 0xFF);
        k->wire[2] = 0;
        k->wire[3] = 0;
        k->wire[4] = (uint8_t)(k->req_len >> 8); /* the unit id and the PDU */
        k->wire[5] = (uint8_t)(k->req_len & 0xFF);
        memcpy(k->wire + 6, k->req, (size_t)k->req_len);
        k->wire_len = 6 + k->req_len;
        return 0;
    }
    if (!lk->wrapped)
        return emb_rtu_frame(k->req[0], k->req + 1, k->req_len - 1, k->wire, &k->wire_len);
    if (emb_rtu_frame(k->req[0], k->req + 1, k->req_len - 1, k->wire + EMB_LL_WRAP, &len) == -1)
        return -1;
    k->wire[0] = 0xFF;
    k->wire[1] = 0xAA;
    k->wire[2] = k->req[2]; /* the register address */
    k->wire[3] = k->req[3];
    k->wire[EMB_LL_WRAP + len] = 0x0D;
    k->wire_len = len + EMB_LL_WRAP + 1;
    return 0;
}

/* Send what is left of the request.  0: it is out (the reply is awaited from now on);
 * 1: the send buffer is full (the rest when the socket is writable); -1 with errno. */
static int emb_ll_push(emb_loop *lp, emb_loop_link *k, int64_t now)
{
    emb_link *lk = k->e->lk;
    ssize_t n;

    while (k->sent < k->wire_len) {
        n = send(k->fd, k->wire + k->sent, (size_t)(k->wire_len - k->sent),
                 MSG_NOSIGNAL | MSG_DONTWAIT);
        if (n > 0) {
            k->sent += (int)n;
            continue;
        }
        if (n == -1 && errno == EINTR)
            continue;
        if (n == -1 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            if (!k->want_out && emb_loop_watch(lp, k->fd, k->slot, 1) == -1)
                return -1;
            k->want_out = 1;
            return 1;
        }
        return -1;
    }
    if (k->want_out && emb_loop_watch(lp, k->fd, k->slot, 0) == -1)
        return -1;
    k->want_out = 0;
    if (lk->wrapped) /* the trace shows the RTU frame inside, as csrc/emb_io.c */
        emb_trace_put(lk, EMB_TRACE_TX, k->wire + EMB_LL_WRAP, k->wire_len - EMB_LL_WRAP - 1);
    else
        emb_trace_put(lk, EMB_TRACE_TX, k->wire, k->wire_len);
    k->start_ns = now;
    k->last_ns = 0;
    k->got = 0;
    k->skipped = 0;
    k->echo_left = lk->echo && !lk->wrapped && !lk->mbap;
    k->state = EMB_LS_AWAIT;
    return 0;
}

/* Begin the read of the pass's next block of device k->which.  0, or -1 with errno. */
static int emb_ll_send(emb_loop *lp, emb_loop_link *k, int64_t now)
{
    emb_engine *e = k->e;
    emb_device *d = e->devices[k->which];
    emb_eblock *b = &d->blocks[d->pass_list[d->index]];

    k->req[0] = (uint8_t)d->slave;
    k->req[1] = b->function;
    k->req[2] = (uint8_t)(b->start >> 8);
    k->req[3] = (uint8_t)(b->start & 0xFF);
    k->req[4] = (uint8_t)(b->count >> 8);
    k->req[5] = (uint8_t)(b->count & 0xFF);
    k->req_len = 6;
    if (emb_ll_frame(k) == -1)
        return -1;
    e->lk->rsp_len = 0;
    emb_fault_sent(e, d);
    k->sent = 0;
    k->start_ns = now; /* the request must be out within the reply timeout */
    k->state = EMB_LS_SEND;
    return emb_ll_push(lp, k, now) == -1 ? -1 : 0;
}

/* Take in what a stream link's socket holds: the bytes read, or -1 with errno. */
static int emb_ll_fill(emb_loop_link *k)
{
    int rc, total = 0;

    while ((rc = emb_stream_fill(k->e->lk, k->fd)) > 0)
        total += rc;
    return rc == -1 ? -1 : total;
}

/* What came while no reply is awaited (idle, sending, settling): a stream link frames it
 * (wrapped reports queued, heartbeats counted, stale bytes dropped), a Modbus TCP link
 * drops it (as its blocking prepare and discard).  The bytes dropped, or -1 with errno;
 * *came: whether bytes came. */
static long emb_ll_absorb(emb_loop_link *k, int *came)
{
    long n;
    int rc;

    if (k->e->lk->mbap) {
        n = emb_discard_input(k->fd, 0, 0, 0);
        *came = n > 0;
        return n;
    }
    rc = emb_ll_fill(k);
    *came = rc > 0;
    return rc == -1 ? -1 : emb_stream_take_idle(k->e->lk);
}

/* Modbus TCP: read a reply into buf (*have bytes of it so far) as far as its header tells,
 * never past its end (what follows stays in the socket, as csrc/emb_rtu.c reads).  Its
 * length when whole, EMB_STREAM_MORE, or -1 with errno (EMBBADDATA, the link's). */
static int emb_ll_mbap_read(int fd, uint8_t *buf, int *have)
{
    ssize_t n;
    int need;

    for (;;) {
        need = emb_reply_length(buf, *have, 1);
        if (need < 0) {
            errno = EMBBADDATA;
            return -1;
        }
        if (*have >= need)
            return need;
        n = emb_read_some(fd, buf + *have, (size_t)(need - *have));
        if (n < 0)
            return -1;
        if (n == 0)
            return EMB_STREAM_MORE;
        *have += (int)n;
    }
}

/* What the reply awaited must be (a wrapped link's receiver picks it by these). */
static void emb_ll_want(const emb_loop_link *k, emb_want *w)
{
    const emb_device *d = k->e->devices[k->which];
    const emb_eblock *b = &d->blocks[d->pass_list[d->index]];

    w->slave = d->slave;
    w->function = b->function;
    w->address = b->start;
    w->count = b->function <= 2 ? (b->count + 7) / 8 : 2 * b->count;
}

/* Frame the reply awaited from what the socket holds: its length in e->rsp (whole,
 * integrity checked), 0 for a frame that answers nothing (another slave's, or a Modbus TCP
 * reply to another transaction id: skipped), EMB_STREAM_MORE, or -1 with errno.  *got:
 * the bytes taken. */
static int emb_ll_take(emb_loop_link *k, int64_t now, int *got)
{
    emb_engine *e = k->e;
    emb_link *lk = e->lk;
    emb_want want;
    int rc, before = k->got;

    *got = 0;
    if (lk->mbap) {
        rc = emb_ll_mbap_read(k->fd, e->rsp, &k->got);
        if (k->got > before)
            k->last_ns = now;
        *got = k->got;
        if (rc < 0)
            return rc;
        k->got = 0;
        if (emb_check_mbap(e->rsp, rc, (long)lk->tid) != EMB_ETID)
            return rc;
        emb_trace_put(lk, EMB_TRACE_RX, e->rsp, rc);
        lk->discarded += rc; /* ours is awaited for the rest of the response timeout */
        k->skipped++;
        *got = 0;
        return 0;
    }
    rc = emb_ll_fill(k);
    if (rc == -1)
        return -1;
    if (rc > 0)
        k->last_ns = now;
    if (lk->wrapped) { /* the frames besides the reply are queued as reports */
        emb_ll_want(k, &want);
        rc = emb_wrapped_backend.recv(lk, k->fd, &want, 0, 0, e->rsp, got);
        return rc == -1 && errno == ETIMEDOUT ? EMB_STREAM_MORE : rc;
    }
    if (k->echo_left) {
        if (emb_stream_backend.skip_echo(lk, k->fd, k->wire, k->wire_len, 0, 0) == -1)
            return errno == ETIMEDOUT || errno == EMB_EPARTIAL ? EMB_STREAM_MORE : -1;
        k->echo_left = 0;
        k->start_ns = now; /* the reply's own timeout from here on, as csrc/emb_io.c */
        k->last_ns = 0;
    }
    return emb_stream_try(lk, e->devices[k->which]->slave, e->rsp, got);
}

/* Bytes of a reply received and not framed yet (heartbeats aside). */
static int emb_ll_pending(emb_loop_link *k)
{
    return k->e->lk->mbap ? k->got : emb_stream_backend.pending(k->e->lk, k->fd);
}

/* The reply's deadline: the response timeout until bytes of it came, then the byte
 * timeout from the last ones (as the blocking receivers; a wrapped reply: the response
 * timeout, as csrc/emb_stream.c emb_wrapped_recv). */
static int64_t emb_ll_reply_due(emb_loop_link *k)
{
    const emb_device *d = k->e->devices[k->which];
    emb_link *lk = k->e->lk;

    if (!lk->wrapped && k->last_ns && k->byte_ms > 0 && emb_ll_pending(k) > 0)
        return k->last_ns + (int64_t)k->byte_ms * 1000000; /* heartbeats do not count */
    return k->start_ns + (int64_t)d->timeout_ms * 1000000;
}

/* Frame a second frame behind the reply into k->next, as emb_ll_take frames the reply
 * (a Modbus TCP one read as far as its header tells, k->got2 bytes so far; one with
 * another transaction id answers nothing: 0). */
static int emb_ll_take_next(emb_loop_link *k, int64_t now, int *got)
{
    emb_link *lk = k->e->lk;
    int rc, before = k->got2;

    *got = 0;
    if (lk->mbap) {
        rc = emb_ll_mbap_read(k->fd, k->next, &k->got2);
        if (k->got2 > before)
            k->last_ns = now;
        *got = k->got2;
        return rc > 0 && emb_check_mbap(k->next, rc, (long)lk->tid) != 0 ? 0 : rc;
    }
    rc = emb_ll_fill(k);
    if (rc == -1)
        return -1;
    if (rc > 0)
        k->last_ns = now;
    return emb_stream_try(lk, k->e->devices[k->which]->slave, k->next, got);
}

/* The last answer wins, as in the blocking receive (csrc/emb_io.c: a DTU that held a
 * late reply sends it with the next one; a Modbus TCP peer that repeats a reply): a
 * frame behind the reply (k->first_len bytes in e->rsp) that answers the request
 * replaces it; one still arriving (at least a header's worth came) is waited for up to
 * the byte timeout from its last bytes (EMB_LS_NEXT), then given up (its bytes are stale
 * before the next request).  Wrapped links take the first answer (the frames behind it
 * are reports).  1 while it waits (its deadline set), else 0: the reply is decided
 * (k->first_len bytes in e->rsp). */
static int emb_ll_last_answer(emb_loop *lp, emb_loop_link *k, int64_t now)
{
    emb_engine *e = k->e;
    emb_link *lk = e->lk;
    int len2, got2 = 0, exc = -1, err, h = emb_ll_header(lk);
    int64_t until;

    if (k->state != EMB_LS_NEXT) {
        if (lk->wrapped || (lk->mbap ? emb_pending(k->fd) < EMB_MBAP + 2
                                     : emb_ll_pending(k) < 5))
            return 0;
        k->got2 = 0;
        k->last_ns = now;
    }
    len2 = emb_ll_take_next(k, now, &got2);
    err = errno;
    if (len2 == EMB_STREAM_MORE) {
        until = k->last_ns + (int64_t)k->byte_ms * 1000000;
        if (now < until) {
            k->state = EMB_LS_NEXT;
            emb_timer_set(lp, k->slot, until);
            return 1;
        }
        k->state = EMB_LS_AWAIT; /* it stopped short */
        if (lk->mbap) {
            emb_trace_put(lk, EMB_TRACE_RX, k->next, got2);
            lk->discarded += got2;
        }
        return 0;
    }
    k->state = EMB_LS_AWAIT;
    emb_trace_put(lk, EMB_TRACE_RX, k->next, len2 > 0 ? len2 : got2);
    if (len2 > 0 && emb_check_reply(k->req, k->req_len, k->next + h - 1,
                                    len2 - (h - 1) - emb_ll_trailer(lk), &exc) == 0) {
        lk->discarded += k->first_len;
        memcpy(e->rsp, k->next, (size_t)len2);
        k->first_len = len2;
        return 0;
    }
    if (len2 >= 0 || lk->mbap || err != EMBBADDATA) /* a stream's bad bytes stay in rx */
        lk->discarded += len2 > 0 ? len2 : got2;
    return 0;
}

/* A whole reply frame (len bytes in e->rsp, its CRC checked): checked against the
 * request and decoded.  0: read (the pass goes on), else the errno of its failure. */
static int emb_ll_reply(emb_loop_link *k, int len, int64_t now)
{
    emb_engine *e = k->e;
    emb_link *lk = e->lk;
    emb_device *d = e->devices[k->which];
    emb_eblock *b = &d->blocks[d->pass_list[d->index]];
    void *data = b->data ? b->data : (b->function <= 2 ? (void *)e->bits : (void *)e->regs);
    int h = emb_ll_header(lk);
    const uint8_t *p = e->rsp + h + 2;
    int exc = -1, err, i;

    lk->rsp_len = len;
    err = lk->mbap ? emb_check_mbap(e->rsp, len, (long)lk->tid) : 0;
    if (!err)
        err = emb_check_reply(k->req, k->req_len, e->rsp + h - 1,
                              len - (h - 1) - emb_ll_trailer(lk), &exc);
    if (!err && exc >= 0)
        err = EMB_EEXCEPTION + exc;
    if (err)
        return err;
    if (b->function <= 2) {
        for (i = 0; i < b->count; i++) /* first bit in the low bit (6.1) */
            ((uint8_t *)data)[i] = (uint8_t)((p[i / 8] >> (i % 8)) & 1);
    } else {
        for (i = 0; i < b->count; i++) /* big-endian registers (4.2) */
            ((uint16_t *)data)[i] = (uint16_t)((p[2 * i] << 8) | p[2 * i + 1]);
    }
    emb_fault_took(e);
    if (e->pace_ns)
        e->ready_ns = now + e->pace_ns;
    emb_fault_answered(e, d, b, b->count, data, k->start_ns, k->tries < k->first);
    k->state = EMB_LS_IDLE;
    return 0;
}

/* The read failed with err: a link error ends here (EMB_LS_FAILED); else the line is
 * cleaned first (EMB_LS_SETTLE) or at once. */
static void emb_ll_failed(emb_loop_link *k, int err, int64_t now)
{
    emb_engine *e = k->e;

    emb_fault_took(e);
    if (e->pace_ns)
        e->ready_ns = now + e->pace_ns;
    k->err = err;
    k->kind = emb_fault_kind(err, &k->code);
    if (k->kind == EMB_K_LINK) {
        e->event_errno = err;
        k->state = EMB_LS_FAILED;
        return;
    }
    k->clean_total_ms = 0;
    k->clean_limit_ms = 0;
    switch (emb_fault_clean_of(e, k->kind)) {
    case EMB_CLEAN_SETTLE:
        k->clean_total_ms = e->settle_ms;
        k->clean_limit_ms = e->settle_limit_ms;
        break;
    case EMB_CLEAN_DRAIN:
        k->clean_total_ms = e->quiet_ms;
        k->clean_limit_ms = e->drain_limit_ms;
        break;
    default:
        break;
    }
    k->start_ns = now;
    k->last_ns = 0;
    k->dropped = 0;
    k->state = EMB_LS_SETTLE;
}

/* The link failed outside a read (err): EMB_LS_FAILED. */
static void emb_ll_lost(emb_loop_link *k, int err)
{
    k->e->event_errno = err;
    k->state = EMB_LS_FAILED;
}

/* List device `which`'s ended pass for Python when it has news (as the blocking
 * engine's emb_ended).  1 if listed. */
static int emb_ll_ended(emb_engine *e, emb_device *d, int which, int64_t now)
{
    if (!(d->news || d->notify || now >= d->notify_ns || d->status_ev || d->fail_news))
        return 0;
    if (!d->ended) {
        d->ended = 1;
        e->ended_list[e->n_ended++] = (uint32_t)which;
    }
    return 1;
}

/* A failed reply on a plain RTU link without the echo option that begins with the
 * request's own bytes: EMB_EECHOSEEN (the line echoes: set the echo option), as the
 * blocking exchange says it (csrc/emb_io.c emb_echo_seen); else err. */
static int emb_ll_echo_seen(const emb_loop_link *k, int err, int got)
{
    const emb_link *lk = k->e->lk;

    if (lk->echo || lk->wrapped || lk->mbap || err == ETIMEDOUT)
        return err;
    return emb_echo_seen(err, k->e->rsp, got, k->wire, k->wire_len);
}

/* The reply decided (k->first_len bytes in e->rsp): checked and decoded, or failed. */
static void emb_ll_answered(emb_loop_link *k, int64_t now)
{
    int err = emb_ll_reply(k, k->first_len, now);

    if (err)
        emb_ll_failed(k, emb_ll_echo_seen(k, err, k->e->lk->rsp_len), now);
}

/* The awaited reply: framed, checked and decoded, or failed (the reply timeout, a bad
 * frame, the link).  0: the state moved on; 1: it waits (its deadline is set). */
static int emb_ll_await(emb_loop *lp, emb_loop_link *k, int64_t now)
{
    emb_engine *e = k->e;
    emb_link *lk = e->lk;
    int64_t until;
    int rc, got, err;

    rc = emb_ll_take(k, now, &got);
    if (rc == 0) { /* another slave's frame (a skipped Modbus TCP reply is counted) */
        if (!lk->mbap) {
            emb_trace_put(lk, EMB_TRACE_RX, e->rsp, got);
            lk->discarded += got;
        }
        return 0;
    }
    if (rc == -1) {
        err = errno;
        emb_trace_put(lk, EMB_TRACE_RX, e->rsp, got); /* what came, if anything */
        lk->rsp_len = 0; /* no whole frame to show, as csrc/emb_io.c leaves it */
        emb_ll_failed(k, emb_ll_echo_seen(k, err, got), now);
        return 0;
    }
    if (rc > 0) {
        emb_trace_put(lk, EMB_TRACE_RX, e->rsp, rc);
        k->first_len = rc;
        if (emb_ll_last_answer(lp, k, now))
            return 1;
        emb_ll_answered(k, now);
        return 0;
    }
    until = emb_ll_reply_due(k);
    if (now < until) {
        emb_timer_set(lp, k->slot, until);
        return 1;
    }
    lk->rsp_len = 0;
    err = !lk->wrapped && emb_ll_pending(k) > 0 ? EMB_EPARTIAL : ETIMEDOUT;
    if (err == ETIMEDOUT && k->skipped)
        err = EMB_ETID; /* only replies to other requests came */
    emb_ll_failed(k, err, now);
    return 0;
}

/* Run link k as far as it goes now.  0: it waits (its deadline is set, or none when no
 * device is polled); EMB_EV_CYCLE: passes ended with news (e->ended_list); EMB_EV_SPLIT:
 * exception 02 on a splittable block of device e->event_device; EMB_EV_REPORTS: a wrapped
 * link took reports (e->event_device: the device whose read took them, -1: taken while
 * idle), which Python takes before it runs the link again; EMB_EV_FAILED: the link
 * failed (e->event_errno).  Python acts, then runs the link again. */
int emb_loop_link_run(emb_loop *lp, emb_loop_link *k)
{
    emb_engine *e = k->e;
    emb_device *d;
    int64_t now, until;
    long n;
    int rc, came;

    e->event_device = -1;
    for (;;) {
        now = emb_now_ns();
        switch (k->state) {
        case EMB_LS_IDLE:
            if ((n = emb_ll_absorb(k, &came)) == -1) {
                emb_ll_lost(k, errno);
                break;
            }
            e->lc->discarded += n;
            emb_fault_took(e);
            if (emb_engine_reports(e, k->which))
                return EMB_EV_REPORTS;
            if (k->which >= 0) {
                d = e->devices[k->which];
                if (d->index >= d->n_pass) {
                    emb_dev_end_pass(d, now, e->bounds_ns, e->n_bounds);
                    emb_fault_end_pass(d, now);
                    rc = k->which;
                    k->which = -1;
                    if (emb_ll_ended(e, d, rc, now))
                        return EMB_EV_CYCLE;
                    break;
                }
                if (e->ready_ns > now) {
                    emb_timer_set(lp, k->slot, e->ready_ns);
                    return 0;
                }
                if (!k->retrying)
                    k->first = k->tries = emb_fault_tries(d);
                k->retrying = 0;
                if (emb_ll_send(lp, k, now) == -1)
                    emb_ll_lost(k, errno);
                break;
            }
            d = emb_engine_pick(e, &k->which);
            if (d == NULL) {
                k->which = -1;
                emb_timer_clear(lp, k->slot);
                return 0;
            }
            if (d->due_ns > now) {
                k->which = -1;
                emb_timer_set(lp, k->slot, d->due_ns);
                return 0;
            }
            if (!d->in_pass && emb_dev_begin_pass(d, now) == 0 && d->n_blocks > 0)
                k->which = -1; /* nothing due yet: pick again */
            break;
        case EMB_LS_SEND: /* what comes before the request is out is stale */
            if ((n = emb_ll_absorb(k, &came)) == -1 || (rc = emb_ll_push(lp, k, now)) == -1) {
                emb_ll_lost(k, errno);
                break;
            }
            e->lc->discarded += n;
            if (rc == 0)
                break;
            until = k->start_ns + (int64_t)e->devices[k->which]->timeout_ms * 1000000;
            if (now < until) {
                emb_timer_set(lp, k->slot, until);
                return 0;
            }
            emb_ll_lost(k, ETIMEDOUT); /* the peer took no byte within the reply timeout */
            break;
        case EMB_LS_AWAIT:
            if (emb_ll_await(lp, k, now))
                return 0;
            break;
        case EMB_LS_NEXT:
            if (emb_ll_last_answer(lp, k, now))
                return 0;
            emb_ll_answered(k, now);
            break;
        case EMB_LS_SETTLE:
            n = emb_ll_absorb(k, &came);
            if (n == -1) {
                e->event_errno = errno;
                emb_fault_count(e, e->devices[k->which], k->kind, k->code);
                k->state = EMB_LS_FAILED;
                break;
            }
            k->dropped += n;
            if (came)
                k->last_ns = now;
            until = emb_settle_until(k->start_ns, k->last_ns, k->clean_total_ms,
                                     e->quiet_ms, k->clean_limit_ms);
            if (now < until) {
                emb_timer_set(lp, k->slot, until);
                return 0;
            }
            emb_fault_cleaned(e, k->dropped);
            d = e->devices[k->which];
            emb_fault_count(e, d, k->kind, k->code);
            rc = emb_fault_failed(e, d, &d->blocks[d->pass_list[d->index]], k->kind,
                                  k->code, k->err, &k->tries);
            k->state = EMB_LS_IDLE;
            if (rc == EMB_FAULT_RETRY) {
                k->retrying = 1; /* the same block again, when paced */
                break;
            }
            if (rc == EMB_EV_SPLIT) {
                e->event_device = k->which;
                emb_timer_clear(lp, k->slot);
                return EMB_EV_SPLIT;
            }
            break;
        default: /* EMB_LS_FAILED */
            e->event_device = k->which;
            emb_timer_clear(lp, k->slot);
            return EMB_EV_FAILED;
        }
    }
}
