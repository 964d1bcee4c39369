"""Thin wrappers of the value codec (csrc/emb_codec.c).  The codec package describes
items as plain CodecItem tuples; CodecPlan lays them out over typed output arrays, owns
the C plan and state (allocated once per plan, never per decode) and turns C results
into Python objects."""

from __future__ import annotations

import operator
import struct
from array import array
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

from .block import Block
from .native import ffi, lib

CODEC_MODE_VALUES: int = lib.EMB_MODE_VALUES
CODEC_MODE_TRACK: int = lib.EMB_MODE_TRACK
CODEC_MODE_ALL: int = lib.EMB_MODE_ALL


def codec_constants(prefix: str) -> dict[str, int]:
    """The codec's C constants starting with ``EMB_<prefix>_``, keyed by the rest."""
    head = f"EMB_{prefix}_"
    return {name[len(head) :]: getattr(lib, name) for name in dir(lib) if name.startswith(head)}


class CodecItem(NamedTuple):
    """One item of a read block, as the C codec sees it (see csrc/emb_codec.h)."""

    offset: int
    nregs: int
    wire: int
    flags: int
    bit: int
    target: int
    out: int
    scale: float
    deadband: float


class CodecScale(NamedTuple):
    """An item's engineering units step (emb_scale, csrc/emb_codec.h): value =
    (raw x 10^sf x multiplier - sub) x mul + add; ``range`` EMB_R_* with the raw and
    engineering bounds; ``sf`` the index of its scale factor in the device's
    :class:`ScaleFactors` (-1: none)."""

    sub: float = 0.0
    mul: float = 1.0
    add: float = 0.0
    raw_lo: float = 0.0
    raw_hi: float = 0.0
    eng_lo: float = 0.0
    eng_hi: float = 0.0
    sf: int = -1
    range: int = 0


class ScaleFactors:
    """One device's scale factors (SunSpec ``*_SF`` items), by the name of the item that
    holds each: a C array shared by the plans of the device's blocks.  The plan of a
    block that reads a factor's item stores it (in C, on the line's worker); a plan
    whose items use it reads it there.  :meth:`get` reads it from any thread (an
    aligned int32: the last stored value, or None before the first read).

    Compared by identity: specs of two devices never share one."""

    __slots__ = ("_table", "names")

    def __init__(self, names: Sequence[str]) -> None:
        self.names: dict[str, int] = {name: k for k, name in enumerate(dict.fromkeys(names))}
        self._table = ffi.new("int32_t[]", max(len(self.names), 1))
        for k in range(len(self.names)):
            self._table[k] = lib.EMB_SF_UNKNOWN

    def index(self, name: str) -> int:
        """The slot of ``name``'s factor (KeyError if it is not one)."""
        return self.names[name]

    def get(self, name: str) -> int | None:
        """The last value read of ``name``'s factor (its raw Int16), None before."""
        v = int(self._table[self.names[name]])
        return None if v == lib.EMB_SF_UNKNOWN else v

    def __repr__(self) -> str:
        return f"ScaleFactors({list(self.names)})"


def _fill_item(dst: Any, item: CodecItem, slot: int, aux: int) -> None:
    try:
        dst.offset = item.offset
        dst.nregs = item.nregs
        dst.wire = item.wire
        dst.flags = item.flags
        dst.bit = item.bit
        dst.target = item.target
        dst.out = item.out
        dst.scale = item.scale
        dst.deadband = item.deadband
        dst.slot = slot
        dst.aux = aux
    except (OverflowError, TypeError) as exc:
        raise ValueError(f"codec: {item} does not fit the C item ({exc})") from None


