/* edgemodbus value codec; see emb_codec.h for the contract. */
#include "emb_codec.h"

#include <float.h>
#include <math.h>
#include <string.h>

/* A raw or converted value: which member holds it. */
enum { NUM_INT, NUM_UINT, NUM_FLOAT };

typedef struct emb_num {
    int cls;
    int64_t i;
    uint64_t u;
    double f;
} emb_num;

/* Milliseconds of 0001-01-01T00:00:00Z and 9999-12-31T23:59:59.999Z (Python datetime). */
#define EMB_MS_MIN (-62135596800000LL)
#define EMB_MS_MAX 253402300799999LL

static inline uint16_t bswap16(uint16_t v) { return (uint16_t)((v << 8) | (v >> 8)); }

/* Width in registers of a fixed-size wire value (0 for BYTES, which use nregs). */
static unsigned wire_width(unsigned wire)
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

/* Where register k (0 = most significant) of a w-register value sits among the item's
 * registers: the word order of emb_codec.h (DWORD_SWAP only for 4 registers). */
static inline unsigned reg_index(unsigned k, unsigned w, unsigned flags)
{
    unsigned at = (flags & EMB_F_WORD_SWAP) ? w - 1 - k : k;
    return (w == 4 && (flags & EMB_F_DWORD_SWAP)) ? at ^ 2u : at;
}

/* Register k (0 = most significant) of a w-register value, in value order. */
static inline uint16_t reg_at(const uint16_t *r, unsigned k, unsigned w, unsigned flags)
{
    uint16_t v = r[reg_index(k, w, flags)];
    return (flags & EMB_F_BYTE_SWAP) ? bswap16(v) : v;
}

static uint64_t gather(const uint16_t *r, unsigned w, unsigned flags)
{
    uint64_t v = 0;
    for (unsigned k = 0; k < w; k++)
        v = (v << 16) | reg_at(r, k, w, flags);
    return v;
}

/* Two's complement reinterpretation without implementation-defined casts. */
static inline int64_t sext(uint64_t v, unsigned bits)
{
    if (bits == 64) {
        int64_t s;
        memcpy(&s, &v, sizeof s);
        return s;
    }
    uint64_t sign = (uint64_t)1 << (bits - 1);
    return (int64_t)(v ^ sign) - (int64_t)sign;
}

/* Packed decimal: every nibble 0..9, else -1. */
static int64_t bcd_value(uint64_t v, unsigned digits)
{
    int64_t out = 0;
    for (unsigned k = digits; k-- > 0;) {
        unsigned nib = (unsigned)(v >> (4 * k)) & 0xF;
        if (nib > 9)
            return -1;
        out = out * 10 + nib;
    }
    return out;
}

static double num_to_double(const emb_num *n)
{
    switch (n->cls) {
    case NUM_INT: return (double)n->i;
    case NUM_UINT: return (double)n->u;
    default: return n->f;
    }
}

static bool num_nonzero(const emb_num *n)
{
    switch (n->cls) {
    case NUM_INT: return n->i != 0;
    case NUM_UINT: return n->u != 0;
    default: return n->f != 0.0; /* NaN is nonzero, as in C and Python */
    }
}

/* Record the offending value of a failed item exactly as `n` holds it. */
static void set_err(emb_errval *e, const emb_num *n)
{
    switch (n->cls) {
    case NUM_INT:
        memcpy(&e->bits, &n->i, sizeof e->bits);
        e->kind = EMB_K_INT;
        break;
    case NUM_UINT:
        e->bits = n->u;
        e->kind = EMB_K_UINT;
        break;
    default:
        memcpy(&e->bits, &n->f, sizeof e->bits);
        e->kind = EMB_K_FLOAT;
        break;
    }
}

