/* edgemodbus: the line engine (see emb_engine.h).
 *
 * Polling, faults included, kept in C so that a line re-enters Python at most once per
 * round of passes that has news, not once per request or per device: on a line whose
 * values do not change, its devices cost no Python at all between the caller's
 * deadlines.  The fault policy runs beside the read (csrc/emb_fault.c); Python is told
 * its outcomes (a block's failure, a status change, a block to split).  Devices whose
 * pass ended with news are listed (ended_list) and handed over together, once nothing
 * more is due or before such a device begins its next pass.  Every link kind runs here,
 * DTU streams too (their heartbeats are skipped in C and counted live; the wrapped
 * reports a read took, or that came while the link was idle, are applied in C to the
 * devices' block decoders, csrc/emb_report.c, and taken by Python with the pass's
 * changes; those C cannot apply come back to Python, EMB_EV_REPORTS / EMB_EV_INPUT). */
#define _GNU_SOURCE /* ppoll */
#include "emb_engine.h"

#include <string.h>

#include <errno.h>
#include <poll.h>
#include <time.h>

#include "emb_report.h"

/* A block due this soon (at most a tenth of its period, and EMB_JOIN_NS) is read in the
 * pass that begins now: blocks whose rates are multiples of each other stay in step. */
static int emb_is_due(const emb_eblock *b, int64_t now_ns)
{
    int64_t join = b->period_ns / 10;

    if (join > EMB_JOIN_NS)
        join = EMB_JOIN_NS;
    return b->due_ns - now_ns <= join;
}

static int64_t emb_next_due(const emb_device *d)
{
    int64_t due = EMB_NEVER;
    uint32_t i;

    for (i = 0; i < d->n_blocks; i++)
        if (d->blocks[i].due_ns < due)
            due = d->blocks[i].due_ns;
    return due;
}

/* Begin a pass at now_ns: list the blocks due, in plan order.  Returns how many; 0 with
 * blocks means none is due yet (the device's due time moves to the first block's). */
uint32_t emb_dev_begin_pass(emb_device *d, int64_t now_ns)
{
    uint32_t i, n = 0;

    for (i = 0; i < d->n_blocks; i++)
        if (emb_is_due(&d->blocks[i], now_ns))
            d->pass_list[n++] = i;
    d->n_pass = n;
    d->index = 0;
    d->taken = 0;
    d->news = 0;
    d->timed_out = 0;
    d->answered = 0;
    if (n == 0 && d->n_blocks > 0) {
        d->due_ns = emb_next_due(d);
        return 0;
    }
    d->in_pass = 1;
    d->pass_start_ns = now_ns;
    d->due_ns = now_ns;
    d->passes++;
    return n;
}

/* End the pass under way at now_ns: count it (time, histogram over bounds_ns) and set
 * the next due time of its blocks, one period after the pass began, or now when the
 * pass took longer than a block's period (no burst of catch-up reads).  The pass list
 * stays readable until the next pass begins.  Returns 1 if a block overran (counted). */
int emb_dev_end_pass(emb_device *d, int64_t now_ns, const int64_t *bounds_ns,
                     uint32_t n_bounds)
{
    int64_t elapsed = now_ns - d->pass_start_ns;
    emb_dev_counters *c = &d->c;
    uint32_t i, k = 0;
    int overran = 0;

    c->cycles++;
    c->last_cycle_ns = elapsed;
    c->total_cycle_ns += elapsed;
    if (elapsed > c->max_cycle_ns)
        c->max_cycle_ns = elapsed;
    while (k < n_bounds && k + 1 < EMB_HIST_MAX && elapsed > bounds_ns[k])
        k++;
    c->hist[k]++;
    d->in_pass = 0;
    d->index = 0;
    if (d->n_blocks == 0) {
        if (elapsed > d->cycle_ns) {
            overran = 1;
            d->due_ns = now_ns;
        } else {
            d->due_ns = d->cycle_ns ? d->pass_start_ns + d->cycle_ns : EMB_NEVER;
        }
    } else {
        for (i = 0; i < d->n_pass; i++) {
            emb_eblock *b = &d->blocks[d->pass_list[i]];

            if (elapsed > b->period_ns) {
                overran = 1;
                b->due_ns = now_ns;
            } else {
                b->due_ns = d->pass_start_ns + b->period_ns;
            }
        }
        d->due_ns = emb_next_due(d);
    }
    if (overran)
        c->overruns++;
    return overran;
}

