/* edgemodbus: the fault policy, run by the line engine beside the read.
 *
 * A failed read is handled where it happened, in the C call that made it, without a
 * trip to Python:
 *   - a timeout or a CRC error is read again, up to the device's `retries` (none while
 *     the slave is offline); every request, retry and error is counted once, here;
 *   - RTU has no transaction id: after a timeout the line is settled (a reply late by
 *     up to the settle is waited out, not taken for the answer to the next request; one
 *     later still, to a request alike, cannot be told apart), after a bad
 *     frame it is drained (Modbus over Serial Line 2.5.1.1: frames end with silence);
 *   - a timeout ends the slave's pass: this block and the rest of the pass fail with "not
 *     responding" (and, once the slave is or goes offline, every block); after
 *     `offline_after` such passes in a row the slave is offline and probed once per
 *     backoff, doubling from its cycle up to `max_backoff_ns`;
 *   - an exception 02 (illegal data address) on a block of several pieces comes back to
 *     Python (EMB_EV_SPLIT), which plans the halves once (poll/planner.py bisect_block)
 *     and puts them in place (emb_dev_split); the pass goes on with them;
 *   - any other exception, CRC or protocol error fails that block only; an exception
 *     response means the slave is there (an offline slave is Running again);
 *   - a link error stops the pass (EMB_EV_FAILED): Python closes the link.
 * A block's failure stays on it (fail_kind, what Python words the reason from) until a
 * good read; Python is told only a failure it does not know yet (fail_new). */
#include "emb_fault.h"

#include <errno.h>
#include <string.h>

/* The kind of a read's failure by its errno (_ffi/errors.py maps the same errnos to
 * exceptions); *code: the exception code of an exception response. */
int emb_fault_kind(int err, int *code)
{
    *code = 0;
    if (err == ETIMEDOUT || err == EMB_EPARTIAL)
        return EMB_K_TIMEOUT;
    if (err >= EMB_EEXCEPTION && err < EMB_EEXCEPTION + 256) { /* a code is one byte */
        *code = err - EMB_EEXCEPTION;
        return EMB_K_EXCEPTION;
    }
    if (err > MODBUS_ENOBASE && err <= EMBXGTAR) {
        *code = err - MODBUS_ENOBASE;
        return EMB_K_EXCEPTION;
    }
    if (err == EMBBADCRC)
        return EMB_K_CRC;
    if ((err >= EMB_EECHO && err <= EMB_ELENGTH) || (err > EMBBADCRC && err <= EMBBADSLAVE))
        return EMB_K_PROTOCOL;
    return EMB_K_LINK;
}

/* Count one exception response of `code` (0..255) in x: its slot, a free one, or
 * x->other when every slot holds another code.  No allocation (the engine's loop). */
void emb_exc_count(emb_exc_counts *x, int code)
{
    int i;

    for (i = 0; i < EMB_EXC_SLOTS; i++) {
        if (x->n[i] == 0) {
            x->code[i] = (uint8_t)code;
            /* the code before its count: Python reads the slots live from another
             * thread (stats()), and a count of 0 marks a free slot */
            __atomic_store_n(&x->n[i], 1, __ATOMIC_RELEASE);
            return;
        }
        if (x->code[i] == (uint8_t)code) {
            x->n[i]++;
            return;
        }
    }
    x->other++;
}

/* Count a failed request once, for the device and for the line. */
void emb_fault_count(emb_engine *e, emb_device *d, int kind, int code)
{
    emb_line_counters *lc = e->lc;

    switch (kind) {
    case EMB_K_TIMEOUT:
        d->c.timeouts++;
        lc->timeouts++;
        break;
    case EMB_K_CRC:
        d->c.crc_errors++;
        lc->crc_errors++;
        lc->responses++; /* a frame came */
        break;
    case EMB_K_PROTOCOL:
        d->c.protocol_errors++;
        lc->protocol_errors++;
        lc->responses++;
        break;
    case EMB_K_EXCEPTION:
        emb_exc_count(&d->c.exceptions, code);
        emb_exc_count(&lc->exceptions, code);
        lc->responses++;
        break;
    default:
        break;
    }
}