/* Inclusive signed range of an integer target (U64 handled apart). */
static void target_range(unsigned target, int64_t *lo, int64_t *hi)
{
    switch (target) {
    case EMB_C_I8: *lo = -128; *hi = 127; break;
    case EMB_C_U8: *lo = 0; *hi = 255; break;
    case EMB_C_I16: *lo = -32768; *hi = 32767; break;
    case EMB_C_U16: *lo = 0; *hi = 65535; break;
    case EMB_C_I32: *lo = INT32_MIN; *hi = INT32_MAX; break;
    case EMB_C_U32: *lo = 0; *hi = UINT32_MAX; break;
    case EMB_C_BCD16: *lo = 0; *hi = 9999; break;
    case EMB_C_BCD32: *lo = 0; *hi = 99999999; break;
    case EMB_C_DATETIME: *lo = EMB_MS_MIN; *hi = EMB_MS_MAX; break;
    case EMB_C_I24: *lo = -8388608; *hi = 8388607; break;
    case EMB_C_U24: *lo = 0; *hi = 16777215; break;
    default: *lo = INT64_MIN; *hi = INT64_MAX; break;
    }
}

/* Convert to an integer target, rounding half to even; never wraps. */
static int to_integer(emb_num *n, unsigned target, emb_errval *ev)
{
    if (n->cls == NUM_FLOAT) {
        double f = n->f;
        if (isnan(f)) {
            set_err(ev, n);
            return EMB_E_NAN;
        }
        double d = nearbyint(f); /* default rounding mode: to nearest, ties to even */
        if (target == EMB_C_U64) {
            if (!(d >= 0.0 && d < 18446744073709551616.0)) {
                set_err(ev, n);
                return EMB_E_RANGE;
            }
            n->cls = NUM_UINT;
            n->u = (uint64_t)d;
            return EMB_E_OK;
        }
        int64_t lo, hi;
        target_range(target, &lo, &hi);
        /* [-2^63, 2^63) is exact in double; narrower ranges are exact too. */
        bool ok = (target == EMB_C_I64) ? (d >= -9223372036854775808.0 && d < 9223372036854775808.0)
                                        : (d >= (double)lo && d <= (double)hi);
        if (!ok) {
            set_err(ev, n);
            return EMB_E_RANGE;
        }
        n->cls = NUM_INT;
        n->i = (int64_t)d;
        return EMB_E_OK;
    }
    if (target == EMB_C_U64) {
        if (n->cls == NUM_INT) {
            if (n->i < 0) {
                set_err(ev, n);
                return EMB_E_RANGE;
            }
            n->u = (uint64_t)n->i;
            n->cls = NUM_UINT;
        }
        return EMB_E_OK;
    }
    int64_t lo, hi;
    target_range(target, &lo, &hi);
    if (n->cls == NUM_UINT) {
        if (n->u > (uint64_t)hi) {
            set_err(ev, n);
            return EMB_E_RANGE;
        }
        n->i = (int64_t)n->u;
        n->cls = NUM_INT;
    }
    if (n->i < lo || n->i > hi) {
        set_err(ev, n);
        return EMB_E_RANGE;
    }
    return EMB_E_OK;
}

static int convert(emb_num *n, unsigned target, emb_errval *ev)
{
    switch (target) {
    case EMB_C_NONE:
        return EMB_E_OK;
    case EMB_C_BOOL:
        n->u = num_nonzero(n);
        n->cls = NUM_UINT;
        return EMB_E_OK;
    case EMB_C_F32: {
        double f = num_to_double(n);
        if (isfinite(f) && fabs(f) > FLT_MAX) {
            n->f = f;
            n->cls = NUM_FLOAT;
            set_err(ev, n);
            return EMB_E_RANGE;
        }
        n->f = f;
        n->cls = NUM_FLOAT;
        return EMB_E_OK;
    }
    case EMB_C_F64:
        n->f = num_to_double(n);
        n->cls = NUM_FLOAT;
        return EMB_E_OK;
    default:
        return to_integer(n, target, ev);
    }
}