/* Every block due at at_ns, as a new pass (a start, a new plan, a new link, a probe). */
void emb_dev_all_due(emb_device *d, int64_t at_ns)
{
    uint32_t i;

    for (i = 0; i < d->n_blocks; i++)
        d->blocks[i].due_ns = at_ns;
    d->in_pass = 0;
    d->index = 0;
    d->taken = 0;
    d->n_pass = 0;
    d->due_ns = (d->n_blocks || d->cycle_ns) ? at_ns : EMB_NEVER;
}

/* Block `at` becomes the k blocks Python planned (an exception 02 bisection) in
 * blocks[at..at+k), an array of n_blocks + k - 1 whose other entries this fills from the
 * old one; pass_list: room for as many.  The halves inherit the block's due time and
 * place in the pass under way, which goes on with the first of them.  0, or -1 (EINVAL). */
int emb_dev_split(emb_device *d, emb_eblock *blocks, uint32_t *pass_list, uint32_t at,
                  uint32_t k)
{
    uint32_t i, j, n = 0;

    if (at >= d->n_blocks || k < 1) {
        errno = EINVAL;
        return -1;
    }
    for (j = 0; j < k; j++) {
        blocks[at + j].due_ns = d->blocks[at].due_ns;
        blocks[at + j].read_ns = 0;
        blocks[at + j].reported = 0;
        blocks[at + j].fail_kind = EMB_FAIL_NONE;
        blocks[at + j].fail_new = blocks[at + j].fail_known = 0;
    }
    memcpy(blocks, d->blocks, at * sizeof *blocks);
    memcpy(blocks + at + k, d->blocks + at + 1, (d->n_blocks - at - 1) * sizeof *blocks);
    for (i = 0; i < d->n_pass; i++) {
        uint32_t b = d->pass_list[i];

        if (b < at)
            pass_list[n++] = b;
        else if (b == at)
            for (j = 0; j < k; j++)
                pass_list[n++] = at + j;
        else
            pass_list[n++] = b + k - 1;
    }
    for (i = j = 0; i < d->n_rep; i++) { /* the blocks holding a report, renumbered */
        uint32_t b = d->rep_list[i];

        if (b != at) /* (Python takes the reports before it splits: never the block) */
            d->rep_list[j++] = b < at ? b : b + k - 1;
    }
    d->n_rep = j;
    d->blocks = blocks;
    d->pass_list = pass_list;
    d->n_blocks += k - 1;
    d->n_pass = n;
    return 0;
}

/* A DTU stream's read left wrapped reports, dropped frames or lost reports. */
static int emb_has_reports(const emb_link *lk)
{
    return lk->n_reports > 0 || lk->dropped > 0 || lk->reports_lost > 0;
}

/* After a read of device `which` (-1: none, the link was idle): EMB_EV_REPORTS when the
 * DTU stream took what only Python handles (wrapped reports, applied in the order they
 * came around the reply; dropped frames or lost reports, logged), event_device set;
 * else 0.  The loop's links hand reports over with it (csrc/emb_loop_link.c); the
 * blocking engine first applies in C what it can (emb_take_reports). */
int emb_engine_reports(emb_engine *e, int which)
{
    if (!emb_has_reports(e->lk))
        return 0;
    e->event_device = which;
    return EMB_EV_REPORTS;
}

/* The frame trace is due for Python: a quarter of the ring used, or its oldest frame
 * EMB_TRACE_FLUSH_NS old (a frame reaches the log that soon, and a line with the trace
 * on comes back to Python once per several passes, not after each). */
static int emb_trace_due(const emb_trace *t, int64_t now_ns)
{
    return t && t->n > 0 &&
           (t->used >= EMB_TRACE_SIZE / 4 || now_ns - t->first_ns >= EMB_TRACE_FLUSH_NS);
}

static int emb_woken(emb_engine *e)
{
    return __atomic_load_n(e->wake, __ATOMIC_ACQUIRE) != 0;
}

/* Sleep until until_ns, watching the wake fd (unless a read is owed: see emb_engine_run)
 * and watch_fd when idle: an EMB_EV_* event, or -1 when the time came. */
