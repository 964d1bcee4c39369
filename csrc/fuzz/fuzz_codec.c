/* libFuzzer harness for the value codec (csrc/emb_codec.c), built by tools/fuzz.py with
 * clang -fsanitize=fuzzer,address,undefined (LeakSanitizer on).
 *
 * Each input is split into a plan (item descriptions, absurd ones included), a program of
 * decode steps and a register (or bit) block, and drives the entry points the Python
 * layer uses (_ffi.CodecPlan / codec_encode): emb_plan_check, emb_reset, emb_decode
 * in every mode, emb_encode.  Every buffer is malloc'ed at exactly the size the plan
 * declares, so a read or write one element past it is an ASan report.  Only plans that
 * emb_plan_check accepts are decoded, as in production: the property under test is that
 * the check refuses every description that could make the decode go out of bounds.
 * Besides memory safety the harness checks the codec's contract (emb_codec.h) and
 * aborts on any violation: counts and index lists, statuses, change tracking, value
 * ranges of conversion targets, and encode -> decode round trips.
 *
 * Input layout (bytes; missing bytes read as 0, so every input is valid):
 *   ctl          bit0 bit block (coils); bit1 absurd layout (raw slots, aux, nregs and
 *                array lengths) instead of the production layout; bit2 null one plan
 *                pointer (the next byte says which); bit3 nudge the production layout
 *                off by a little (the two bytes after the items say what and by how much)
 *   [null_sel]   when ctl bit2
 *   count  u16   registers (mod 257) or bits (mod 2049) in the block
 *   n_items u8   mod 48
 *   items        n_items x ITEM (below)
 *   [lengths]    absurd layout: n_i64 n_u64 n_f64 n_bool n_bytes, u16 each (mod 1024)
 *   [nudge]      ctl bit3, production layout: what u8, delta u8
 *   n_steps u8   mod 12; then n_steps step bytes (op = byte % 6, see run_step)
 *   encode sel   raw u64, fval selector, max_regs u8, nbytes u8
 *   data         the rest: the block, big-endian registers (or one byte per bit)
 * ITEM: wire flags target out bit nregs_sel u8, offset u16, scale_sel deadband_sel u8,
 *       and in the absurd layout also slot u16, aux u16, nregs u16.
 * tools/fuzz_seeds.py writes a seed corpus in this layout.
 */
#include "../emb_codec.h"

#include <float.h>
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define MAX_ITEMS 48
#define MAX_REGS 257
#define MAX_BITS 2049

#define FUZZ_NAME "fuzz_codec"
#include "fuzz_input.h"

static uint64_t rd64(reader *r)
{
    uint64_t v = 0;
    for (int k = 0; k < 8; k++)
        v = v << 8 | rd8(r);
    return v;
}

/* Doubles that hit the codec's edges; a selector with bit 7 set reads 8 raw bytes. */
static double rd_double(reader *r)
{
    static const double table[] = {
        1.0, 10.0, 0.1, 0.001, -1.5, 2.0, 1000.0, 0.5, 1e308, -1e308, 5e-324, 1e-300,
        0.0, -0.0, NAN, INFINITY, -INFINITY, 65535.0, 9223372036854775808.0, 3.4028234663852886e38,
        18446744073709551616.0, -9223372036854775808.0, 0.25, 100.0,
    };
    uint8_t sel = rd8(r);
    if (sel & 0x80) {
        uint64_t bits = rd64(r);
        double d;
        memcpy(&d, &bits, sizeof d);
        return d;
    }
    return table[sel % (sizeof table / sizeof table[0])];
}

/* --- what the codec promises ------------------------------------------------------- */

static unsigned width_of(unsigned wire)
{
    switch (wire) {
    case EMB_W_COIL: case EMB_W_REGBOOL: case EMB_W_REGBIT: case EMB_W_U8: case EMB_W_I8:
    case EMB_W_U16: case EMB_W_I16: case EMB_W_BCD16:
        return 1;
    case EMB_W_U32: case EMB_W_I32: case EMB_W_F32: case EMB_W_BCD32: case EMB_W_SEC32:
    case EMB_W_I24: case EMB_W_U24:
        return 2;
    case EMB_W_U64: case EMB_W_I64: case EMB_W_F64: case EMB_W_MS64:
        return 4;
    default:
        return 0;
    }
}

static int64_t sext(uint64_t v, unsigned bits)
{
    if (bits == 64) {
        int64_t s;
        memcpy(&s, &v, sizeof s);
        return s;
    }
    uint64_t sign = (uint64_t)1 << (bits - 1);
    return (int64_t)(v ^ sign) - (int64_t)sign;
}

