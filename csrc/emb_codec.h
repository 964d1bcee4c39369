/* edgemodbus value codec: register blocks <-> values, with change detection.
 *
 * A read block is described once per plan by an array of emb_item (one per tag) inside an
 * emb_plan that also points at the typed output arrays and at the per-item state of the
 * last REPORTED result.  emb_decode() then decodes every item of a block in one call,
 * writes each value into the output array of its group (int64, uint64, double, bool) and
 * lists the items whose value, status or error reason changed.  Python materializes
 * objects only for those (or pulls whole arrays with ffi.unpack).
 *
 * Reentrant: no globals, nothing allocated; a plan is used by one thread at a time.
 *
 * Byte order (MODBUS Application Protocol v1.1b3, 4.2: registers are big-endian): a value
 * of w registers is rebuilt from the registers in word order (reversed when
 * EMB_F_WORD_SWAP) with the two bytes of each register swapped when EMB_F_BYTE_SWAP.
 * ABCD = neither, BADC = byte swap, CDAB = word swap, DCBA = both.  A 4-register value
 * also takes EMB_F_DWORD_SWAP, which swaps its two 2-register halves: register k of the
 * value (0 = most significant) is register k ^ (WORD_SWAP ? 3 : 0) ^ (DWORD_SWAP ? 2 : 0)
 * of the item, so (bytes in address order, A most significant) none = ABCDEFGH,
 * WORD_SWAP = GHEFCDAB, DWORD_SWAP = EFGHABCD ("first DWord low"), both = CDABGHEF,
 * and BYTE_SWAP swaps the bytes of each register of any of them.  Which flags an item
 * gets (a one-register value is swapped only when asked) is decided by its compiler,
 * src/edgemodbus/codec/spec.py; the codec applies them as given.
 */
#ifndef EMB_CODEC_H
#define EMB_CODEC_H

#include <stdbool.h>
#include <stdint.h>

/* Wire kinds: how the item's registers (or bit) become a raw value. */
#define EMB_W_COIL 1    /* coil / discrete input: one byte per bit, != 0 */
#define EMB_W_REGBOOL 2 /* first register != 0 */
#define EMB_W_REGBIT 3  /* bit `bit` (0 = LSB) of the register, after byte swap */
#define EMB_W_U8 4      /* low byte of the register after byte swap */
#define EMB_W_I8 5
#define EMB_W_U16 6
#define EMB_W_I16 7
#define EMB_W_U32 8
#define EMB_W_I32 9
#define EMB_W_U64 10
#define EMB_W_I64 11
#define EMB_W_F32 12
#define EMB_W_F64 13
#define EMB_W_BCD16 14  /* packed decimal, 4 digits */
#define EMB_W_BCD32 15  /* packed decimal, 8 digits, 2 registers */
#define EMB_W_SEC32 16  /* uint32 Unix seconds, reported as int64 milliseconds */
#define EMB_W_MS64 17   /* int64 Unix milliseconds */
#define EMB_W_BYTES 18  /* nregs registers as bytes in format order */
/* 24-bit integers in 2 registers: the 2-register value is rebuilt as for I32 (bytes
 * A B C D, A most significant, in the item's format) and its low 3 bytes B C D are the
 * value; byte A is unused: ignored when read, written as 0.  A sits in the high byte of
 * register 0 (ABCD), low byte of register 0 (BADC), high byte of register 1 (CDAB), low
 * byte of register 1 (DCBA).  README.md, "Int24 and UInt24", shows the table. */
#define EMB_W_I24 19    /* sign-extended from bit 23 */
#define EMB_W_U24 20
#define EMB_W_LAST 20

/* Item flags. */
#define EMB_F_BYTE_SWAP 0x01
#define EMB_F_WORD_SWAP 0x02
#define EMB_F_MULTIPLY 0x04 /* value = raw * scale (a double) */
#define EMB_F_DIVIDE 0x08   /* value = raw / scale: scale is 1/multiplier, exact for 0.1 etc. */
#define EMB_F_STRIP 0x10    /* BYTES: reported length excludes trailing NULs */
#define EMB_F_DWORD_SWAP 0x20 /* 4-register values: swap the two halves; else ignored */
#define EMB_F_EXT 0x40      /* engineering units: scaled by plan->scales[aux] (below);
                             * set with MULTIPLY (scale 1 for none) or DIVIDE, so that an
                             * item without a multiplier pays no test more than before */

/* Conversion targets (convertedDataType); NONE keeps the raw value's kind. */
#define EMB_C_NONE 0
#define EMB_C_BOOL 1
#define EMB_C_I8 2
#define EMB_C_U8 3
#define EMB_C_I16 4
#define EMB_C_U16 5
#define EMB_C_I32 6
#define EMB_C_U32 7
#define EMB_C_I64 8
#define EMB_C_U64 9
#define EMB_C_BCD16 10    /* an integer 0..9999 */
#define EMB_C_BCD32 11    /* an integer 0..99999999 */
#define EMB_C_F32 12      /* a double whose magnitude fits a float32 */
#define EMB_C_F64 13
#define EMB_C_DATETIME 14 /* milliseconds within years 1..9999 (Python datetime) */
#define EMB_C_I24 15      /* -8388608..8388607 */
#define EMB_C_U24 16      /* 0..16777215 */
#define EMB_C_LAST 16