static int emb_sleep(emb_engine *e, int64_t until_ns, int idle)
{
    struct pollfd pfd[2];
    struct timespec ts;
    int64_t left;
    nfds_t n = 0;
    int rc;

    pfd[0].fd = e->owed ? -1 : e->wake_fd;
    pfd[0].events = POLLIN;
    pfd[1].fd = idle ? e->watch_fd : -1;
    pfd[1].events = POLLIN;
    n = pfd[1].fd >= 0 ? 2 : 1;
    for (;;) {
        if (!e->owed && emb_woken(e))
            return EMB_EV_WAKE;
        left = until_ns - emb_now_ns();
        if (left <= 0)
            return -1;
        ts.tv_sec = (time_t)(left / 1000000000LL);
        ts.tv_nsec = (long)(left % 1000000000LL);
        pfd[0].revents = 0;
        pfd[1].revents = 0;
        rc = ppoll(pfd, n, &ts, NULL);
        if (rc == -1) {
            if (errno == EINTR)
                continue;
            e->event_errno = errno;
            return EMB_EV_ERROR;
        }
        if (rc == 0)
            continue; /* the time came: checked at the top */
        if (pfd[0].revents)
            return EMB_EV_WAKE;
        if (pfd[1].revents)
            return EMB_EV_INPUT;
    }
}

/* The device due first (active, polled), or NULL when none is polled; *which: its
 * index.  The blocking engine and the loop's links (emb_loop_link.c) pick alike. */
emb_device *emb_engine_pick(const emb_engine *e, int *which)
{
    emb_device *best = NULL;
    uint32_t i;

    for (i = 0; i < e->n_devices; i++) {
        emb_device *d = e->devices[i];

        if (d->active && d->due_ns != EMB_NEVER && (!best || d->due_ns < best->due_ns)) {
            best = d;
            *which = (int)i;
        }
    }
    return best;
}

/* Read and decode the pass's next block with the fault policy: 0 (the pass goes on), or
 * an EMB_EV_* for Python (csrc/emb_fault.c). */
static int emb_step(emb_engine *e, emb_device *d, int64_t until_ns)
{
    emb_eblock *b = &d->blocks[d->pass_list[d->index]];
    void *data = b->data ? b->data : (b->function <= 2 ? (void *)e->bits : (void *)e->regs);

    return emb_fault_read(e, d, b, data, until_ns);
}

/* A pass of d (device `which`) that Python must see ended: list it.  The list goes to
 * Python before the next pass of a device in it (a round), or rather than let the line
 * idle longer than a tenth of a listed device's cycle (at most EMB_HANDOVER_NS, at least
 * EMB_JOIN_NS), or EMB_LATEST_NS after the first pass listed (a line busy with passes
 * without news): the passes of the devices of a round join it, and news waits at most
 * one cycle of its device (its next pass) and EMB_LATEST_NS. */
static void emb_ended(emb_engine *e, emb_device *d, int which)
{
    int64_t idle = d->cycle_ns / 10, now = emb_now_ns();

    if (d->ended)
        return;
    d->ended = 1;
    if (idle > EMB_HANDOVER_NS)
        idle = EMB_HANDOVER_NS;
    if (idle < EMB_JOIN_NS)
        idle = EMB_JOIN_NS;
    if (e->n_ended == 0 || idle < e->idle_ns)
        e->idle_ns = idle;
    if (e->n_ended == 0)
        e->latest_ns = now + EMB_LATEST_NS;
    e->ended_list[e->n_ended++] = (uint32_t)which;
}

/* The reports waiting in the link's ring, taken after a read of block cur of device
 * `which` (-1, NULL: while idle): applied in C (csrc/emb_report.c) up to the first that
 * cannot be, a device not in a pass that got news listed for Python (before its next
 * pass, as a pass's end).  1 if that was all; 0: Python applies the rest, and logs
 * dropped frames or lost reports (it reads those counts from the link). */
static int emb_take_reports(emb_engine *e, int which, const emb_eblock *cur)
{
    int all = emb_reports_apply(e, which, cur);
    uint32_t i;

    for (i = 0; i < e->n_devices; i++) {
        emb_device *d = e->devices[i];

        if (d->n_rep && !d->in_pass && !d->ended) {
            d->taken = d->n_pass; /* its last pass, not listed: nothing there for Python */
            emb_ended(e, d, (int)i);
        }
    }
    return all && e->lk->dropped == 0 && e->lk->reports_lost == 0;
}

/* Input on an idle wrapped link (watch_fd): read and frame it, heartbeats and stale
 * bytes counted live, the reports applied in C.  1 if that was all; 0: Python pumps
 * (emb_pump failed: the link is lost, which Python's pump finds again) or takes the
 * reports. */
