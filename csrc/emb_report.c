/* edgemodbus: wrapped reports applied by the line engine, in C.
 *
 * An edge MCU behind a DTU pushes wrapped frames unasked; csrc/emb_stream.c frames them
 * and queues them in the link's ring.  A report updates the items of its slave whose
 * registers (or bits) lie wholly inside it, as src/edgemodbus/poll/reports.py does in
 * Python.  Here the engine applies it to the plan of the device's polled block that
 * holds it: the plan a reply decodes into, with its change tracking (emb_decode over the
 * report's items only, emb_decode_range), so that a report costs about what a polled
 * block costs: no return to Python, no object per report.  Python takes the items it
 * changed with the pass's changes (emb_device.rep_list; src/edgemodbus/_ffi/engine.py
 * EngineDevice.take_reports).
 *
 * Order: each item sees the frames in the order they came on the wire.  A block's plan
 * holds one decode Python has not taken at a time, so a report is applied here only to
 * a block that holds none (no reply of the pass listed and not taken, no report, no new
 * failure), and never when it came before the reply of the block just read (the reply is
 * newer and was decoded already).  The reports waiting are applied in order up to the
 * first that cannot be applied here (a device that reports every item, a report across
 * blocks or outside every polled block, one that collides, ...): it and those behind it
 * go to Python, as before (EMB_EV_REPORTS, EMB_EV_INPUT), which takes what C applied
 * before it applies them (Poller.take_reports).  No globals, no allocation: the scratch
 * buffers are the engine's. */
#include "emb_report.h"

#include "emb_stream.h" /* emb_report_peek, emb_report_take */

#define EMB_WRAP_PREFIX 4 /* FF AA and the register address */

/* One report, parsed from its wrapped frame (checked by csrc/emb_stream.c). */
typedef struct {
    uint32_t address; /* the wrapper's register address: the first register or bit */
    uint32_t n;       /* registers (FC03/04) or bits (FC01/02, whole bytes) it carries;
                       * 0: it holds no item (an exception, a write's echo) */
    int slave, function;
    const uint8_t *data; /* after the byte count */
} emb_rep;

static void emb_rep_parse(const uint8_t *frame, emb_rep *r)
{
    const uint8_t *rtu = frame + EMB_WRAP_PREFIX;

    r->address = (uint32_t)(frame[2] << 8 | frame[3]);
    r->slave = rtu[0];
    r->function = rtu[1];
    r->data = rtu + 3;
    if (r->function >= 1 && r->function <= 2)
        r->n = rtu[2] * 8u;
    else if (r->function >= 3 && r->function <= 4)
        r->n = rtu[2] / 2u;
    else
        r->n = 0;
}

/* The device's polled block that may take report r (rep_ok, the same function, r inside
 * its range), or NULL; *k: its index. */
static emb_eblock *emb_rep_block(const emb_device *d, const emb_rep *r, uint32_t *k)
{
    uint32_t i;

    for (i = 0; i < d->n_blocks; i++) {
        emb_eblock *b = &d->blocks[i];

        if (b->rep_ok && b->plan && b->rep_span && b->function == r->function &&
            r->address >= b->start && r->address + r->n <= (uint32_t)b->start + b->count) {
            *k = i;
            return b;
        }
    }
    return NULL;
}

/* Block k holds a reply's decode listed in the pass and not taken by Python yet. */
static int emb_rep_untaken(const emb_device *d, uint32_t k)
{
    uint32_t i, upto = d->in_pass ? d->index : d->n_pass;

    if (d->blocks[k].reported == 0)
        return 0;
    for (i = d->taken; i < upto; i++)
        if (d->pass_list[i] == k)
            return 1;
    return 0;
}

/* Whether report r can be applied here to every device it concerns (active, its slave);
 * `before`: it came before the reply of block cur of device cur_dev. */
static int emb_rep_check(const emb_engine *e, const emb_rep *r, int before, int cur_dev,
                         const emb_eblock *cur)
{
    uint32_t i, k;

    if (r->n == 0)
        return 1; /* no items: nothing to do for any device (Python ignores it too) */
    for (i = 0; i < e->n_devices; i++) {
        emb_device *d = e->devices[i];
        emb_eblock *b;

        if (!d->active || d->slave != r->slave)
            continue;
        if (d->mode == EMB_MODE_ALL) /* every report of every item goes to the callbacks */
            return 0;
        b = emb_rep_block(d, r, &k);
        if (b == NULL || b->rep_pending || b->fail_new ||
            (before && (int)i == cur_dev && b == cur) || emb_rep_untaken(d, k))
            return 0;
    }
    return 1;
}