/* Output groups: which typed array holds the item's result (at index `slot`). */
#define EMB_O_I64 0
#define EMB_O_U64 1
#define EMB_O_F64 2
#define EMB_O_BOOL 3
#define EMB_O_BYTES 4 /* bytes at out_bytes[aux], length in out_u64[slot] */

/* Per-item status. */
#define EMB_E_OK 0
#define EMB_E_MISSING 1 /* registers past the end of the response */
#define EMB_E_BCD 2     /* a BCD nibble above 9 */
#define EMB_E_NAN 3     /* NaN cannot become an integer */
#define EMB_E_RANGE 4   /* value outside the target type */
#define EMB_E_RAW_RANGE 5  /* EMB_F_EXT: raw value outside rawMin..rawMax (errval: it) */
#define EMB_E_SF_UNKNOWN 6 /* EMB_F_EXT: its scale factor not read yet */
#define EMB_E_SF_NI 7      /* EMB_F_EXT: scale factor 0x8000 (SunSpec: not implemented) */
#define EMB_E_SF_RANGE 8   /* EMB_F_EXT: scale factor outside -EMB_SF_MAX..EMB_SF_MAX
                            * (errval: it, an int) */
#define EMB_E_UNREPORTED 255 /* state only: nothing reported yet */

/* Kinds of a failed item's offending value (emb_errval.kind). */
#define EMB_K_NONE 0  /* no value: EMB_E_MISSING */
#define EMB_K_INT 1   /* bits hold an int64 (two's complement) */
#define EMB_K_UINT 2  /* bits hold a uint64 */
#define EMB_K_FLOAT 3 /* bits hold a double */

/* Decode modes. */
#define EMB_MODE_VALUES 0 /* decode only; state untouched; errs lists the failed items */
#define EMB_MODE_TRACK 1  /* decode, list changed items, remember what is reported */
#define EMB_MODE_ALL 2    /* decode, report every item, remember it; `changed` lists the
                           * items whose result differs exactly from the last report */

/* Engineering units (docs/engineering-units.md).  An item with EMB_F_EXT is scaled, in
 * this order: x = raw (as a double); x *= 10^sf (sf: its scale factor, read from another
 * item, SunSpec's *_SF; a negative sf divides by 10^-sf, so 0.1 steps are correctly
 * rounded); x *= scale (EMB_F_MULTIPLY) or x /= scale (EMB_F_DIVIDE);
 * x = (x - sub) * mul + add; with EMB_R_CLAMP x is then held in [eng_lo, eng_hi].  With a
 * range (EMB_R_INVALID or EMB_R_CLAMP) a raw value outside [raw_lo, raw_hi] (or NaN) is
 * EMB_E_RAW_RANGE under EMB_R_INVALID; under EMB_R_CLAMP a NaN is (no bound is nearest).  The result goes through the target conversion
 * as any value does. */
#define EMB_R_NONE 0
#define EMB_R_INVALID 1
#define EMB_R_CLAMP 2
#define EMB_SF_MAX 10              /* |sf| allowed */
#define EMB_SF_UNKNOWN INT32_MIN   /* a scale factor slot not read yet */
#define EMB_SF_NI (-32768)         /* 0x8000: SunSpec's "not implemented" */

typedef struct emb_scale {
    double sub, mul, add;
    double raw_lo, raw_hi; /* raw_lo <= raw_hi */
    double eng_lo, eng_hi; /* eng_lo <= eng_hi */
    int32_t sf;            /* index in plan->sf of the item's scale factor; -1: none */
    uint8_t range;         /* EMB_R_* */
} emb_scale;

/* An item whose raw Int16 (wire EMB_W_I16) is a scale factor: emb_decode stores it in
 * plan->sf[index] before it scales any item of the block (TRACK and ALL modes only: a
 * VALUES decode, a write's check, never changes what the device last reported). */
typedef struct emb_sfsrc {
    uint32_t item;
    uint32_t index;
} emb_sfsrc;

typedef struct emb_item {
    uint32_t offset;   /* first register (or bit) of the item inside the block */
    uint32_t aux;      /* BYTES: offset in out_bytes / last_bytes */
    uint32_t slot;     /* index in the output array of the item's group */
    uint16_t nregs;    /* registers read: the wire width, or the byte count / 2 for BYTES */
    uint8_t wire;      /* EMB_W_* */
    uint8_t flags;     /* EMB_F_* */
    uint8_t bit;       /* EMB_W_REGBIT: 0..15 */
    uint8_t target;    /* EMB_C_* */
    uint8_t out;       /* EMB_O_* */
    uint8_t reserved;
    double scale;      /* EMB_F_MULTIPLY: multiplier; EMB_F_DIVIDE: divisor */
    double deadband;   /* absolute, on the final value; 0 = any change */
} emb_item;