/* Inclusive range an integer target promises (0 when the target is not one of those). */
static int int_range(unsigned target, int64_t *lo, int64_t *hi)
{
    switch (target) {
    case EMB_C_I8: *lo = -128; *hi = 127; return 1;
    case EMB_C_U8: *lo = 0; *hi = 255; return 1;
    case EMB_C_I16: *lo = -32768; *hi = 32767; return 1;
    case EMB_C_U16: *lo = 0; *hi = 65535; return 1;
    case EMB_C_I32: *lo = INT32_MIN; *hi = INT32_MAX; return 1;
    case EMB_C_U32: *lo = 0; *hi = UINT32_MAX; return 1;
    case EMB_C_BCD16: *lo = 0; *hi = 9999; return 1;
    case EMB_C_BCD32: *lo = 0; *hi = 99999999; return 1;
    case EMB_C_DATETIME: *lo = -62135596800000LL; *hi = 253402300799999LL; return 1;
    case EMB_C_I24: *lo = -8388608; *hi = 8388607; return 1;
    case EMB_C_U24: *lo = 0; *hi = 16777215; return 1;
    case EMB_C_I64: *lo = INT64_MIN; *hi = INT64_MAX; return 1;
    default: return 0;
    }
}

static int is_float_wire(unsigned wire) { return wire == EMB_W_F32 || wire == EMB_W_F64; }

static double as_double(uint64_t bits)
{
    double d;
    memcpy(&d, &bits, sizeof d);
    return d;
}

/* Whether the offending value of a failed item is one its target refuses (emb_codec.h:
 * errval is the exact value the item failed for). */
static int refused_value(const emb_item *it, int st, const emb_errval *ev)
{
    int64_t lo, hi;
    switch (st) {
    case EMB_E_MISSING:
        return ev->kind == EMB_K_NONE;
    case EMB_E_NAN:
        return ev->kind == EMB_K_FLOAT && isnan(as_double(ev->bits));
    case EMB_E_BCD: {
        unsigned digits = it->wire == EMB_W_BCD16 ? 4 : 8;
        if (ev->kind != EMB_K_UINT || (digits == 4 && ev->bits > 0xFFFF)
            || ev->bits > 0xFFFFFFFFu)
            return 0;
        for (unsigned k = 0; k < digits; k++)
            if (((ev->bits >> (4 * k)) & 0xF) > 9)
                return 1;
        return 0;
    }
    case EMB_E_RANGE:
        break;
    default:
        return 0;
    }
    if (it->target == EMB_C_F32) {
        double f = as_double(ev->bits);
        return ev->kind == EMB_K_FLOAT && isfinite(f) && fabs(f) > FLT_MAX;
    }
    if (ev->kind == EMB_K_FLOAT) {
        double d = nearbyint(as_double(ev->bits));
        if (isnan(d))
            return 0;
        if (it->target == EMB_C_U64)
            return !(d >= 0.0 && d < 18446744073709551616.0);
        if (!int_range(it->target, &lo, &hi))
            return 0;
        return !(d >= (double)lo && d <= (double)hi) || d >= 9223372036854775808.0;
    }
    if (it->target == EMB_C_U64)
        return ev->kind == EMB_K_INT && sext(ev->bits, 64) < 0;
    if (!int_range(it->target, &lo, &hi))
        return 0;
    if (ev->kind == EMB_K_UINT)
        return ev->bits > (uint64_t)hi;
    return ev->kind == EMB_K_INT && (sext(ev->bits, 64) < lo || sext(ev->bits, 64) > hi);
}

/* The part of a failed item's result its reason depends on besides the status (the
 * codec keeps it in `last` to report a new reason; emb_codec.h). */
static uint64_t reason_key(int st, const emb_errval *ev)
{
    return (st == EMB_E_BCD || st == EMB_E_RANGE) ? ev->bits : 0;
}

/* An independent model of the item rules of emb_plan_check (emb_codec.h: "every item
 * fits the plan's arrays and is coherent"); keep the two in step. */