/* The raw value of a fixed-size item at `offset` of data (registers, or bits for COIL). */
static int read_raw(const emb_item *it, const void *data, emb_num *n, emb_errval *ev)
{
    unsigned fl = it->flags;
    uint64_t v;
    n->cls = NUM_UINT;
    if (it->wire == EMB_W_COIL) {
        n->u = ((const uint8_t *)data)[it->offset] != 0;
        return EMB_E_OK;
    }
    const uint16_t *r = (const uint16_t *)data + it->offset;
    switch (it->wire) {
    case EMB_W_REGBOOL:
        n->u = r[0] != 0;
        return EMB_E_OK;
    case EMB_W_REGBIT:
        n->u = (gather(r, 1, fl) >> (it->bit & 15)) & 1;
        return EMB_E_OK;
    case EMB_W_U8:
        n->u = gather(r, 1, fl) & 0xFF;
        return EMB_E_OK;
    case EMB_W_I8:
        n->cls = NUM_INT;
        n->i = sext(gather(r, 1, fl) & 0xFF, 8);
        return EMB_E_OK;
    case EMB_W_U16:
        n->u = gather(r, 1, fl);
        return EMB_E_OK;
    case EMB_W_I16:
        n->cls = NUM_INT;
        n->i = sext(gather(r, 1, fl), 16);
        return EMB_E_OK;
    case EMB_W_U32:
        n->u = gather(r, 2, fl);
        return EMB_E_OK;
    case EMB_W_I32:
        n->cls = NUM_INT;
        n->i = sext(gather(r, 2, fl), 32);
        return EMB_E_OK;
    case EMB_W_I24: /* byte A (most significant of the 2 registers) unused: emb_codec.h */
        n->cls = NUM_INT;
        n->i = sext(gather(r, 2, fl) & 0xFFFFFF, 24);
        return EMB_E_OK;
    case EMB_W_U24:
        n->u = gather(r, 2, fl) & 0xFFFFFF;
        return EMB_E_OK;
    case EMB_W_U64:
        n->u = gather(r, 4, fl);
        return EMB_E_OK;
    case EMB_W_I64:
    case EMB_W_MS64:
        n->cls = NUM_INT;
        n->i = sext(gather(r, 4, fl), 64);
        return EMB_E_OK;
    case EMB_W_SEC32:
        n->cls = NUM_INT;
        n->i = (int64_t)gather(r, 2, fl) * 1000;
        return EMB_E_OK;
    case EMB_W_F32: {
        uint32_t w = (uint32_t)gather(r, 2, fl);
        float f;
        memcpy(&f, &w, sizeof f);
        n->cls = NUM_FLOAT;
        n->f = (double)f;
        return EMB_E_OK;
    }
    case EMB_W_F64:
        v = gather(r, 4, fl);
        n->cls = NUM_FLOAT;
        memcpy(&n->f, &v, sizeof n->f);
        return EMB_E_OK;
    case EMB_W_BCD16:
    case EMB_W_BCD32: {
        unsigned w = it->wire == EMB_W_BCD16 ? 1 : 2;
        v = gather(r, w, fl);
        int64_t d = bcd_value(v, 4 * w);
        if (d < 0) {
            ev->bits = v;
            ev->kind = EMB_K_UINT;
            return EMB_E_BCD;
        }
        n->u = (uint64_t)d;
        return EMB_E_OK;
    }
    default:
        return EMB_E_RANGE; /* unreachable for a checked plan */
    }
}

/* Copy nregs registers as bytes in format order; returns the reported length. */
static uint32_t read_bytes(const emb_item *it, const uint16_t *r, uint8_t *dst)
{
    unsigned q = it->nregs, fl = it->flags;
    for (unsigned k = 0; k < q; k++) {
        uint16_t w = reg_at(r, k, q, fl);
        dst[2 * k] = (uint8_t)(w >> 8);
        dst[2 * k + 1] = (uint8_t)w;
    }
    uint32_t len = 2u * q;
    if (fl & EMB_F_STRIP)
        while (len > 0 && dst[len - 1] == 0)
            len--;
    return len;
}

