/* edgemodbus: one link of the loop engine as a state machine (see emb_loop_link.h).
 *
 * emb_loop_link_run() takes the link as far as it goes without waiting: it reads what
 * the socket holds, frames and checks a reply, runs the fault policy's pure steps
 * (csrc/emb_fault.c) and the device passes (csrc/emb_engine.c's emb_dev_begin_pass /
 * emb_dev_end_pass), sends the next request, and sets the link's one deadline on the
 * loop's heap for what it waits for next.  A late reply during a settle is dropped
 * (RTU frames carry no transaction id: Modbus over Serial Line v1.02, 2.5.1.1). */
#include "emb_loop_link.h"

#include <errno.h>
#include <string.h>
#include <sys/socket.h>

#include "emb_check.h"
#include "emb_engine.h"
#include "emb_rtu.h"
#include "emb_stream.h"

/* Send the read of the pass's next block of device k->which.  0, or -1 with errno. */
static int emb_ll_send(emb_loop_link *k, int64_t now)
{
    emb_engine *e = k->e;
    emb_device *d = e->devices[k->which];
    emb_eblock *b = &d->blocks[d->pass_list[d->index]];
    uint8_t frame[EMB_MAX_RTU];
    int len = 0;
    ssize_t n;

    k->req[0] = (uint8_t)d->slave;
    k->req[1] = b->function;
    k->req[2] = (uint8_t)(b->start >> 8);
    k->req[3] = (uint8_t)(b->start & 0xFF);
    k->req[4] = (uint8_t)(b->count >> 8);
    k->req[5] = (uint8_t)(b->count & 0xFF);
    k->req_len = 6;
    if (emb_rtu_frame(d->slave, k->req + 1, 5, frame, &len) == -1)
        return -1;
    e->lk->rsp_len = 0;
    emb_fault_sent(e, d);
    n = send(k->fd, frame, (size_t)len, MSG_NOSIGNAL);
    if (n != len) { /* 8 bytes on a link whose send buffer is full: the DTU is gone */
        if (n >= 0)
            errno = EAGAIN;
        return -1;
    }
    k->start_ns = now;
    k->last_ns = 0;
    k->state = EMB_LS_AWAIT;
    return 0;
}

/* Take in what the socket holds: the bytes read, or -1 with errno (the link failed). */
static int emb_ll_fill(emb_loop_link *k)
{
    int rc, total = 0;

    while ((rc = emb_stream_fill(k->e->lk, k->fd)) > 0)
        total += rc;
    return rc == -1 ? -1 : total;
}

/* The reply's deadline: the response timeout until bytes of it came, then the byte
 * timeout from the last ones (as the blocking receive, csrc/emb_stream.c). */
static int64_t emb_ll_reply_due(const emb_loop_link *k)
{
    const emb_device *d = k->e->devices[k->which];

    if (k->last_ns && k->byte_ms > 0 && emb_stream_backend.pending(k->e->lk, k->fd) > 0)
        return k->last_ns + (int64_t)k->byte_ms * 1000000; /* heartbeats do not count */
    return k->start_ns + (int64_t)d->timeout_ms * 1000000;
}

/* Another whole frame already behind the reply (len bytes in e->rsp) that answers the
 * request replaces it: the last answer wins, as in the blocking receive (csrc/emb_io.c:
 * a DTU that held a late reply sends it with the next one).  A second frame still on
 * its way is not waited for: its bytes are dropped as stale before the next request.
 * The reply's length. */