static int item_ok(const emb_plan *p, const emb_item *it)
{
    if (it->wire < EMB_W_COIL || it->wire > EMB_W_LAST || it->target > EMB_C_LAST)
        return 0;
    if ((it->wire == EMB_W_COIL) != (p->bits != 0))
        return 0;
    if ((it->wire == EMB_W_BYTES) != (it->out == EMB_O_BYTES))
        return 0;
    uint64_t slot = it->slot;
    switch (it->out) {
    case EMB_O_I64: if (slot >= p->n_i64) return 0; break;
    case EMB_O_U64: if (slot >= p->n_u64) return 0; break;
    case EMB_O_F64: if (slot >= p->n_f64) return 0; break;
    case EMB_O_BOOL: if (slot >= p->n_bool) return 0; break;
    case EMB_O_BYTES:
        if (slot >= p->n_u64 || (uint64_t)it->aux + 2 * (uint64_t)it->nregs > p->n_bytes)
            return 0;
        break;
    default: return 0;
    }
    int scaled = (it->flags & (EMB_F_MULTIPLY | EMB_F_DIVIDE)) != 0;
    if (it->flags & EMB_F_EXT)
        return 0; /* engineering units need plan->scales, which this harness never sets */
    if (it->wire == EMB_W_BYTES) {
        if (it->nregs == 0 || it->target != EMB_C_NONE || scaled)
            return 0;
    } else if (it->nregs != width_of(it->wire) || it->bit > 15) {
        return 0;
    }
    return !scaled || (isfinite(it->scale) && it->scale != 0.0);
}

/* What emb_plan_check must return for a plan whose pointers are all set. */
static long expected_check(const emb_plan *p)
{
    for (uint32_t i = 0; i < p->n_items; i++)
        if (!item_ok(p, &p->items[i]))
            return (long)i + 1;
    return 0;
}

/* Whether emb_encode must pack the item (emb_codec.h lists when it refuses). */
static int encode_ok(const emb_item *it, uint64_t raw, double fval, uint32_t nbytes,
                     uint32_t max_regs)
{
    unsigned w = it->wire == EMB_W_BYTES ? it->nregs : width_of(it->wire);
    if (w == 0 || w > max_regs || it->wire == EMB_W_REGBIT)
        return 0;
    switch (it->wire) {
    case EMB_W_BCD16: return raw <= 9999;
    case EMB_W_BCD32: return raw <= 99999999;
    case EMB_W_F32: return !(isfinite(fval) && fabs(fval) > FLT_MAX);
    case EMB_W_BYTES: return nbytes <= 2u * w;
    default: return 1;
    }
}

/* --- the plan and its buffers ------------------------------------------------------ */

typedef struct world {
    emb_item items[MAX_ITEMS];
    emb_plan plan;
    int production;       /* slots unique per group, as _ffi.CodecPlan lays them out */
    uint32_t count;       /* elements in data */
    void *data;           /* exactly count registers (or count bytes for bits) */
    /* snapshots for the state checks */
    uint64_t last[MAX_ITEMS];
    uint8_t last_status[MAX_ITEMS];
} world;

static void *alloc_exact(size_t n, size_t size)
{
    /* malloc(0) gives a zero-size block under ASan: any access to it is reported. */
    void *p = malloc(n * size);
    if (!p && n)
        abort();
    if (n)
        memset(p, 0xA5, n * size); /* not zero: a decode must not rely on clean outputs */
    return p;
}

static void free_plan(emb_plan *p)
{
    free(p->out_i64);
    free(p->out_u64);
    free(p->out_f64);
    free(p->out_bool);
    free(p->out_bytes);
    free(p->last_bytes);
    free(p->status);
    free(p->errval);
    free(p->errs);
    free(p->changed);
    free(p->last);
    free(p->last_status);
}

/* Per-item arrays and outputs, with the lengths already in the plan. */
static void alloc_plan(emb_plan *p)
{
    uint32_t n = p->n_items;
    p->out_i64 = alloc_exact(p->n_i64, sizeof(int64_t));
    p->out_u64 = alloc_exact(p->n_u64, sizeof(uint64_t));
    p->out_f64 = alloc_exact(p->n_f64, sizeof(double));
    p->out_bool = alloc_exact(p->n_bool, sizeof(bool));
    if (p->n_bool)
        memset(p->out_bool, 0, p->n_bool * sizeof(bool)); /* a bool must hold 0 or 1 */
    p->out_bytes = alloc_exact(p->n_bytes, 1);
    p->last_bytes = alloc_exact(p->n_bytes, 1);
    p->status = alloc_exact(n, 1);
    p->errval = alloc_exact(n, sizeof(emb_errval));
    p->errs = alloc_exact(n, sizeof(uint32_t));
    p->changed = alloc_exact(n, sizeof(uint32_t));
    p->last = alloc_exact(n, sizeof(uint64_t));
    p->last_status = alloc_exact(n, 1);
}