/* Store a converted value in its output group; returns the bits used for comparison. */
static uint64_t store(const emb_plan *p, const emb_item *it, const emb_num *n)
{
    uint64_t bits;
    switch (it->out) {
    case EMB_O_I64: {
        int64_t v = n->cls == NUM_INT ? n->i : n->cls == NUM_UINT ? sext(n->u, 64) : 0;
        p->out_i64[it->slot] = v;
        memcpy(&bits, &v, sizeof bits);
        return bits;
    }
    case EMB_O_U64: {
        uint64_t v = n->cls == NUM_UINT ? n->u : n->cls == NUM_INT ? (uint64_t)n->i : 0;
        p->out_u64[it->slot] = v;
        return v;
    }
    case EMB_O_F64: {
        double f = num_to_double(n);
        p->out_f64[it->slot] = f;
        memcpy(&bits, &f, sizeof bits);
        return bits;
    }
    default: { /* EMB_O_BOOL */
        bool b = num_nonzero(n);
        p->out_bool[it->slot] = b;
        return b;
    }
    }
}

/* 10^k, exact in a double for k <= 22. */
static const double emb_pow10[EMB_SF_MAX + 1] = {1e0, 1e1, 1e2, 1e3, 1e4, 1e5,
                                                 1e6, 1e7, 1e8, 1e9, 1e10};

/* The engineering units step of an EMB_F_EXT item (emb_codec.h) on its raw value `x`:
 * the engineering value and a status (EMB_E_RAW_RANGE leaves the caller to record the
 * raw value).  Out of line, on scalars, its result in registers: the decode loop keeps
 * its emb_num in registers (docs/engineering-units.md "Cost"). */
typedef struct emb_scaled {
    double value;
    int status; /* EMB_E_* */
} emb_scaled;

__attribute__((noinline)) static emb_scaled scale_ext(const emb_plan *p, const emb_item *it,
                                                      double x, emb_errval *ev)
{
    emb_scaled r = {0.0, EMB_E_OK};
    const emb_scale *s = &p->scales[it->aux];
    /* NaN is outside every range, and clamping has no nearest bound for it: Invalid
     * either way (docs/engineering-units.md: clamped values are held in engMin..engMax) */
    if ((s->range == EMB_R_INVALID && !(x >= s->raw_lo && x <= s->raw_hi)) ||
        (s->range == EMB_R_CLAMP && x != x)) {
        r.status = EMB_E_RAW_RANGE;
        return r;
    }
    if (s->sf >= 0) {
        int32_t sf = p->sf[s->sf];
        if (sf == EMB_SF_UNKNOWN || sf == EMB_SF_NI) {
            ev->bits = 0;
            ev->kind = EMB_K_NONE;
            r.status = sf == EMB_SF_NI ? EMB_E_SF_NI : EMB_E_SF_UNKNOWN;
            return r;
        }
        if (sf < -EMB_SF_MAX || sf > EMB_SF_MAX) {
            int64_t v = sf;
            memcpy(&ev->bits, &v, sizeof ev->bits);
            ev->kind = EMB_K_INT;
            r.status = EMB_E_SF_RANGE;
            return r;
        }
        x = sf >= 0 ? x * emb_pow10[sf] : x / emb_pow10[-sf];
    }
    if (it->flags & EMB_F_DIVIDE)
        x /= it->scale;
    else if (it->flags & EMB_F_MULTIPLY)
        x *= it->scale;
    x = (x - s->sub) * s->mul + s->add;
    if (s->range == EMB_R_CLAMP) { /* x is no NaN here (refused above) */
        if (x < s->eng_lo)
            x = s->eng_lo;
        else if (x > s->eng_hi)
            x = s->eng_hi;
    }
    r.value = x;
    return r;
}