/* How to clean the line after a failure of `kind`: settle after a timeout (when the line
 * settles at all), drain after a bad frame, else nothing (EMB_CLEAN_*).  Pure: the
 * blocking engine cleans at once (emb_fault_clean), the loop engine (csrc/emb_loop.c)
 * as a state of the link with a deadline. */
int emb_fault_clean_of(const emb_engine *e, int kind)
{
    if (kind == EMB_K_TIMEOUT && e->settle_ms > 0)
        return EMB_CLEAN_SETTLE;
    if (kind == EMB_K_CRC || kind == EMB_K_PROTOCOL)
        return EMB_CLEAN_DRAIN;
    return EMB_CLEAN_NONE;
}

/* The line was cleaned: n bytes dropped; what the link dropped and skipped besides is
 * moved into the line's counters. */
void emb_fault_cleaned(emb_engine *e, long n)
{
    e->lc->discarded += n + e->lk->discarded;
    e->lk->discarded = 0;
    e->lc->heartbeats += e->lk->heartbeats;
    e->lk->heartbeats = 0;
}

/* Clean the line after a failure of `kind` now (blocking).  0, or -1 with errno when
 * the link failed meanwhile. */
static int emb_fault_clean(emb_engine *e, int kind)
{
    long n = 0;

    switch (emb_fault_clean_of(e, kind)) {
    case EMB_CLEAN_SETTLE:
        n = emb_link_discard(e->ctx, e->lk, e->settle_ms, e->quiet_ms, e->settle_limit_ms);
        break;
    case EMB_CLEAN_DRAIN:
        n = emb_link_discard(e->ctx, e->lk, e->quiet_ms, e->quiet_ms, e->drain_limit_ms);
        break;
    default:
        break;
    }
    if (n == -1)
        return -1;
    emb_fault_cleaned(e, n);
    return 0;
}

/* Put a failure on block b: its own (EMB_FAIL_OWN: errno err, the reply in e->rsp) or
 * the slave's silence at block `at` (EMB_FAIL_SILENT).  News for Python when it differs
 * from what Python knows. */
static void emb_fault_mark(emb_engine *e, emb_device *d, emb_eblock *b, int kind,
                           const emb_eblock *at, int err)
{
    uint16_t len = 0;
    uint8_t header = e->lk->mbap ? 7 : 1;

    if (kind == EMB_FAIL_OWN) {
        len = (uint16_t)e->lk->rsp_len;
        if (len > 260)
            len = 0;
    }
    b->reported = 0;
    if (b->fail_known && d->mode != EMB_MODE_ALL && b->fail_kind == kind && b->fail_errno == err &&
        b->fail_function == at->function && b->fail_start == at->start &&
        b->fail_count == at->count && b->fail_rsp_len == len && b->fail_header == header &&
        memcmp(b->fail_rsp, e->rsp, len < EMB_FAIL_RSP ? len : EMB_FAIL_RSP) == 0)
        return; /* the same failure again: Python's items already say so (unless every
                 * item is reported every cycle) */
    b->fail_kind = (uint8_t)kind;
    b->fail_errno = err;
    b->fail_function = at->function;
    b->fail_start = at->start;
    b->fail_count = at->count;
    b->fail_rsp_len = len;
    b->fail_header = header;
    memset(b->fail_rsp, 0, EMB_FAIL_RSP);
    memcpy(b->fail_rsp, e->rsp, len < EMB_FAIL_RSP ? len : EMB_FAIL_RSP);
    b->fail_new = 1;
    b->fail_known = 0;
    d->fail_news = 1;
}