static void read_item(reader *r, emb_item *it, int absurd)
{
    uint8_t wire = rd8(r), flags = rd8(r), target = rd8(r), out = rd8(r), bit = rd8(r);
    uint8_t nsel = rd8(r);
    memset(it, 0, sizeof *it);
    it->offset = rd16(r);
    it->scale = rd_double(r);
    it->deadband = rd_double(r);
    if (absurd) {
        it->wire = wire;
        it->flags = flags;
        it->target = target;
        it->out = out;
        it->bit = bit;
        it->slot = rd16(r);
        it->aux = rd16(r);
        it->nregs = rd16(r);
        if (nsel & 1)
            it->offset |= (uint32_t)rd16(r) << 16; /* offsets near 2^32: overflow bait */
        return;
    }
    /* Near-valid values, so that most plans pass the check and reach the decode. */
    it->wire = (uint8_t)(wire % (EMB_W_LAST + 2));    /* 0 and LAST+1 are invalid */
    it->flags = (uint8_t)(flags & 0x3F);              /* every flag, 0x01..0x20 */
    it->target = (uint8_t)(target % (EMB_C_LAST + 2));
    it->out = (uint8_t)(out % 6);                     /* 5 is no group */
    it->bit = (uint8_t)(bit % 17);                    /* 16 is invalid */
    it->offset %= 300;
    if (it->wire == EMB_W_BYTES)
        it->nregs = (uint16_t)(nsel % 130);
    else
        it->nregs = (uint16_t)((nsel & 0x80) ? nsel % 6 : width_of(it->wire));
}

/* Slots and byte offsets as _ffi.CodecPlan assigns them (BYTES share u64 slots). */
static void production_layout(emb_plan *p, emb_item *items)
{
    uint32_t sizes[4] = {0, 0, 0, 0};
    uint32_t nbytes = 0;
    for (uint32_t i = 0; i < p->n_items; i++) {
        emb_item *it = &items[i];
        unsigned g = it->out == EMB_O_BYTES ? EMB_O_U64 : it->out;
        if (g >= 4) {
            it->slot = 0; /* refused by the check: no group */
            continue;
        }
        it->slot = sizes[g]++;
        if (it->out == EMB_O_BYTES) {
            it->aux = nbytes;
            nbytes += 2u * it->nregs;
        }
    }
    p->n_i64 = sizes[0];
    p->n_u64 = sizes[1];
    p->n_f64 = sizes[2];
    p->n_bool = sizes[3];
    p->n_bytes = nbytes;
}

/* Off-by-a-little errors of the caller (one array too short, an item one slot or a few
 * bytes too far, one register more): the check must refuse every one that would take
 * the decode out of its arrays. */
static void nudge(emb_plan *p, emb_item *items, uint8_t what, uint8_t delta)
{
    uint32_t d = 1u + delta % 4;
    uint32_t *len[] = {&p->n_i64, &p->n_u64, &p->n_f64, &p->n_bool, &p->n_bytes};
    if (what % 8 < 5) {
        uint32_t *n = len[what % 8];
        *n = *n > d ? *n - d : 0;
        return;
    }
    if (!p->n_items)
        return;
    emb_item *it = &items[(delta / 4u) % p->n_items];
    switch (what % 8) {
    case 5: it->aux += d; break;
    case 6: it->slot += d; break;
    default: it->nregs = (uint16_t)(it->nregs + d); break;
    }
}

/* Set one pointer of the plan to NULL; returns whether the plan then must be refused. */
static int null_one(emb_plan *p, unsigned which, void **freed)
{
    int needed_items = p->n_items > 0;
    void **slot;
    int needed;
    switch (which % 13) {
    case 0: slot = (void **)&p->items; needed = needed_items; break;
    case 1: slot = (void **)&p->status; needed = needed_items; break;
    case 2: slot = (void **)&p->errval; needed = needed_items; break;
    case 3: slot = (void **)&p->errs; needed = needed_items; break;
    case 4: slot = (void **)&p->changed; needed = needed_items; break;
    case 5: slot = (void **)&p->last; needed = needed_items; break;
    case 6: slot = (void **)&p->last_status; needed = needed_items; break;
    case 7: slot = (void **)&p->out_i64; needed = p->n_i64 > 0; break;
    case 8: slot = (void **)&p->out_u64; needed = p->n_u64 > 0; break;
    case 9: slot = (void **)&p->out_f64; needed = p->n_f64 > 0; break;
    case 10: slot = (void **)&p->out_bool; needed = p->n_bool > 0; break;
    case 11: slot = (void **)&p->out_bytes; needed = p->n_bytes > 0; break;
    default: slot = (void **)&p->last_bytes; needed = p->n_bytes > 0; break;
    }
    if (which % 13 != 0) /* items is not ours to free */
        *freed = *slot;
    *slot = NULL;
    return needed;
}