/* Store the block's scale factors (emb_sfsrc) before any item is scaled with them. */
__attribute__((noinline)) static void store_factors(emb_plan *p, const uint16_t *regs,
                                                  uint32_t count)
{
    for (uint32_t k = 0; k < p->n_sf_src; k++) {
        const emb_item *it = &p->items[p->sf_src[k].item];
        if ((uint64_t)it->offset + 1 > count)
            continue; /* not in this reply: the last value stays */
        p->sf[p->sf_src[k].index] = (int32_t)sext(gather(regs + it->offset, 1, it->flags), 16);
    }
}

/* Whether a new value differs from the last reported one by more than the deadband.
 * Doubles: any NaN equals any NaN (its payload is no value), a NaN against a number is
 * a change, and so is -0.0 against 0.0 without a deadband.  Integers: the distance is
 * exact (a double would round 64-bit values and hide a move past the deadband). */
static bool value_changed(const emb_item *it, uint64_t now, uint64_t was)
{
    if (now == was)
        return false;
    double db = it->deadband;
    switch (it->out) {
    case EMB_O_F64: {
        double a, b;
        memcpy(&a, &now, sizeof a);
        memcpy(&b, &was, sizeof b);
        if (isnan(a) || isnan(b))
            return !(isnan(a) && isnan(b));
        return !(db > 0.0) || !(fabs(a - b) <= db); /* an infinity: a change */
    }
    case EMB_O_I64:
    case EMB_O_U64: {
        if (!(db > 0.0))
            return true;
        /* |now - was| < 2^64 in either group, so the unsigned difference is exact */
        bool up = it->out == EMB_O_I64 ? sext(now, 64) > sext(was, 64) : now > was;
        uint64_t d = up ? now - was : was - now;
        /* an integer d exceeds db exactly when it exceeds floor(db) */
        return db < 18446744073709551616.0 && d > (uint64_t)db;
    }
    default:
        return true;
    }
}

/* What a failed item's reason says besides its status: the offending value for BCD and
 * range errors; a missing register and a NaN have one reason each. */
static inline uint64_t err_key(int st, const emb_errval *ev)
{
    return (st == EMB_E_BCD || st == EMB_E_RANGE || st == EMB_E_RAW_RANGE
            || st == EMB_E_SF_RANGE) ? ev->bits : 0;
}

/* Whether n bytes at a and b are equal: inline, 8 bytes at a time (an item is 1 to 8
 * bytes but for BYTES; a libc memcmp call per item cost more than the compare). */
static inline bool same_bytes(const uint8_t *a, const uint8_t *b, uint32_t n)
{
    uint64_t x, y;

    for (; n >= 8; a += 8, b += 8, n -= 8) {
        memcpy(&x, a, 8);
        memcpy(&y, b, 8);
        if (x != y)
            return false;
    }
    for (; n > 0; n--)
        if (*a++ != *b++)
            return false;
    return true;
}

/* The bytes of a decode's data (count registers or bits) that the raw image keeps. */
static uint32_t raw_bytes(const emb_plan *p, uint32_t count)
{
    uint64_t n = p->bits ? count : 2u * (uint64_t)count;
    return n < p->raw_cap ? (uint32_t)n : p->raw_cap;
}