/* The slave answers: Running again (told to Python), its failed cycles forgotten. */
static void emb_fault_back(emb_device *d)
{
    if (d->running)
        return;
    d->running = 1;
    d->status_ev |= d->offline ? EMB_ST_BACK | EMB_ST_AGAIN : EMB_ST_BACK;
    d->offline = 0;
    d->failed_cycles = 0;
    d->backoff_ns = d->cycle_ns;
}

/* The slave timed out on block b (errno err): its pass ends here. */
static void emb_fault_silent(emb_engine *e, emb_device *d, emb_eblock *b, int err)
{
    uint32_t i;

    d->c.skipped_blocks += d->n_pass - d->index - 1;
    for (i = d->index; i < d->n_pass; i++)
        emb_fault_mark(e, d, &d->blocks[d->pass_list[i]], EMB_FAIL_SILENT, b, err);
    if (d->offline || d->failed_cycles + 1 >= d->offline_after)
        for (i = 0; i < d->n_blocks; i++) /* not due now either: no fresh value */
            emb_fault_mark(e, d, &d->blocks[i], EMB_FAIL_SILENT, b, err);
    d->timed_out = 1;
    d->index = d->n_pass;
}

/* A request for a block of d is about to go out: counted once, for the device and the
 * line. */
void emb_fault_sent(emb_engine *e, emb_device *d)
{
    e->lc->requests++;
    d->c.requests++;
}

/* What the link dropped and skipped during a request (stale bytes, a DTU stream's
 * heartbeats: live, no Python), moved into the line's counters. */
void emb_fault_took(emb_engine *e)
{
    e->lc->discarded += e->lk->discarded;
    e->lk->discarded = 0;
    e->lc->heartbeats += e->lk->heartbeats;
    e->lk->heartbeats = 0;
}

/* Block b was read (rc registers or bits in data, the request sent at start_ns): counted,
 * decoded (news for Python when items changed), its failure forgotten, the slave Running
 * again when a retry got through (retried); the pass goes on. */
void emb_fault_answered(emb_engine *e, emb_device *d, emb_eblock *b, int rc, void *data,
                        int64_t start_ns, int retried)
{
    e->lc->rtt_ns += emb_now_ns() - start_ns;
    e->lc->responses++;
    b->read_ns = start_ns; /* the data is no older than the request */
    d->c.responses++;
    b->reported = b->plan ? emb_decode(b->plan, data, (uint32_t)rc, d->mode) : 0;
    if (b->reported || b->keep)
        d->news = 1;
    b->fail_kind = EMB_FAIL_NONE;
    b->fail_known = 0;
    d->answered = 1;
    if (retried)
        emb_fault_back(d);
    d->index++;
}

/* The tries a read of d gets after its first: the device's retries, none offline. */
int emb_fault_tries(const emb_device *d)
{
    return d->offline ? 0 : d->retries;
}

/* A read of block b failed with err (of `kind`, exception `code`), counted and the line
 * cleaned; *tries: the retries left.  EMB_FAULT_RETRY: request again (one retry used,
 * counted); else as emb_fault_read: 0 (the failure is marked, or the pass ended on a
 * timeout) or EMB_EV_SPLIT.  Pure: no I/O. */
int emb_fault_failed(emb_engine *e, emb_device *d, emb_eblock *b, int kind, int code,
                     int err, int *tries)
{
    if ((kind == EMB_K_TIMEOUT || kind == EMB_K_CRC) && *tries > 0) {
        (*tries)--;
        d->c.retries++;
        return EMB_FAULT_RETRY;
    }
    if (kind == EMB_K_TIMEOUT) {
        emb_fault_silent(e, d, b, err);
        return 0;
    }
    if (kind == EMB_K_EXCEPTION && code == 2 && b->splittable)
        return EMB_EV_SPLIT; /* the block stays the pass's next: Python splits it */
    if (kind == EMB_K_EXCEPTION) {
        d->answered = 1;
        emb_fault_back(d);
    }
    emb_fault_mark(e, d, b, EMB_FAIL_OWN, b, err);
    d->index++;
    return 0;
}