class CodecLayout:
    """The immutable part of a compiled read block: the C items, the engineering units
    steps, where each item's value lands and how the values list is assembled.

    ``posts[i]`` (or None) turns item i's raw result into its Python value (bytes for
    BYTES items).  ``scales[i]`` (or None; no list: no item is) is item i's engineering
    units step; ``sources`` the (item index, factor slot) of the items that hold a
    scale factor of ``factors`` (needed by both).  Never written after it is built, so
    the plans of many devices whose blocks hold the same items share one (C reads the
    items through a const pointer, csrc/emb_codec.h); each :class:`CodecPlan` has the
    per-device arrays and change-tracking state."""

    __slots__ = ("__weakref__", "_citems", "_scales", "_sources", "bits", "factors",
                 "getter", "group", "n_bytes", "n_items", "raw_bytes", "runs", "sizes",
                 "slot", "special", "special_rest", "special_runs")

    def __init__(
        self,
        bits: bool,
        items: Sequence[CodecItem],
        posts: Sequence[Callable[[Any], object] | None],
        scales: Sequence[CodecScale | None] = (),
        factors: ScaleFactors | None = None,
        sources: Sequence[tuple[int, int]] = (),
    ) -> None:
        n = len(items)
        o_bytes = lib.EMB_O_BYTES
        group_of = [it.out for it in items]
        sizes = [0, 0, 0, 0]  # i64, u64 (also BYTES lengths), f64, bool
        slots: list[int] = []
        auxes: list[int] = []
        n_bytes = 0
        for it, group in zip(items, group_of, strict=True):
            g = lib.EMB_O_U64 if group == o_bytes else group
            if not 0 <= g < 4:
                raise ValueError(f"codec item at offset {it.offset}: bad output group {it.out}")
            slots.append(sizes[g])
            sizes[g] += 1
            if group == o_bytes:
                auxes.append(n_bytes)
                n_bytes += 2 * it.nregs
            else:
                auxes.append(0)
        self.bits = bits
        self.n_items = n
        self.n_bytes = n_bytes
        # the data bytes the items read: the plan's raw image (csrc/emb_codec.h
        # raw_last); none past any Modbus read (items C will refuse, or no block)
        reach = max((it.offset + it.nregs for it in items), default=0)
        reach = reach if bits else 2 * reach
        self.raw_bytes = reach if reach <= _RAW_MAX else 0
        self.factors = factors
        self._citems = ffi.new("emb_item[]", max(n, 1))
        for k, it in enumerate(items):
            _fill_item(self._citems[k], it, slots[k], auxes[k])
        self._scales: Any = ffi.NULL
        self._sources: Any = ffi.NULL
        try:
            self._lay_out(scales, sources)
        except (OverflowError, TypeError) as exc:
            raise ValueError(f"codec: scaling steps do not fit the C plan ({exc})") from None
        ni, nu, nf, nb = sizes
        self.sizes = (ni, nu, nf, nb)
        # Item k's value is lists[src][idx]: src 0..3 the groups, 4 the post-processed items.
        # Per item (a layout is held once per distinct block, but devices of distinct
        # address lists hold one per tag) its group (0..3, or 4 for special[j],
        # post-processed or bytes) in a bytes and its slot in that group (or j) in an
        # int array: a byte and two or four bytes an item, no object of its own (only
        # the special items have a tuple each, which values() reads fastest).
        special: list[tuple[int, int, int, Callable[[Any], object] | None, int]] = []
        place: list[tuple[int, int]] = []
        for k, group in enumerate(group_of):
            g = lib.EMB_O_U64 if group == o_bytes else group
            aux = auxes[k] if group == o_bytes else -1
            post = posts[k]
            if post is None and aux < 0:
                place.append((g, slots[k]))
            else:
                place.append((4, len(special)))
                special.append((k, g, slots[k], post, aux))
        special, place = self._group_special(special, place)
        self.group = bytes(src for src, _ in place)
        self.slot = array("H" if n <= 0xFFFF else "I", [idx for _, idx in place])
        self.special = special  # a tuple each: values() iterates them on every decode
        # Assemble the values list from runs of consecutive slots (a few list slices for
        # the usual blocks of same-typed items), or with one itemgetter when interleaved.
        runs: list[list[int]] = []
        for src, idx in place:
            if runs and runs[-1][0] == src and runs[-1][2] == idx:
                runs[-1][2] += 1
            else:
                runs.append([src, idx, idx + 1])
        lengths = (ni, nu, nf, nb, len(special))
        self.runs: list[tuple[int, int, int, bool]] = []
        self.getter: Callable[[list[object]], Any] | None = None
        if len(runs) > max(4, n // 8):
            base = (0, ni, ni + nu, ni + nu + nf, ni + nu + nf + nb)
            self.getter = operator.itemgetter(*[base[src] + idx for src, idx in place])
        else:
            self.runs = [(src, a, b, a == 0 and b == lengths[src]) for src, a, b in runs]

    def _group_special(
        self, special: list[tuple[int, int, int, Callable[[Any], object] | None, int]],
        place: list[tuple[int, int]],
    ) -> tuple[list[tuple[int, int, int, Callable[[Any], object] | None, int]],
               list[tuple[int, int]]]:
        """Order the special items so that those of one group and one post step (no
        bytes) come together, first: ``special_runs`` holds each such run (group, post
        step, the slots in the group), which values() converts with two maps when no item
        failed, not a loop step per item (the Float items' Float32, mostly); the bytes
        items follow (``special_rest``).  ``place`` renumbered to the new order."""
        runs: dict[tuple[int, int], tuple[Callable[[Any], object] | None, list[int]]] = {}
        rest: list[int] = []
        for j, (_, g, _, post, aux) in enumerate(special):
            if aux < 0:
                runs.setdefault((g, id(post)), (post, []))[1].append(j)
            else:
                rest.append(j)
        order = [j for _, js in runs.values() for j in js] + rest
        new_of = {old: new for new, old in enumerate(order)}
        self.special_runs = [
            ((g, post, array("H", [special[j][2] for j in js])))
            for (g, _), (post, js) in runs.items()]
        ordered = [special[j] for j in order]
        self.special_rest = ordered[len(order) - len(rest):]
        return ordered, [(4, new_of[idx]) if src == 4 else (src, idx) for src, idx in place]

    def _lay_out(self, scales: Sequence[CodecScale | None],
                 sources: Sequence[tuple[int, int]]) -> None:
        """Lay out the engineering units steps (EMB_F_EXT items' aux) and the scale
        factor items of the block."""
        used = [(k, sc) for k, sc in enumerate(scales) if sc is not None]
        if used:
            self._scales = ffi.new("emb_scale[]", len(used))
            for j, (k, sc) in enumerate(used):
                dst = self._scales[j]
                (dst.sub, dst.mul, dst.add, dst.raw_lo, dst.raw_hi, dst.eng_lo, dst.eng_hi,
                 dst.sf, dst.range) = sc
                citem = self._citems[k]
                citem.flags |= lib.EMB_F_EXT
                if not citem.flags & (lib.EMB_F_MULTIPLY | lib.EMB_F_DIVIDE):
                    citem.flags |= lib.EMB_F_MULTIPLY  # by 1.0: EXT rides on its test
                    citem.scale = 1.0
                citem.aux = j
        if sources:
            self._sources = ffi.new("emb_sfsrc[]", len(sources))
            for j, (k, index) in enumerate(sources):
                self._sources[j].item = k
                self._sources[j].index = index

    def bind(self, plan: Any) -> None:
        """Point the C plan ``plan`` at the items, steps and factor table."""
        plan.items = self._citems
        plan.n_items = self.n_items
        plan.bits = 1 if self.bits else 0
        if self._scales != ffi.NULL:
            plan.scales, plan.n_scales = self._scales, len(self._scales)
        if self._sources != ffi.NULL:
            plan.sf_src, plan.n_sf_src = self._sources, len(self._sources)
        if self.factors is not None:
            plan.sf, plan.n_sf = self.factors._table, len(self.factors.names)


class CodecPlan:
    """A compiled read block of one device: a :class:`CodecLayout` (shared), its typed
    output arrays and change-tracking state (its own).

    ``CodecPlan(bits, items, posts, ...)`` compiles a layout of its own (see
    :class:`CodecLayout` for the arguments); :meth:`of` makes a plan over a layout that
    other plans may share.  Used by one thread at a time, like the block it decodes.

    Small, as a gateway holds one per read block: the C plan and every array it points
    at are one allocation (:data:`_REGIONS`), seen from Python through memoryviews of
    that one buffer; no instance dict (docs/item-store.md, "Memory").
    """

    __slots__ = ("_arrays", "_bytes_view", "_f64", "_getter", "_group", "_mem", "_plan",
                 "_runs", "_sizes", "_slot", "_special", "_view_bool", "_view_i64",
                 "_view_u64", "bits", "layout", "n_items", "status_view")

    def __init__(
        self,
        bits: bool,
        items: Sequence[CodecItem],
        posts: Sequence[Callable[[Any], object] | None],
        scales: Sequence[CodecScale | None] = (),
        factors: ScaleFactors | None = None,
        sources: Sequence[tuple[int, int]] = (),
    ) -> None:
        self._bind(CodecLayout(bits, items, posts, scales, factors, sources))

    @classmethod
    def of(cls, layout: CodecLayout) -> CodecPlan:
        """A new plan (fresh state: every item unreported) over ``layout``."""
        plan = cls.__new__(cls)
        plan._bind(layout)
        return plan

    def _bind(self, layout: CodecLayout) -> None:
        n = layout.n_items
        ni, nu, nf, nb = self._sizes = layout.sizes
        counts = {"i64": ni, "u64": nu, "f64": nf, "last": n, "errval": n, "errs": n,
                  "changed": n, "bool": nb, "status": n, "last_status": n,
                  "bytes": layout.n_bytes, "last_bytes": layout.n_bytes,
                  "raw": layout.raw_bytes}
        at, size = _regions(counts)
        # one zeroed allocation, 8-byte aligned: the emb_plan first, then its arrays
        mem = ffi.new("uint64_t[]", size // 8)
        base = ffi.cast("uint8_t *", mem)
        plan = ffi.cast("emb_plan *", mem)
        layout.bind(plan)
        ptr = {name: ffi.cast(_REGIONS[name][0] + " *", base + at[name]) for name in at}
        plan.out_i64, plan.n_i64 = ptr["i64"], ni
        plan.out_u64, plan.n_u64 = ptr["u64"], nu
        plan.out_f64, plan.n_f64 = ptr["f64"], nf
        plan.out_bool, plan.n_bool = ptr["bool"], nb
        plan.out_bytes, plan.n_bytes = ptr["bytes"], layout.n_bytes
        plan.status, plan.errval = ptr["status"], ptr["errval"]
        plan.errs, plan.changed = ptr["errs"], ptr["changed"]
        plan.last, plan.last_status = ptr["last"], ptr["last_status"]
        plan.last_bytes = ptr["last_bytes"]
        if layout.raw_bytes:
            plan.raw_last, plan.raw_cap = ptr["raw"], layout.raw_bytes
        bad = lib.emb_plan_check(plan)
        if bad:
            where = f"item {bad - 1}" if bad > 0 else "the plan"
            raise ValueError(f"codec: {where} is inconsistent (a bug in the item compiler)")
        lib.emb_reset(plan)
        self._mem = mem  # owns the memory the plan and every pointer below point into
        self._plan = plan
        self.layout = layout
        self.bits = layout.bits
        self.n_items = n
        view = memoryview(ffi.buffer(mem))

        def typed(name: str, code: str) -> memoryview:
            count = counts[name]
            if not count:
                return _EMPTY_VIEWS[code]  # an empty group shares one empty view
            start = at[name]
            return view[start:start + count * _REGIONS[name][1]].cast(code)

        self.status_view = typed("status", "B")  # EMB_E_* of each item
        # Typed views that turn the integer and bool arrays into lists at C speed (for
        # doubles ffi.unpack is the faster one: a pointer is kept for it).
        self._view_i64 = typed("i64", "q")
        self._view_u64 = typed("u64", "Q")
        self._view_bool = typed("bool", "?")
        self._f64 = ptr["f64"]
        self._bytes_view = typed("bytes", "B")
        self._arrays = (self._view_i64, self._view_u64, self._f64, self._view_bool)
        # the layout's, read by values() and value() on every decode
        self._group, self._slot, self._special = layout.group, layout.slot, layout.special
        self._runs, self._getter = layout.runs, layout.getter

    def decode(self, block: Block, mode: int) -> int:
        """Run the C decode over ``block``; returns the reported (or failed) item count."""
        if block.bits != self.bits:
            kind = "bits" if self.bits else "registers"
            raise ValueError(f"codec: this block decoder expects {kind}")
        return int(lib.emb_decode(self._plan, block._ptr, block.count, mode))

    @property
    def n_errors(self) -> int:
        return int(self._plan.n_errors)

    def errors(self) -> list[int]:
        """Indices of the items that failed in the last decode."""
        plan = self._plan
        return ffi.unpack(plan.errs, plan.n_errors)

    def changed(self, n: int) -> list[int]:
        """Indices of the ``n`` items reported by the last TRACK/ALL decode."""
        return ffi.unpack(self._plan.changed, n)

    def status(self, index: int) -> int:
        return self.status_view[index]

    def errval(self, index: int) -> int | float | None:
        """The value item ``index`` failed for in the last decode, exact: an int (64-bit
        values are not rounded), a float, or None (a register missing from the reply)."""
        ev = self._plan.errval[index]
        bits, kind = int(ev.bits), int(ev.kind)
        if kind == lib.EMB_K_INT:
            return bits - (1 << 64) if bits >> 63 else bits
        if kind == lib.EMB_K_UINT:
            return bits
        if kind == lib.EMB_K_FLOAT:
            return float(struct.unpack("=d", struct.pack("=Q", bits))[0])
        return None

    def values(self) -> list[object]:
        """Every item's value from the last decode (None where it failed)."""
        lists: list[list[Any]] = [
            self._view_i64.tolist(),
            self._view_u64.tolist(),
            ffi.unpack(self._f64, self._sizes[2]),
            self._view_bool.tolist(),
        ]
        extra: list[object] = []
        if self._special:
            status = self.status_view
            buf = self._bytes_view
            special = self._special
            if not self._plan.n_errors:  # every item good: a run of special items at once
                for g, post, slots in self.layout.special_runs:
                    got = map(lists[g].__getitem__, slots)
                    extra += got if post is None else map(post, got)
                special = self.layout.special_rest
            for k, g, slot, post, aux in special:
                if status[k]:
                    extra.append(None)
                    continue
                raw = lists[g][slot]
                if aux >= 0:
                    raw = buf[aux : aux + raw].tobytes()
                extra.append(raw if post is None else post(raw))
        lists.append(extra)
        out: list[object]
        if self._getter is not None:
            out = list(self._getter(lists[0] + lists[1] + lists[2] + lists[3] + extra))
        else:
            runs = self._runs
            if len(runs) == 1 and runs[0][3]:
                out = lists[runs[0][0]]
            else:
                out = []
                for src, a, b, whole in runs:
                    out += lists[src] if whole else lists[src][a:b]
        if self._plan.n_errors:
            for k in self.errors():
                out[k] = None
        return out

    def value(self, index: int) -> object:
        """One item's value from the last decode (call only when its status is OK)."""
        group = self._group[index]
        if group < 4:
            return self._arrays[group][self._slot[index]]
        _, g, slot, post, aux = self._special[self._slot[index]]
        raw = self._arrays[g][slot]
        if aux >= 0:
            raw = self._bytes_view[aux : aux + raw].tobytes()
        return raw if post is None else post(raw)

    def reset(self) -> None:
        """Forget the reported state: the next TRACK decode reports every item."""
        lib.emb_reset(self._plan)


# The arrays of a plan (csrc/emb_codec.h emb_plan), in the order they are laid out after
# the emb_plan in its one allocation (widest first: each starts aligned): C type, size.
_REGIONS: dict[str, tuple[str, int]] = {
    "i64": ("int64_t", 8), "u64": ("uint64_t", 8), "f64": ("double", 8),
    "last": ("uint64_t", 8), "errval": ("emb_errval", ffi.sizeof("emb_errval")),
    "errs": ("uint32_t", 4), "changed": ("uint32_t", 4), "bool": ("_Bool", 1),
    "status": ("uint8_t", 1), "last_status": ("uint8_t", 1), "bytes": ("uint8_t", 1),
    "last_bytes": ("uint8_t", 1), "raw": ("uint8_t", 1),
}


def _regions(counts: Mapping[str, int]) -> tuple[dict[str, int], int]:
    """Where each array of :data:`_REGIONS` starts in a plan's allocation (``counts``
    elements each; at least one, as C is never handed an empty array), and the
    allocation's size (a multiple of 8)."""
    at: dict[str, int] = {}
    end = ffi.sizeof("emb_plan")
    for name, (ctype, size) in _REGIONS.items():
        end = -(-end // ffi.alignof(ctype)) * ffi.alignof(ctype)
        at[name] = end
        end += max(counts[name], 1) * size
    return at, -(-end // 8) * 8


# The largest raw image a plan keeps, in bytes: above the largest read's data (2000 bits
# as a byte each, 125 registers: Modbus Application Protocol v1.1b3, 6.1-6.4).
_RAW_MAX = 4096

_EMPTY_VIEWS = {code: memoryview(b"").cast(code) for code in "qQ?B"}


def codec_encode(item: CodecItem, raw: int, fval: float, data: bytes) -> list[int]:
    """Pack a raw value into the item's registers (integers as two's complement ``raw``,
    floats as ``fval``, strings/binary as ``data``); ValueError if C refuses it."""
    citem = ffi.new("emb_item *")
    _fill_item(citem, item, 0, 0)
    size = max(item.nregs, 4)
    regs = ffi.new("uint16_t[]", size)
    n = lib.emb_encode(citem, raw & 0xFFFF_FFFF_FFFF_FFFF, fval, data, len(data), regs, size)
    if n < 0:
        raise ValueError(f"codec: cannot pack raw value {raw!r}/{fval!r}/{data!r}")
    return ffi.unpack(regs, n)