long emb_decode(emb_plan *p, const void *data, uint32_t count, int mode)
{
    const uint16_t *regs = data;
    uint32_t n_err = 0, n_chg = 0;
    /* the raw image (emb_codec.h): TRACK only, no factor table (a factor another block
     * read moves a value whose own registers did not) */
    int image = p->raw_last != NULL && mode == EMB_MODE_TRACK && p->n_sf == 0;
    uint32_t n_raw = image ? raw_bytes(p, count) : 0, unit = p->bits ? 1u : 2u;
    const uint8_t *was = image && p->raw_valid && count == p->raw_count ? p->raw_last : NULL;

    /* An item whose bytes are those of the last decode (a TRACK one, of the same count)
     * decodes as it did then, and that decode left it either reported (its state now
     * this value) or within its deadband of the state: it is not reported, its outputs
     * and status stay what they are.  The same bytes in all: nothing to do. */
    if (was && (n_raw == 0 || memcmp(data, was, n_raw) == 0)) {
        p->raw_reported = 0;
        return 0;
    }
    if (was && 2 * (uint64_t)p->raw_reported > p->n_items)
        was = NULL; /* most items moved last time: decode them all */
    p->raw_valid = 0;
    if (__builtin_expect(p->n_sf_src != 0, 0) && mode != EMB_MODE_VALUES)
        store_factors(p, regs, count);

    for (uint32_t i = 0; i < p->n_items; i++) {
        const emb_item *it = &p->items[i];
        uint64_t now = 0;
        int st;

        if (was && ((uint64_t)it->offset + it->nregs > count ||
                    same_bytes((const uint8_t *)data + unit * it->offset,
                               was + unit * it->offset, unit * it->nregs))) {
            if (p->status[i] != EMB_E_OK) /* missing then too, or the same failure */
                p->errs[n_err++] = i;
            continue;
        }
        /* nregs is the wire width for fixed-size items (emb_plan_check enforces it) */
        if ((uint64_t)it->offset + it->nregs > count) {
            st = EMB_E_MISSING;
            p->errval[i].bits = 0;
            p->errval[i].kind = EMB_K_NONE;
        } else if (it->wire == EMB_W_BYTES) {
            uint32_t len = read_bytes(it, regs + it->offset, p->out_bytes + it->aux);
            p->out_u64[it->slot] = len;
            now = len;
            st = EMB_E_OK;
        } else {
            emb_num n = {NUM_UINT, 0, 0, 0.0};
            st = read_raw(it, data, &n, &p->errval[i]);
            /* an EMB_F_EXT item has MULTIPLY or DIVIDE too (emb_plan_check): the items
             * without either pay this one test, as before engineering units */
            if (st == EMB_E_OK && (it->flags & (EMB_F_MULTIPLY | EMB_F_DIVIDE))) {
                if (__builtin_expect((it->flags & EMB_F_EXT) != 0, 0)) {
                    emb_scaled r = scale_ext(p, it, num_to_double(&n), &p->errval[i]);
                    st = r.status;
                    if (st == EMB_E_RAW_RANGE)
                        set_err(&p->errval[i], &n);
                    n.f = r.value;
                    n.cls = NUM_FLOAT;
                } else {
                    double x = num_to_double(&n);
                    n.f = (it->flags & EMB_F_DIVIDE) ? x / it->scale : x * it->scale;
                    n.cls = NUM_FLOAT;
                }
            }
            if (st == EMB_E_OK)
                st = convert(&n, it->target, &p->errval[i]);
            if (st == EMB_E_OK)
                now = store(p, it, &n);
        }
        p->status[i] = (uint8_t)st;
        if (st != EMB_E_OK)
            p->errs[n_err++] = i;
        if (mode == EMB_MODE_VALUES)
            continue;

        /* ALL reports every item but lists only those whose result is not exactly the
         * last reported one (failed items always), so the caller reuses the rest.  A
         * failed item keeps the key of its reason in `last` (emb_codec.h): a new
         * offending value is a new reason, reported like a new value. */
        bool report;
        if (st != EMB_E_OK)
            now = err_key(st, &p->errval[i]);
        if (st != p->last_status[i])
            report = true;
        else if (st != EMB_E_OK)
            report = mode == EMB_MODE_ALL || now != p->last[i];
        else if (it->wire == EMB_W_BYTES)
            report = memcmp(p->out_bytes + it->aux, p->last_bytes + it->aux, 2u * it->nregs) != 0;
        else if (mode == EMB_MODE_ALL)
            report = now != p->last[i];
        else
            report = value_changed(it, now, p->last[i]);
        if (report) {
            p->changed[n_chg++] = i;
            p->last_status[i] = (uint8_t)st;
            p->last[i] = now;
            if (st == EMB_E_OK && it->wire == EMB_W_BYTES)
                memcpy(p->last_bytes + it->aux, p->out_bytes + it->aux, 2u * it->nregs);
        }
    }
    p->n_errors = n_err;
    if (image) {
        if (n_raw)
            memcpy(p->raw_last, data, n_raw);
        p->raw_count = count;
        p->raw_valid = 1;
        p->raw_reported = n_chg;
    }
    return mode == EMB_MODE_VALUES ? (long)n_err : (long)n_chg;
}