/* --- decode checks ----------------------------------------------------------------- */

static int strictly_increasing(const uint32_t *v, long n, uint32_t limit)
{
    for (long k = 0; k < n; k++)
        if (v[k] >= limit || (k > 0 && v[k] <= v[k - 1]))
            return 0;
    return 1;
}

/* What must hold after any decode of a checked plan. */
static void check_decode(const world *w, long rc, int mode)
{
    const emb_plan *p = &w->plan;
    uint32_t n = p->n_items;
    CHECK(rc >= 0 && rc <= (long)n);
    CHECK(p->n_errors <= n);
    CHECK(strictly_increasing(p->errs, p->n_errors, n));
    if (mode == EMB_MODE_VALUES)
        CHECK(rc == (long)p->n_errors);
    else
        CHECK(strictly_increasing(p->changed, rc, n));
    uint32_t failed = 0;
    for (uint32_t i = 0; i < n; i++) {
        const emb_item *it = &p->items[i];
        uint8_t st = p->status[i];
        CHECK(st <= EMB_E_RANGE);
        CHECK((st == EMB_E_MISSING) == ((uint64_t)it->offset + it->nregs > w->count));
        if (st != EMB_E_OK) {
            CHECK(failed < p->n_errors && p->errs[failed] == i);
            failed++;
        }
        int scaled = (it->flags & (EMB_F_MULTIPLY | EMB_F_DIVIDE)) != 0;
        int64_t lo, hi;
        int integer = int_range(it->target, &lo, &hi) || it->target == EMB_C_U64;
        if (st == EMB_E_BCD)
            CHECK(it->wire == EMB_W_BCD16 || it->wire == EMB_W_BCD32);
        if (st == EMB_E_NAN)
            CHECK(integer && (scaled || is_float_wire(it->wire)));
        if (st == EMB_E_RANGE)
            CHECK(integer || it->target == EMB_C_F32);
        if (st != EMB_E_OK)
            CHECK(refused_value(it, st, &p->errval[i]));
        if (st != EMB_E_OK || !w->production)
            continue; /* shared slots (absurd layout) may be overwritten by later items */
        /* The value an OK item left in its output group honours its target. */
        switch (it->out) {
        case EMB_O_I64:
            if (int_range(it->target, &lo, &hi))
                CHECK(p->out_i64[it->slot] >= lo && p->out_i64[it->slot] <= hi);
            break;
        case EMB_O_F64:
            if (it->target == EMB_C_F32) {
                double f = p->out_f64[it->slot];
                CHECK(!isfinite(f) || fabs(f) <= FLT_MAX);
            }
            break;
        case EMB_O_BYTES: {
            uint64_t len = p->out_u64[it->slot];
            CHECK(len <= 2u * it->nregs);
            if (it->flags & EMB_F_STRIP)
                CHECK(len == 0 || p->out_bytes[it->aux + len - 1] != 0);
            else
                CHECK(len == 2u * it->nregs);
            break;
        }
        default:
            break;
        }
    }
    CHECK(failed == p->n_errors);
}

static void snapshot_state(world *w)
{
    if (!w->plan.n_items)
        return; /* the state arrays may be NULL then */
    memcpy(w->last, w->plan.last, w->plan.n_items * sizeof(uint64_t));
    memcpy(w->last_status, w->plan.last_status, w->plan.n_items);
}

static int state_unchanged(const world *w)
{
    if (!w->plan.n_items)
        return 1;
    return memcmp(w->last, w->plan.last, w->plan.n_items * sizeof(uint64_t)) == 0
           && memcmp(w->last_status, w->plan.last_status, w->plan.n_items) == 0;
}

static int listed(const uint32_t *v, long n, uint32_t i)
{
    for (long k = 0; k < n; k++)
        if (v[k] == i)
            return 1;
    return 0;
}

/* A failed item is reported when its status or its reason's value moved (TRACK), or
 * always (ALL); whatever is reported becomes the state. */