/* The value a failed item was rejected for, exact (a 64-bit integer is not rounded to a
 * double), so that its error reason names what the slave holds.  Which kind a status
 * carries is fixed by the item (its wire, multiplier and target), never by the data. */
typedef struct emb_errval {
    uint64_t bits;
    uint8_t kind;      /* EMB_K_* */
} emb_errval;

typedef struct emb_plan {
    const emb_item *items;
    uint32_t n_items;
    uint32_t bits;       /* nonzero: data holds one byte per bit (coils, discrete inputs) */
    /* outputs, rewritten by each decode */
    int64_t *out_i64;
    uint64_t *out_u64;
    double *out_f64;
    bool *out_bool;
    uint8_t *out_bytes;
    uint32_t n_i64, n_u64, n_f64, n_bool, n_bytes; /* array lengths, checked by emb_plan_check */
    uint8_t *status;     /* [n_items] EMB_E_* */
    emb_errval *errval;  /* [n_items] the offending value of a failed item */
    uint32_t *errs;      /* [n_items] indices of failed items */
    uint32_t *changed;   /* [n_items] indices of reported items */
    uint32_t n_errors;   /* written by each decode */
    /* state: the last reported result of each item */
    uint64_t *last;      /* [n_items] value bits; for a failed item the key of its reason:
                          * the errval bits for EMB_E_BCD and EMB_E_RANGE, else 0 */
    uint8_t *last_status; /* [n_items] EMB_E_*, EMB_E_UNREPORTED before the first report */
    uint8_t *last_bytes; /* [n_bytes] raw bytes of BYTES items */
    /* engineering units, all optional (NULL / 0 when no item of the plan is scaled) */
    const emb_scale *scales;  /* [n_scales], EMB_F_EXT items' aux indexes it */
    uint32_t n_scales;
    const emb_sfsrc *sf_src;  /* [n_sf_src] the block's scale factor items */
    uint32_t n_sf_src;
    int32_t *sf;              /* [n_sf] the device's scale factors, shared by its blocks'
                               * plans (a block read later in the pass, or in an earlier
                               * pass, sees what this one stored); EMB_SF_UNKNOWN unread */
    uint32_t n_sf;
    /* the raw image (optional: NULL, no skip): the data bytes the items read (raw_cap:
     * their reach, 2 bytes a register, 1 a bit) of the last decode, kept by a TRACK
     * decode; raw_valid: it is the data of the last decode, a TRACK one, and the state
     * is what that decode left.  A TRACK decode of the same count and the same bytes
     * would report nothing and leave every output as it is, so emb_decode skips it (a
     * block none of whose registers moved costs one memcmp, not a decode per item);
     * never for a plan whose items are scaled by a factor (another block's read may
     * have moved the factor) */
    uint8_t *raw_last;
    uint32_t raw_cap;
    uint32_t raw_count;
    uint32_t raw_valid;
    uint32_t raw_reported; /* items the last TRACK decode reported: when more than half
                            * were, the next one decodes every item without comparing
                            * (every value moving: the compare would only cost) */
} emb_plan;

/* 0 if every item fits the plan's arrays and is coherent; else 1 + the first bad item's
 * index (or -1 when the plan itself is unusable).  Call once per plan, not per decode. */
long emb_plan_check(const emb_plan *plan);

/* Decode `count` registers (or bits) at `data` for every item of a checked plan (a
 * TRACK decode of the raw image's data returns 0 at once: see emb_plan.raw_last).
 * Returns the number of items listed in plan->changed (TRACK: the reported ones, whose
 * status changed, whose value moved past the deadband (any NaN equals any NaN; 64-bit
 * integers compare exactly), or which still fail but for another offending value, so
 * with another reason; ALL: those whose result is not exactly the last reported one,
 * plus every failed item) or, for VALUES, the number of failed items.  plan->n_errors
 * and plan->errs always list the failed items. */
long emb_decode(emb_plan *plan, const void *data, uint32_t count, int mode);

/* Forget the reported state: the next TRACK decode reports every item. */
void emb_reset(emb_plan *plan);

/* Pack one raw value into the registers of `item` (its wire, nregs and byte/word swap):
 * integers (two's complement) and BCD digits as `raw`, floats as `fval`, BYTES as
 * `bytes` (NUL-padded).  Returns the register count written, or -1 if it cannot be
 * packed (BCD out of range, float32 overflow, too many bytes, a bit item, small buffer). */
int emb_encode(const emb_item *item, uint64_t raw, double fval, const uint8_t *bytes,
               uint32_t nbytes, uint16_t *regs, uint32_t max_regs);

#endif
