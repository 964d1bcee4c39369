/* edgemodbus: one link of the loop engine as a state machine (see emb_loop_link.h).
 *
 * emb_loop_link_run() takes the link as far as it goes without waiting: it takes in what
 * the socket holds and frames the reply (csrc/emb_loop_io.c, each link kind as the
 * blocking engine's backends frame it), checks and decodes it, runs the fault policy's
 * pure steps (csrc/emb_fault.c) and the device passes (csrc/emb_engine.c's
 * emb_dev_begin_pass / emb_dev_end_pass), sends the next request, and sets the link's
 * one deadline on the loop's heap for what it waits for next.  A wrapped link's reports
 * go to Python as the blocking engine hands them (emb_engine_reports).  A late reply
 * during a settle is dropped (RTU frames carry no transaction id: Modbus over Serial
 * Line v1.02, 2.5.1.1). */
#include "emb_loop_link.h"

#include <errno.h>

#include "emb_check.h"
#include "emb_engine.h"
#include "emb_io.h" /* emb_trace_put */

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
    k->owed = 0; /* this read pays for the job that ran before it */
    k->sent = 0;
    k->start_ns = now; /* the request must be out within the reply timeout */
    k->state = EMB_LS_SEND;
    return emb_ll_push(lp, k, now) == -1 ? -1 : 0;
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
 * idle), which Python takes before it runs the link again; EMB_EV_WAKE: the link is
 * idle and k->jobs is set (Python runs a job; with k->owed set, only once the link sent
 * its next due read, or nothing is due: one job between two reads while polling is
 * due, as csrc/emb_engine.c keeps it); EMB_EV_FAILED: the link
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
                if (k->jobs && !k->owed)
                    return EMB_EV_WAKE; /* a job between two blocks of the pass */
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
            if (k->jobs && !k->owed)
                return EMB_EV_WAKE; /* Python runs the link's jobs while it is idle */
            d = emb_engine_pick(e, &k->which);
            if (d == NULL || d->due_ns > now) {
                k->which = -1;
                if (k->jobs) { /* nothing due: the jobs may have the link */
                    k->owed = 0;
                    return EMB_EV_WAKE;
                }
                if (d == NULL)
                    emb_timer_clear(lp, k->slot);
                else
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