static void check_failed_tracking(const world *w, long rc, int mode)
{
    const emb_plan *p = &w->plan;
    for (uint32_t i = 0; i < p->n_items; i++) {
        uint8_t st = p->status[i];
        if (st == EMB_E_OK)
            continue;
        uint64_t key = reason_key(st, &p->errval[i]);
        int moved = st != w->last_status[i] || key != w->last[i];
        int reported = listed(p->changed, rc, i);
        CHECK(reported == (mode == EMB_MODE_ALL || moved));
        CHECK(p->last_status[i] == st);
        CHECK(!reported || p->last[i] == key);
    }
}

static long decode(world *w, int mode)
{
    if (mode != EMB_MODE_VALUES)
        snapshot_state(w);
    long rc = emb_decode(&w->plan, w->data, w->count, mode);
    check_decode(w, rc, mode);
    if (mode != EMB_MODE_VALUES)
        check_failed_tracking(w, rc, mode);
    return rc;
}

/* One step of the program; each keeps the block exactly `count` elements long. */
static void run_step(world *w, uint8_t op, reader *r)
{
    emb_plan *p = &w->plan;
    switch (op % 6) {
    /* The repeat checks hold for coherent plans only: in the absurd layout BYTES items
     * may share bytes of out_bytes/last_bytes and then see each other's data. */
    case 0: { /* TRACK, then TRACK again on the same block reports nothing */
        decode(w, EMB_MODE_TRACK);
        long again = decode(w, EMB_MODE_TRACK);
        CHECK(again == 0 || !w->production);
        break;
    }
    case 1: { /* ALL, then ALL again lists only the failed items */
        decode(w, EMB_MODE_ALL);
        long again = decode(w, EMB_MODE_ALL);
        if (w->production) {
            CHECK(again == (long)p->n_errors);
            CHECK(again == 0
                  || memcmp(p->changed, p->errs, (size_t)again * sizeof(uint32_t)) == 0);
        }
        break;
    }
    case 2: { /* VALUES leaves the reported state alone */
        snapshot_state(w);
        decode(w, EMB_MODE_VALUES);
        CHECK(state_unchanged(w));
        break;
    }
    case 3: /* after a reset TRACK reports every item */
        emb_reset(p);
        CHECK(decode(w, EMB_MODE_TRACK) == (long)p->n_items);
        break;
    case 4: { /* change one element of the block */
        uint16_t at = rd16(r), v = rd16(r);
        if (w->count) {
            if (p->bits)
                ((uint8_t *)w->data)[at % w->count] = (uint8_t)v;
            else
                ((uint16_t *)w->data)[at % w->count] = v;
        }
        break;
    }
    default: { /* a shorter (or empty) response: reallocated, so overreads are caught */
        uint32_t shorter = w->count ? rd16(r) % (w->count + 1) : 0;
        size_t size = p->bits ? 1 : 2;
        void *d = alloc_exact(shorter, size);
        if (shorter)
            memcpy(d, w->data, shorter * size);
        free(w->data);
        w->data = d;
        w->count = shorter;
        decode(w, EMB_MODE_TRACK);
        break;
    }
    }
}

/* --- encode -------------------------------------------------------------------------- */

/* The natural output group of a wire with no conversion (as codec._compile picks it). */
static uint8_t natural_out(unsigned wire)
{
    switch (wire) {
    case EMB_W_COIL: case EMB_W_REGBOOL: case EMB_W_REGBIT: return EMB_O_BOOL;
    case EMB_W_U64: return EMB_O_U64;
    case EMB_W_F32: case EMB_W_F64: return EMB_O_F64;
    case EMB_W_BYTES: return EMB_O_BYTES;
    default: return EMB_O_I64;
    }
}

/* Decode `regs` (n registers, or one bit byte for a coil) with a one-item plan of `src`'s
 * wire and format, no conversion; checks the result against what was encoded. */