static int emb_idle_input(emb_engine *e)
{
    if (e->rep_regs == NULL || emb_pump(e->ctx, e->lk) == -1)
        return 0;
    emb_fault_took(e);
    return emb_take_reports(e, -1, NULL);
}

/* Run the line until something needs Python (an EMB_EV_* code; event_device and
 * event_errno say more) or until until_ns.
 *
 * Fair line scheduling: with owed set (the worker ran a queued job since the last read),
 * a queued job waits while a block is due until one read was made (good or failed), so
 * that between two poll transactions at most one job runs and a flood of jobs cannot
 * starve polling; a job still waits for one transaction at most.  When nothing is due
 * the wake flag is seen at once, as without owed. */
int emb_engine_run(emb_engine *e, int64_t until_ns)
{
    const emb_eblock *cur;
    emb_device *d;
    int64_t now, wait;
    int which = -1, ev;

    e->event_device = -1;
    e->event_errno = 0;
    for (;;) {
        now = emb_now_ns();
        d = emb_engine_pick(e, &which);
        if (e->n_ended && (d == NULL || (!d->in_pass && d->ended) || now >= e->latest_ns ||
                           d->due_ns > now + e->idle_ns))
            return EMB_EV_CYCLE; /* the passes that ended, before a new pass of one of
                                  * them (a round), before idling longer than idle_ns, or
                                  * at latest_ns on a busy line: one Python entry per
                                  * round of the devices of a line */
        if (e->owed && (d == NULL || d->due_ns > now))
            e->owed = 0; /* nothing due: the jobs may have the line */
        if (emb_woken(e) && !e->owed)
            return EMB_EV_WAKE;
        if (now >= until_ns)
            return EMB_EV_DEADLINE;
        if (emb_trace_due(e->lk->trace, now))
            return EMB_EV_TRACE; /* between passes: no device concerned */
        if (d == NULL || d->due_ns > now) {
            wait = d == NULL || d->due_ns > until_ns ? until_ns : d->due_ns;
            if (e->lk->trace && e->lk->trace->n > 0 &&
                e->lk->trace->first_ns + EMB_TRACE_FLUSH_NS < wait)
                wait = e->lk->trace->first_ns + EMB_TRACE_FLUSH_NS;
            ev = emb_sleep(e, wait, 1);
            if (ev == EMB_EV_INPUT && emb_idle_input(e))
                continue;
            if (ev >= 0)
                return ev;
            continue;
        }
        if (!d->in_pass && emb_dev_begin_pass(d, now) == 0 && d->n_blocks > 0)
            continue; /* woken early: nothing due yet */
        while (d->index < d->n_pass) {
            ev = -1;
            now = emb_now_ns(); /* one clock read per block for both checks, unless
                                 * it slept for the pacing */
            if (e->ready_ns > now) {
                ev = emb_sleep(e, e->ready_ns, 0);
                now = emb_now_ns();
            } else if (!e->owed && emb_woken(e)) {
                ev = EMB_EV_WAKE;
            } else if (e->lk->trace && e->lk->trace->used > EMB_TRACE_SIZE / 2) {
                ev = EMB_EV_TRACE; /* a long pass: Python logs what the ring holds */
            }
            if (ev < 0 && now >= until_ns)
                ev = EMB_EV_DEADLINE; /* no request at or after until_ns (a pair's lease
                                       * ends there: line/worker.py); the pass goes on
                                       * at the next run */
            if (ev < 0 && d->blocks[d->pass_list[d->index]].rep_pending)
                ev = EMB_EV_REPORTS; /* the block holds a report: Python takes it first */
            if (ev >= 0) {
                e->event_device = which; /* interrupted mid-pass */
                return ev;
            }
            e->owed = 0; /* this read pays for the job that ran before it */
            cur = &d->blocks[d->pass_list[d->index]];
            ev = emb_step(e, d, until_ns);
            if (ev != 0) {
                e->event_device = which;
                return ev;
            }
            if (emb_has_reports(e->lk) && !emb_take_reports(e, which, cur)) {
                e->event_device = which; /* the pass goes on when Python hands it back */
                return EMB_EV_REPORTS;
            }
        }
        now = emb_now_ns();
        emb_dev_end_pass(d, now, e->bounds_ns, e->n_bounds);
        emb_fault_end_pass(d, now);
        if (d->news || d->notify || now >= d->notify_ns || d->status_ev || d->fail_news)
            emb_ended(e, d, which);
    }
}