/* One request for block b into data (the device's response timeout, the line's pacing),
 * counted: the register or bit count (*start_ns: when it was sent), or -1 with errno. */
static int emb_fault_request(emb_engine *e, emb_device *d, emb_eblock *b, void *data,
                             int64_t *start_ns)
{
    int rc, err;

    if (d->timeout_ms != e->timeout_ms) {
        modbus_set_response_timeout(e->ctx, (uint32_t)(d->timeout_ms / 1000),
                                    (uint32_t)(d->timeout_ms % 1000) * 1000U);
        e->timeout_ms = d->timeout_ms;
    }
    emb_fault_sent(e, d);
    *start_ns = emb_now_ns();
    rc = emb_read(e->ctx, e->lk, d->slave, b->function, b->start, b->count, data, e->rsp);
    err = errno;
    emb_fault_took(e);
    if (e->pace_ns)
        e->ready_ns = emb_now_ns() + e->pace_ns;
    errno = err;
    return rc;
}

/* Read block b with the fault policy.  0: the pass goes on (the block was read, or its
 * failure is marked, or the pass ended on a timeout); EMB_EV_SPLIT or EMB_EV_FAILED
 * (event_errno) for Python.  No retry starts at or after until_ns (the run's deadline:
 * a pair's lease, line/worker.py): the failure is then taken as the last try's. */
int emb_fault_read(emb_engine *e, emb_device *d, emb_eblock *b, void *data, int64_t until_ns)
{
    const int first = emb_fault_tries(d);
    int tries = first;
    int64_t start;
    int rc, err, kind, code;

    for (;;) {
        rc = emb_fault_request(e, d, b, data, &start);
        if (rc >= 0) {
            emb_fault_answered(e, d, b, rc, data, start, tries < first);
            return 0;
        }
        err = errno;
        kind = emb_fault_kind(err, &code);
        if (kind == EMB_K_LINK) {
            e->event_errno = err;
            return EMB_EV_FAILED;
        }
        if (emb_fault_clean(e, kind) == -1) {
            e->event_errno = errno;
            emb_fault_count(e, d, kind, code);
            return EMB_EV_FAILED;
        }
        emb_fault_count(e, d, kind, code); /* once the line is clean: what it cost */
        if (tries > 0 && emb_now_ns() >= until_ns)
            tries = 0;
        rc = emb_fault_failed(e, d, b, kind, code, err, &tries);
        if (rc != EMB_FAULT_RETRY)
            return rc;
    }
}

/* Every block (and the device) due at at_ns, the pass list kept for Python (an offline
 * slave's next probe). */
void emb_dev_due_at(emb_device *d, int64_t at_ns)
{
    uint32_t i;

    for (i = 0; i < d->n_blocks; i++)
        d->blocks[i].due_ns = at_ns;
    d->due_ns = (d->n_blocks || d->cycle_ns) ? at_ns : EMB_NEVER;
}

/* The pass ended (emb_dev_end_pass counted it): a failed cycle when it timed out, with
 * offline and backoff; else the slave's failed cycles are forgotten, and it is Running
 * if it answered. */
void emb_fault_end_pass(emb_device *d, int64_t now_ns)
{
    if (!d->timed_out) {
        d->failed_cycles = 0;
        if (d->answered)
            emb_fault_back(d);
        return;
    }
    d->c.failed_cycles++;
    d->failed_cycles++;
    if (d->failed_cycles < d->offline_after)
        return;
    if (d->offline) {
        d->backoff_ns = d->backoff_ns > d->max_backoff_ns / 2 ? d->max_backoff_ns
                                                              : d->backoff_ns * 2;
    } else {
        d->offline = 1;
        d->running = 0;
        d->status_ev |= EMB_ST_OFFLINE;
        d->backoff_ns = d->cycle_ns < d->max_backoff_ns ? d->cycle_ns : d->max_backoff_ns;
    }
    emb_dev_due_at(d, now_ns + d->backoff_ns); /* the probe: a pass over every block */
}