static void round_trip(const emb_item *src, const uint16_t *regs, int n, uint64_t raw,
                       double fval, const uint8_t *bytes, uint32_t nbytes)
{
    emb_item it;
    memset(&it, 0, sizeof it);
    it.wire = src->wire;
    it.flags = src->flags & (EMB_F_BYTE_SWAP | EMB_F_WORD_SWAP | EMB_F_DWORD_SWAP | EMB_F_STRIP);
    it.nregs = (uint16_t)n;
    it.target = EMB_C_NONE;
    it.out = natural_out(it.wire);
    it.scale = 1.0;

    int64_t i64 = 0;
    uint64_t u64 = 0, last = 0;
    double f64 = 0.0;
    emb_errval errval = {0, EMB_K_NONE};
    bool b = false;
    uint8_t out_bytes[2 * 130], last_bytes[2 * 130];
    uint8_t status = 0, last_status = 0;
    uint32_t errs = 0, changed = 0;
    uint8_t coil = (uint8_t)regs[0];
    emb_plan p = {
        .items = &it, .n_items = 1, .bits = it.wire == EMB_W_COIL,
        .out_i64 = &i64, .out_u64 = &u64, .out_f64 = &f64, .out_bool = &b,
        .out_bytes = out_bytes, .n_i64 = 1, .n_u64 = 1, .n_f64 = 1, .n_bool = 1,
        .n_bytes = sizeof out_bytes, .status = &status, .errval = &errval, .errs = &errs,
        .changed = &changed, .last = &last, .last_status = &last_status,
        .last_bytes = last_bytes,
    };
    CHECK(emb_plan_check(&p) == 0);
    emb_reset(&p);
    CHECK(emb_decode(&p, p.bits ? (const void *)&coil : (const void *)regs, (uint32_t)n,
                     EMB_MODE_TRACK) == 1);
    CHECK(status == EMB_E_OK);

    switch (it.wire) {
    case EMB_W_COIL: case EMB_W_REGBOOL: CHECK(b == (raw != 0)); break;
    case EMB_W_U8: CHECK(i64 == (int64_t)(raw & 0xFF)); break;
    case EMB_W_I8: CHECK(i64 == sext(raw & 0xFF, 8)); break;
    case EMB_W_U16: CHECK(i64 == (int64_t)(raw & 0xFFFF)); break;
    case EMB_W_I16: CHECK(i64 == sext(raw & 0xFFFF, 16)); break;
    case EMB_W_U32: CHECK(i64 == (int64_t)(raw & 0xFFFFFFFF)); break;
    case EMB_W_I32: CHECK(i64 == sext(raw & 0xFFFFFFFF, 32)); break;
    case EMB_W_U24: CHECK(i64 == (int64_t)(raw & 0xFFFFFF)); break;
    case EMB_W_I24: CHECK(i64 == sext(raw & 0xFFFFFF, 24)); break;
    case EMB_W_U64: CHECK(u64 == raw); break;
    case EMB_W_I64: case EMB_W_MS64: CHECK(i64 == sext(raw, 64)); break;
    case EMB_W_SEC32: CHECK(i64 == (int64_t)(raw & 0xFFFFFFFF) * 1000); break;
    case EMB_W_BCD16: case EMB_W_BCD32: CHECK(i64 == (int64_t)raw); break;
    case EMB_W_F32: {
        float f = (float)fval; /* the encoder refused anything beyond float range */
        CHECK(isnan(fval) ? isnan(f64) : f64 == (double)f);
        break;
    }
    case EMB_W_F64:
        CHECK(memcmp(&f64, &fval, sizeof f64) == 0); /* bit-exact, NaN payloads too */
        break;
    case EMB_W_BYTES: {
        uint32_t len = 2u * (uint32_t)n;
        for (uint32_t k = 0; k < len; k++)
            CHECK(out_bytes[k] == (k < nbytes ? bytes[k] : 0));
        if (it.flags & EMB_F_STRIP)
            while (len > 0 && out_bytes[len - 1] == 0)
                len--;
        CHECK(u64 == len);
        break;
    }
    default:
        CHECK(0); /* no other wire encodes */
    }
}

/* emb_encode with each item of the plan (checked or not) into a buffer of exactly
 * max_regs registers; a plan-valid item is then decoded back. */
static void fuzz_encode(const world *w, reader *r, const uint8_t *bytes, uint32_t avail)
{
    uint64_t raw = rd64(r);
    double fval = rd_double(r);
    uint8_t max_sel = rd8(r), nb_sel = rd8(r);
    for (uint32_t i = 0; i < w->plan.n_items; i++) {
        const emb_item *it = &w->items[i]; /* plan.items may have been nulled */
        unsigned width = it->wire == EMB_W_BYTES ? it->nregs : width_of(it->wire);
        uint32_t max_regs = (max_sel & 0x80) ? (uint32_t)(max_sel % 8) : (width ? width : 1);
        uint32_t nbytes = nb_sel % 261;
        if (nbytes > avail)
            nbytes = avail;
        /* BCD only fits when the digits do: keep raw in range half the time */
        uint64_t v = raw;
        if ((it->wire == EMB_W_BCD16 || it->wire == EMB_W_BCD32) && !(max_sel & 0x40))
            v = raw % (it->wire == EMB_W_BCD16 ? 10000u : 100000000u);
        uint16_t *regs = alloc_exact(max_regs, sizeof(uint16_t));
        int n = emb_encode(it, v, fval, nbytes ? bytes : NULL, nbytes, regs, max_regs);
        CHECK(n == -1 || (n >= 1 && (uint32_t)n <= max_regs && (unsigned)n == width));
        CHECK((n > 0) == encode_ok(it, v, fval, nbytes, max_regs));
        if (n > 0 && n <= 130) /* round_trip's byte buffers hold 130 registers */
            round_trip(it, regs, n, v, fval, bytes, nbytes);
        free(regs);
        raw = raw * 6364136223846793005ULL + 1442695040888963407ULL; /* next item's value */
    }
}