static int emb_ll_last_answer(emb_loop_link *k, int len)
{
    emb_engine *e = k->e;
    uint8_t next[EMB_MAX_ADU];
    int len2, got2 = 0, exc = -1;

    if (emb_stream_backend.pending(e->lk, k->fd) < emb_stream_backend.min_next)
        return len;
    len2 = emb_stream_try(e->lk, e->devices[k->which]->slave, next, &got2);
    if (len2 > 0 && emb_check_reply(k->req, k->req_len, next, len2 - 2, &exc) == 0) {
        e->lk->discarded += len;
        memcpy(e->rsp, next, (size_t)len2);
        return len2;
    }
    if (len2 > 0 || len2 == 0 || (len2 == -1 && errno != EMBBADDATA))
        e->lk->discarded += len2 > 0 ? len2 : got2; /* taken from rx: counted here */
    return len;
}

/* A whole reply frame (len bytes in e->rsp, its CRC checked): checked against the
 * request and decoded.  0: read (the pass goes on), else the errno of its failure. */
static int emb_ll_reply(emb_loop_link *k, int len, int64_t now)
{
    emb_engine *e = k->e;
    emb_device *d = e->devices[k->which];
    emb_eblock *b = &d->blocks[d->pass_list[d->index]];
    void *data = b->data ? b->data : (b->function <= 2 ? (void *)e->bits : (void *)e->regs);
    const uint8_t *p = e->rsp + 3;
    int exc = -1, err, i;

    e->lk->rsp_len = len;
    err = emb_check_reply(k->req, k->req_len, e->rsp, len - 2, &exc);
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

/* Run link k as far as it goes now.  0: it waits (its deadline is set, or none when no
 * device is polled); EMB_EV_CYCLE: passes ended with news (e->ended_list); EMB_EV_SPLIT:
 * exception 02 on a splittable block of device e->event_device; EMB_EV_FAILED: the link
 * failed (e->event_errno).  Python acts, then runs the link again. */
int emb_loop_link_run(emb_loop *lp, emb_loop_link *k)
{
    emb_engine *e = k->e;
    emb_device *d;
    int64_t now, until;
    long n;
    int rc, got;

    e->event_device = -1;
    for (;;) {
        now = emb_now_ns();
        switch (k->state) {
        case EMB_LS_IDLE:
            if (emb_ll_fill(k) == -1 || (n = emb_stream_take_idle(e->lk)) == -1) {
                e->event_errno = errno;
                k->state = EMB_LS_FAILED;
                break;
            }
            e->lc->discarded += n;
            emb_fault_took(e);
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
                if (emb_ll_send(k, now) == -1) {
                    e->event_errno = errno;
                    k->state = EMB_LS_FAILED;
                }
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
        case EMB_LS_AWAIT:
            rc = emb_ll_fill(k);
            if (rc == -1) {
                emb_ll_failed(k, errno, now);
                break;
            }
            if (rc > 0)
                k->last_ns = now;
            rc = emb_stream_try(e->lk, e->devices[k->which]->slave, e->rsp, &got);
            if (rc == 0) { /* another slave's frame */
                e->lk->discarded += got;
                break;
            }
            if (rc == -1) {
                e->lk->rsp_len = got;
                emb_ll_failed(k, errno, now);
                break;
            }
            if (rc > 0) {
                rc = emb_ll_reply(k, emb_ll_last_answer(k, rc), now);
                if (rc)
                    emb_ll_failed(k, rc, now);
                break;
            }
            until = emb_ll_reply_due(k);
            if (now < until) {
                emb_timer_set(lp, k->slot, until);
                return 0;
            }
            e->lk->rsp_len = 0;
            emb_ll_failed(k, emb_stream_backend.pending(e->lk, k->fd) > 0 ? EMB_EPARTIAL
                                                                           : ETIMEDOUT, now);
            break;
        case EMB_LS_SETTLE:
            rc = emb_ll_fill(k);
            n = rc == -1 ? -1 : emb_stream_take_idle(e->lk);
            if (n == -1) {
                e->event_errno = errno;
                emb_fault_count(e, e->devices[k->which], k->kind, k->code);
                k->state = EMB_LS_FAILED;
                break;
            }
            if (n > 0) {
                k->dropped += n;
                k->last_ns = now;
            }
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