void emb_reset(emb_plan *p)
{
    p->raw_valid = 0;
    if (p->n_items) /* memset(NULL, .., 0) is undefined: an empty plan may have no array */
        memset(p->last_status, EMB_E_UNREPORTED, p->n_items);
}

static bool group_fits(const emb_plan *p, const emb_item *it)
{
    switch (it->out) {
    case EMB_O_I64: return it->slot < p->n_i64;
    case EMB_O_U64: return it->slot < p->n_u64;
    case EMB_O_F64: return it->slot < p->n_f64;
    case EMB_O_BOOL: return it->slot < p->n_bool;
    case EMB_O_BYTES:
        return it->slot < p->n_u64 && (uint64_t)it->aux + 2u * it->nregs <= p->n_bytes;
    default: return false;
    }
}

static bool scale_fits(const emb_plan *p, const emb_item *it)
{
    if (it->wire == EMB_W_BYTES || it->wire == EMB_W_COIL || !p->scales || it->aux >= p->n_scales)
        return false;
    const emb_scale *s = &p->scales[it->aux];
    if (s->range > EMB_R_CLAMP || !isfinite(s->sub) || !isfinite(s->mul) || !isfinite(s->add))
        return false;
    if (s->range != EMB_R_NONE && !(s->raw_lo <= s->raw_hi && s->eng_lo <= s->eng_hi))
        return false;
    return s->sf < 0 || (p->sf && (uint32_t)s->sf < p->n_sf);
}

long emb_plan_check(const emb_plan *p)
{
    if (p->n_items > 0 && (!p->items || !p->status || !p->errval || !p->errs || !p->changed ||
                           !p->last || !p->last_status))
        return -1;
    if ((p->n_i64 && !p->out_i64) || (p->n_u64 && !p->out_u64) || (p->n_f64 && !p->out_f64) ||
        (p->n_bool && !p->out_bool) || (p->n_bytes && (!p->out_bytes || !p->last_bytes)))
        return -1;
    for (uint32_t i = 0; i < p->n_items; i++) {
        const emb_item *it = &p->items[i];
        bool ok = it->wire >= EMB_W_COIL && it->wire <= EMB_W_LAST && it->target <= EMB_C_LAST
                  && group_fits(p, it) && ((it->wire == EMB_W_COIL) == (p->bits != 0))
                  && ((it->wire == EMB_W_BYTES) == (it->out == EMB_O_BYTES));
        if (ok && it->wire == EMB_W_BYTES)
            ok = it->nregs >= 1 && it->target == EMB_C_NONE
                 && !(it->flags & (EMB_F_MULTIPLY | EMB_F_DIVIDE));
        else if (ok)
            ok = it->nregs == wire_width(it->wire) && it->bit <= 15;
        if (ok && (it->flags & (EMB_F_MULTIPLY | EMB_F_DIVIDE)))
            ok = isfinite(it->scale) && it->scale != 0.0;
        if (ok && (it->flags & EMB_F_EXT))
            ok = (it->flags & (EMB_F_MULTIPLY | EMB_F_DIVIDE)) && scale_fits(p, it);
        if (ok && p->raw_last) /* the raw image holds every byte the item reads */
            ok = ((uint64_t)it->offset + it->nregs) * (p->bits ? 1u : 2u) <= p->raw_cap;
        if (!ok)
            return (long)i + 1;
    }
    for (uint32_t k = 0; k < p->n_sf_src; k++) {
        const emb_sfsrc *src = &p->sf_src[k];
        if (!p->sf || src->item >= p->n_items || src->index >= p->n_sf
            || p->items[src->item].wire != EMB_W_I16)
            return -1;
    }
    return 0;
}