/* --- entry ------------------------------------------------------------------------- */

#ifdef EMB_FUZZ_LEAK_CANARY
/* tools/fuzz.py builds a second binary with this and feeds it "LEAK!" to prove that
 * LeakSanitizer reports a leak on this machine (it can be silently off, e.g. without
 * ptrace), so "no leak" from a run means something. */
void *volatile emb_fuzz_canary;
#endif

int LLVMFuzzerTestOneInput(const uint8_t *input, size_t size)
{
#ifdef EMB_FUZZ_LEAK_CANARY
    if (size >= 5 && memcmp(input, "LEAK!", 5) == 0) {
        emb_fuzz_canary = malloc(24);
        emb_fuzz_canary = NULL;
    }
#endif
    reader r = {input, size};
    world w;
    memset(&w, 0, sizeof w);
    emb_plan *p = &w.plan;

    uint8_t ctl = rd8(&r);
    unsigned null_sel = (ctl & 4) ? rd8(&r) : 0;
    int bits = ctl & 1, absurd = (ctl & 2) != 0;
    uint16_t count_sel = rd16(&r);
    w.count = bits ? count_sel % MAX_BITS : count_sel % MAX_REGS;
    p->n_items = rd8(&r) % MAX_ITEMS;
    p->bits = bits;
    for (uint32_t i = 0; i < p->n_items; i++)
        read_item(&r, &w.items[i], absurd);
    if (absurd) {
        p->n_i64 = rd16(&r) % 1024;
        p->n_u64 = rd16(&r) % 1024;
        p->n_f64 = rd16(&r) % 1024;
        p->n_bool = rd16(&r) % 1024;
        p->n_bytes = rd16(&r) % 1024;
    } else {
        production_layout(p, w.items);
    }
    w.production = !absurd;
    if (!absurd && (ctl & 8)) {
        uint8_t what = rd8(&r);
        nudge(p, w.items, what, rd8(&r));
        w.production = 0; /* slots or bytes may be shared now */
    }
    p->items = w.items;
    alloc_plan(p);

    void *nulled = NULL;
    int must_refuse = (ctl & 4) ? null_one(p, null_sel, &nulled) : 0;
    long bad = emb_plan_check(p);
    CHECK(bad >= -1 && bad <= (long)p->n_items);
    CHECK(bad == (must_refuse ? -1 : expected_check(p)));

    uint8_t steps[16];
    uint8_t n_steps = rd8(&r) % 12;
    for (unsigned k = 0; k < n_steps; k++)
        steps[k] = rd8(&r);
    reader enc = r; /* encode selectors; the block follows them */
    for (int k = 0; k < 19; k++)
        (void)rd8(&r);

    /* The block: exactly count elements, from the rest of the input (zero-padded). */
    size_t elem = bits ? 1 : 2;
    w.data = alloc_exact(w.count, elem);
    for (uint32_t k = 0; k < w.count; k++) {
        if (bits)
            ((uint8_t *)w.data)[k] = rd8(&r);
        else
            ((uint16_t *)w.data)[k] = rd16(&r);
    }

    if (bad == 0) {
        emb_reset(p);
        CHECK(decode(&w, EMB_MODE_TRACK) == (long)p->n_items); /* first report: all */
        for (unsigned k = 0; k < n_steps; k++)
            run_step(&w, steps[k], &r);
        snapshot_state(&w);
        decode(&w, EMB_MODE_VALUES);
        CHECK(state_unchanged(&w));
    }
    /* Encode sees every item, accepted by the check or not: it validates on its own. */
    fuzz_encode(&w, &enc, input, (uint32_t)(size < 260 ? size : 260));

    free(nulled);
    free_plan(p);
    free(w.data);
    return 0;
}