/* Decode the items of plan p whose span (rep_span: first register or bit, count) lies in
 * lo..hi-1 from data (the block's `count` registers or bits), with the plan's change
 * tracking (EMB_MODE_TRACK), the others untouched.  Lists the changed items in
 * p->changed and the failed ones in p->errs as emb_decode does; returns how many
 * changed; *found: how many items lie inside. */
long emb_decode_range(emb_plan *p, const uint32_t *span, const void *data, uint32_t count,
                      uint32_t lo, uint32_t hi, uint32_t *found)
{
    emb_plan v = *p; /* a view of one item at a time: its state, the plan's outputs */
    uint32_t i, changed, failed, n_chg = 0, n_err = 0;

    v.n_items = 1;
    v.changed = &changed;
    v.errs = &failed;
    v.sf_src = NULL; /* scale factors: rep_ok excludes their plans */
    v.n_sf_src = 0;
    v.raw_last = NULL; /* one item: no raw image; the block's no longer says its state */
    p->raw_valid = 0;
    *found = 0;
    for (i = 0; i < p->n_items; i++) {
        if (span[2 * i] < lo || (uint64_t)span[2 * i] + span[2 * i + 1] > hi)
            continue;
        (*found)++;
        v.items = &p->items[i];
        v.status = p->status + i;
        v.errval = p->errval + i;
        v.last = p->last + i;
        v.last_status = p->last_status + i;
        if (emb_decode(&v, data, count, EMB_MODE_TRACK) > 0)
            p->changed[n_chg++] = i;
        if (v.n_errors)
            p->errs[n_err++] = i;
    }
    p->n_errors = n_err;
    return (long)n_chg;
}

/* Apply report r (checked) to every device it concerns. */
static void emb_rep_apply(emb_engine *e, const emb_rep *r)
{
    uint32_t i, j, k, lo, found;
    const void *data;
    long n;

    e->lc->reports++;
    if (r->n == 0)
        return;
    for (i = 0; i < e->n_devices; i++) {
        emb_device *d = e->devices[i];
        emb_eblock *b;

        if (!d->active || d->slave != r->slave)
            continue;
        b = emb_rep_block(d, r, &k);
        if (b == NULL) /* cannot be: emb_rep_check found it */
            continue;
        lo = r->address - b->start;
        if (r->function <= 2) { /* one byte per bit, the first in the low bit (6.1, 6.2) */
            for (j = 0; j < r->n; j++)
                e->rep_bits[lo + j] = (uint8_t)((r->data[j >> 3] >> (j & 7)) & 1);
            data = e->rep_bits;
        } else { /* big-endian registers (Modbus Application Protocol 4.2) */
            for (j = 0; j < r->n; j++)
                e->rep_regs[lo + j] = (uint16_t)(r->data[2 * j] << 8 | r->data[2 * j + 1]);
            data = e->rep_regs;
        }
        n = emb_decode_range(b->plan, b->rep_span, data, b->count, lo, lo + r->n, &found);
        if (found)
            d->c.reports++;
        if (n > 0) {
            b->rep_pending = 1;
            b->rep_n = (uint32_t)n;
            d->rep_list[d->n_rep++] = k;
            if (d->in_pass)
                d->news = 1; /* Python takes it at the pass's end */
        }
    }
}

/* Apply the reports waiting in the link's ring, in order, up to the first that cannot be
 * applied here (it stays, with those behind it, for Python: the caller returns to it).
 * cur_dev, cur: the device and block just read (the reports before its reply,
 * lk->n_before, came before it), or -1 and NULL (idle).  Returns 1 if the ring was
 * emptied here. */
int emb_reports_apply(emb_engine *e, int cur_dev, const emb_eblock *cur)
{
    emb_link *lk = e->lk;
    uint8_t frame[EMB_REPORT_MAX];
    uint32_t at;
    emb_rep r;

    if (e->rep_regs == NULL || e->rep_bits == NULL)
        return lk->n_reports == 0;
    while (lk->n_reports > 0) {
        at = 0;
        emb_report_peek(lk, &at, frame);
        emb_rep_parse(frame, &r);
        if (!emb_rep_check(e, &r, lk->n_before > 0, cur_dev, cur))
            return 0;
        emb_report_take(lk, frame);
        emb_rep_apply(e, &r);
    }
    return 1;
}