/* Inverse of gather: register k of the value (0 = most significant) to its place. */
static void scatter(uint64_t v, unsigned w, unsigned flags, uint16_t *regs)
{
    for (unsigned k = 0; k < w; k++) {
        uint16_t word = (uint16_t)(v >> (16 * (w - 1 - k)));
        regs[reg_index(k, w, flags)] = (flags & EMB_F_BYTE_SWAP) ? bswap16(word) : word;
    }
}

static int64_t bcd_pack(uint64_t v, unsigned digits)
{
    uint64_t out = 0;
    for (unsigned k = 0; k < digits; k++) {
        out |= (v % 10) << (4 * k);
        v /= 10;
    }
    return v == 0 ? (int64_t)out : -1;
}

int emb_encode(const emb_item *it, uint64_t raw, double fval, const uint8_t *bytes,
               uint32_t nbytes, uint16_t *regs, uint32_t max_regs)
{
    unsigned w = it->wire == EMB_W_BYTES ? it->nregs : wire_width(it->wire);
    unsigned fl = it->flags;
    if (w == 0 || w > max_regs)
        return -1;
    switch (it->wire) {
    case EMB_W_COIL:
    case EMB_W_REGBOOL:
        regs[0] = raw != 0;
        return 1;
    case EMB_W_U8:
    case EMB_W_I8:
        scatter(raw & 0xFF, 1, fl, regs);
        return 1;
    case EMB_W_BCD16:
    case EMB_W_BCD32: {
        int64_t packed = bcd_pack(raw, 4 * w);
        if (packed < 0)
            return -1;
        scatter((uint64_t)packed, w, fl, regs);
        return (int)w;
    }
    case EMB_W_F32: {
        if (isfinite(fval) && fabs(fval) > FLT_MAX)
            return -1;
        float f = (float)fval;
        uint32_t u;
        memcpy(&u, &f, sizeof u);
        scatter(u, 2, fl, regs);
        return 2;
    }
    case EMB_W_F64: {
        uint64_t u;
        memcpy(&u, &fval, sizeof u);
        scatter(u, 4, fl, regs);
        return 4;
    }
    case EMB_W_BYTES:
        if (nbytes > 2u * w || (nbytes && !bytes))
            return -1;
        for (unsigned k = 0; k < w; k++) {
            unsigned hi = 2 * k < nbytes ? bytes[2 * k] : 0;
            unsigned lo = 2 * k + 1 < nbytes ? bytes[2 * k + 1] : 0;
            uint16_t word = (uint16_t)(hi << 8 | lo);
            regs[reg_index(k, w, fl)] = (fl & EMB_F_BYTE_SWAP) ? bswap16(word) : word;
        }
        return (int)w;
    case EMB_W_I24:
    case EMB_W_U24: /* the unused byte A is written as 0 (emb_codec.h) */
        scatter(raw & 0xFFFFFF, 2, fl, regs);
        return 2;
    case EMB_W_REGBIT:
        return -1; /* a bit is written by read-modify-write of its register */
    default: /* 16/32/64-bit integers, SEC32, MS64: two's complement bits */
        scatter(w == 4 ? raw : raw & (((uint64_t)1 << (16 * w)) - 1), w, fl, regs);
        return (int)w;
    }
}
