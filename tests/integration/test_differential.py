"""Differential test of the whole read path: a value reported Ok is never wrong.

Hypothesis draws an address list (every data type and byte order: dataFormat, byteSwap16
and dataFormat64 per device and per item; Smart Cast quantities, multipliers and
converted types, register bits, coils and discrete inputs, Strings and Binaries longer
than a block, gaps, overlapping items, disabled items; engineering units: offset, range
scaling with and without clamp, docs/engineering-units.md) and planner settings (block
sizes, merge gap, continuous blocks, report mode), puts random registers and bits into a
slave of our simulator (``edgemodbus.sim``: in process, so its registers are set
directly and at once), and runs a DriverModbusRtu against it for several cycles. At the
end of every cycle the registers change (and the address list may be replaced by
``update_addresses``), so change detection and re-planning are exercised; some examples
add illegal-address ranges (exception 02, which bisects blocks), other exception codes,
or wire faults, and some give items scan rates of their own (``readCycle``), so that a
cycle reads only the blocks due.

Every item that is Ok - at the end of every cycle (snapshot publisher with a 1 ms
interval, called by the worker when a cycle ends), in every ``address_updated_callback``
and every ``addresses_updated_callback`` - must hold exactly the value that
:func:`reference` gives for the slave's registers.  ``reference`` is written here from
the documented semantics (docs/device-files.md "Data types", the codec module's notes) with
``struct``; it does not use our codec.  Items it calls invalid (bad BCD, a conversion
out of range, an address the slave refuses) must not be Ok.  Without faults, every
valid item must be Ok at the end of each cycle, and a batch holds an item at most once.
Where items have rates of their own, an item not due in a cycle holds what it read in an
earlier one: there an Ok value must be the reference of the registers as they are or as
they were at the end of an earlier cycle, and an item is missing only if it was valid
all along.

The example count is bounded for ``make test``: EDGEMODBUS_DIFF_EXAMPLES (default 20);
``make soak`` raises it.
"""

from __future__ import annotations

import copy
import math
import os
import random
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from datetime import datetime, timedelta, timezone
from typing import Any

import pytest
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st

import edgemodbus as em
from edgemodbus.codec import Float32
from edgemodbus.datatypes import ItemStatus
from edgemodbus.sim import Simulator
from tests.peers import free_port
from tests.waiting import wait_for

EXAMPLES = int(os.environ.get("EDGEMODBUS_DIFF_EXAMPLES", "20"))
DIFF = settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                           HealthCheck.filter_too_much, HealthCheck.function_scoped_fixture],
)
CYCLES = 5  # cycles checked per example
# the hang guard of a whole test (pytest-timeout): an example that stops making cycles
# fails by itself after 60 s (run's wait_for); an example with wire faults costs up to
# ~10 s on a loaded 2-core machine (each fault a drain or a timeout of 50-150 ms), and
# 20 of them once took 161 s there: 120 s cut a test that was making progress
HANG_GUARD = max(600, 30 * EXAMPLES)
REG_SPAN = 320  # items live in registers 0..REG_SPAN-1 of hr and ir
BIT_SPAN = 160  # and bits 0..BIT_SPAN-1 of coils and discrete inputs
FLT_MAX = 3.4028234663852886e38
EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)

# -- the reference decoder ----------------------------------------------------------------

# (kind, registers) a fixed-size type is read with, by quantity: a quantity smaller than
# the type needs reads the widest smaller value (Smart Cast), None is the type's default
WIDTHS: dict[str, dict[int | None, tuple[str, int]]] = {
    "Boolean": {None: ("bool", 1), 1: ("bool", 1)},
    "Byte": {None: ("u8", 1), 1: ("u8", 1)},
    "Sbyte": {None: ("i8", 1), 1: ("i8", 1)},
    "Char": {None: ("char", 1), 1: ("char", 1)},
    "Int16": {None: ("i16", 1), 1: ("i16", 1)},
    "UInt16": {None: ("u16", 1), 1: ("u16", 1)},
    "BCD16": {None: ("bcd", 1), 1: ("bcd", 1)},
    "Int24": {None: ("i24", 2), 2: ("i24", 2), 1: ("i16", 1)},
    "UInt24": {None: ("u24", 2), 2: ("u24", 2), 1: ("u16", 1)},
    "Int32": {None: ("i32", 2), 2: ("i32", 2), 1: ("i16", 1)},
    "UInt32": {None: ("u32", 2), 2: ("u32", 2), 1: ("u16", 1)},
    "Float": {None: ("f32", 2), 2: ("f32", 2), 1: ("i16", 1)},
    "BCD32": {None: ("bcd", 2), 2: ("bcd", 2), 1: ("bcd", 1)},
    "Int64": {None: ("i64", 4), 4: ("i64", 4), 2: ("i32", 2), 1: ("i16", 1)},
    "UInt64": {None: ("u64", 4), 4: ("u64", 4), 2: ("u32", 2), 1: ("u16", 1)},
    "Double": {None: ("f64", 4), 4: ("f64", 4), 2: ("f32", 2), 1: ("i16", 1)},
    "DateTime": {None: ("sec", 2), 2: ("sec", 2), 4: ("ms", 4)},
    "Timestamp": {None: ("sec", 2), 2: ("sec", 2), 4: ("ms", 4)},
}
STRUCT = {"i16": ">h", "u16": ">H", "i32": ">i", "u32": ">I", "i64": ">q", "u64": ">Q",
          "f32": ">f", "f64": ">d", "sec": ">I", "ms": ">q"}
NUMERIC = {"Byte", "Sbyte", "Int16", "UInt16", "Int24", "UInt24", "Int32", "UInt32", "Int64",
           "UInt64", "BCD16", "BCD32", "Float", "Double"}
INT_RANGE = {
    "Byte": (0, 0xFF), "Sbyte": (-0x80, 0x7F), "Int16": (-0x8000, 0x7FFF),
    "UInt16": (0, 0xFFFF), "Int24": (-(1 << 23), (1 << 23) - 1), "UInt24": (0, (1 << 24) - 1),
    "Int32": (-(1 << 31), (1 << 31) - 1), "UInt32": (0, (1 << 32) - 1),
    "Int64": (-(1 << 63), (1 << 63) - 1), "UInt64": (0, (1 << 64) - 1),
    "BCD16": (0, 9999), "BCD32": (0, 99_999_999),
}
UNCONVERTED = {"Char", "String", "Binary", "DateTime", "Timestamp"}
TARGETS = ["Boolean", *INT_RANGE, "Float", "Double", "String"]
MULTIPLIERS = [0.1, 0.01, 0.001, 0.5, 0.25, 2.0, 10.0, -1.0, 1.5]
OFFSETS = [-40.0, 0.5, 273.15, -1e4, 3.0]
RAW_ENDS = [0.0, 4000.0, 20000.0, 27648.0, -100.0, 65535.0, 10.0, 1e9]
ENG_ENDS = [0.0, 4.0, 20.0, 100.0, -50.5, 1e3]
DECIMAL_STEPS = {0.1: 10, 0.01: 100, 0.001: 1000}  # a multiplier 1/10^k divides by 10^k
FORMATS = ["ABCD", "BADC", "CDAB", "DCBA"]
# 64-bit orders: the value's bytes A..H as the registers hold them by address
FORMATS64 = ["ABCDEFGH", "BADCFEHG", "CDABGHEF", "DCBAHGFE", "EFGHABCD", "FEHGBADC",
             "GHEFCDAB", "HGFEDCBA"]
STRETCHED = {"ABCD": "ABCDEFGH", "BADC": "BADCFEHG", "CDAB": "GHEFCDAB", "DCBA": "HGFEDCBA"}
BAD = object()  # the reference's verdict "invalid": the item must not be Ok


@dataclass(frozen=True)
class Spec:
    """One configured item as the test sees it."""

    name: str
    area: str  # hr, ir, coil, di
    offset: int
    dtype: str
    bit: int | None = None
    quantity: int | None = None
    fmt: str | None = None  # the item's override of the device's dataFormat
    swap16: bool | None = None  # ... of the device's byteSwap16
    fmt64: str | None = None  # ... of the device's dataFormat64
    multiplier: float = 1.0
    converted: str | None = None
    encoding: str | None = None
    enabled: bool = True
    rate: int | None = None  # the item's readCycle (ms), None: the device's
    add: float = 0.0  # the item's "offset" key (engineering units)
    span: tuple[float, float, float, float] | None = None  # rawMin, rawMax, engMin, engMax
    clamp: bool = False

    @property
    def scaled(self) -> bool:
        return self.multiplier != 1 or self.add != 0 or self.span is not None

    @property
    def size(self) -> int:
        if self.area in ("coil", "di") or self.bit is not None:
            return 1
        if self.quantity is not None:
            return self.quantity
        return WIDTHS[self.dtype][None][1]

    @property
    def address(self) -> str:
        text = f"{self.area}:{self.offset}"
        return text if self.bit is None else f"{text}.{self.bit}"

    def as_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "address": self.address,
                               "deviceDataType": self.dtype, "isEnable": self.enabled}
        if self.quantity is not None:
            out["quantity"] = self.quantity
        if self.fmt is not None:
            out["dataFormat"] = self.fmt
        if self.swap16 is not None:
            out["byteSwap16"] = self.swap16
        if self.fmt64 is not None:
            out["dataFormat64"] = self.fmt64
        if self.multiplier != 1:
            out["dataMultiplier"] = self.multiplier
        if self.converted is not None:
            out["convertedDataType"] = self.converted
        if self.encoding is not None:
            out["encoding"] = self.encoding
        if self.rate is not None:
            out["readCycle"] = self.rate
        if self.add:
            out["offset"] = self.add
        if self.span is not None:
            out.update(zip(("rawMin", "rawMax", "engMin", "engMax"), self.span, strict=True))
            out["clamp"] = self.clamp
        return out


@dataclass
class Truth:
    """What the slave holds: registers of hr/ir, bits of coils/di, refused ranges."""

    regs: dict[str, list[int]]
    bits: dict[str, list[bool]]
    refused: list[tuple[str, int, int]] = field(default_factory=list)  # area, start, end


def _swap(r: int) -> int:
    return ((r & 0xFF) << 8) | (r >> 8)


@dataclass(frozen=True)
class Order:
    """An item's effective byte order keys (its own, else the device's)."""

    fmt: str
    swap16: bool
    fmt64: str | None


def _by_letters(regs: list[int], order: str) -> bytes:
    """The value's bytes, most significant first, from registers whose bytes by address
    are the value's bytes the letters name (``"CDAB"``: register 0 holds C and D)."""
    wire = b"".join(r.to_bytes(2, "big") for r in regs)
    value = bytearray(len(wire))
    for at, letter in enumerate(order):
        value[ord(letter) - ord("A")] = wire[at]
    return bytes(value)


def _value_bytes(regs: list[int], order: Order) -> bytes:
    """docs/device-files.md "Byte order": one register is the register (BA with byteSwap16), two
    follow dataFormat, four dataFormat64 (default: dataFormat stretched to 8 letters)."""
    if len(regs) == 1:
        return _by_letters(regs, "BA" if order.swap16 else "AB")
    if len(regs) == 2:
        return _by_letters(regs, order.fmt)
    return _by_letters(regs, order.fmt64 or STRETCHED[order.fmt])


def _ordered_bytes(regs: list[int], fmt: str) -> bytes:
    """Registers to bytes in the format's order: CDAB/DCBA reverse the registers, BADC/
    DCBA swap the bytes inside each register."""
    if fmt in ("CDAB", "DCBA"):
        regs = regs[::-1]
    if fmt in ("BADC", "DCBA"):
        regs = [_swap(r) for r in regs]
    return b"".join(r.to_bytes(2, "big") for r in regs)


def _raw(spec: Spec, regs: list[int], order: Order, encoding: str) -> Any:
    """The value of the registers before multiplier and conversion (BAD if invalid)."""
    if spec.dtype in ("String", "Binary"):
        data = _ordered_bytes(regs, order.fmt)
        if spec.dtype == "Binary":
            return data
        return data.rstrip(b"\0").decode(encoding, "replace")
    kind, n = WIDTHS[spec.dtype][spec.quantity]
    data = _value_bytes(regs[:n], order)
    if kind == "bool":
        return regs[0] != 0  # a whole register: not zero, in any byte order
    if kind in ("u8", "i8", "char"):
        low = data[1]  # the low byte after the byte swap
        return low if kind == "u8" else chr(low) if kind == "char" else low - 256 * (low > 127)
    if kind in ("i24", "u24"):  # byte A unused: the low three bytes
        return int.from_bytes(data[1:], "big", signed=kind == "i24")
    if kind == "bcd":
        digits = data.hex()
        return int(digits) if all(c in "0123456789" for c in digits) else BAD
    number = struct.unpack(STRUCT[kind], data)[0]
    if kind in ("sec", "ms"):
        ms = number * 1000 if kind == "sec" else number
        if spec.dtype == "Timestamp":
            return ms
        try:
            return EPOCH + timedelta(milliseconds=ms)
        except OverflowError:
            return BAD
    if spec.dtype == "Float":  # a Float item's value: a float whose text is float32's
        return Float32(number)
    if spec.dtype == "Double":
        return float(number)
    return number


def _scaled(value: Any, multiplier: float) -> Any:
    if multiplier == 1:
        return value
    steps = DECIMAL_STEPS.get(multiplier)
    return float(value) / steps if steps else float(value) * multiplier


def _engineering(value: Any, spec: Spec) -> Any:
    """docs/engineering-units.md's formulas, in doubles step by step as documented: a
    range maps the raw value (Invalid outside it, or clamped); else value x multiplier +
    offset."""
    if spec.span is None:
        return _scaled(value, spec.multiplier) + spec.add if spec.add else _scaled(
            value, spec.multiplier)
    r0, r1, e0, e1 = spec.span
    x = float(value)
    if not min(r0, r1) <= x <= max(r0, r1) and not spec.clamp:
        return BAD  # NaN too
    x = (x - r0) * ((e1 - e0) / (r1 - r0)) + e0
    if spec.clamp:
        x = min(e0, e1) if x < min(e0, e1) else max(e0, e1) if x > max(e0, e1) else x
    return x


def _converted(value: Any, target: str) -> Any:
    if target == "String":
        return str(value)
    if target == "Boolean":
        return value != 0
    if target in ("Float", "Double"):
        number = float(value)
        if target == "Float" and math.isfinite(number) and abs(number) > FLT_MAX:
            return BAD
        return Float32(number) if target == "Float" else number
    if isinstance(value, float):
        if not math.isfinite(value):
            return BAD
        value = round(value)  # half to even
    lo, hi = INT_RANGE[target]
    return int(value) if lo <= value <= hi else BAD


def reference(spec: Spec, truth: Truth, device_fmt: str, device_encoding: str,
              device_swap16: bool = False, device_fmt64: str | None = None) -> Any:
    """The value the item must hold when Ok, or BAD when it must not be Ok."""
    end = spec.offset + spec.size
    for area, start, stop in truth.refused:
        if area == spec.area and spec.offset < stop and start < end:
            return BAD
    if spec.area in ("coil", "di"):
        value: Any = truth.bits[spec.area][spec.offset]
    else:
        regs = truth.regs[spec.area][spec.offset:end]
        order = Order(spec.fmt or device_fmt,
                      device_swap16 if spec.swap16 is None else spec.swap16,
                      spec.fmt64 or device_fmt64)
        if spec.bit is not None:
            reg = _swap(regs[0]) if order.swap16 else regs[0]
            value = (reg >> spec.bit) & 1 == 1  # counted after the 16-bit swap
        else:
            value = _raw(spec, regs, order, spec.encoding or device_encoding)
    if value is BAD:
        return BAD
    value = _engineering(value, spec)
    if value is BAD:  # outside rawMin..rawMax: no conversion makes it good
        return BAD
    target = spec.converted
    if target is None or (target == spec.dtype and not spec.scaled):
        return value
    return _converted(value, target)


def same(a: Any, b: Any) -> bool:
    """Exactly equal: same type and value (NaN equals NaN)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    return bool(a == b)


# -- register contents ---------------------------------------------------------------------

def register_value(rng: random.Random) -> int:
    """A register that is often meaningful: valid BCD, text, small numbers, extremes."""
    pick = rng.random()
    if pick < 0.3:
        return rng.randrange(0x10000)
    if pick < 0.45:
        return rng.randrange(21)
    if pick < 0.55:
        return rng.choice([0, 0xFFFF, 0x8000, 0x7FFF, 0x0001, 0x00FF, 0xFF00, 0x7F80, 0x7FC0])
    if pick < 0.75:
        return int(f"{rng.randrange(10000):04d}", 16)  # packed decimal
    if pick < 0.9:
        return rng.randrange(32, 127) << 8 | rng.randrange(32, 127)  # two ASCII letters
    return rng.choice([0, rng.randrange(32, 127) << 8, 0xC3A9, 0xE4BD])  # NULs, UTF-8 bits


def fresh_truth(rng: random.Random) -> Truth:
    return Truth(
        regs={a: [register_value(rng) for _ in range(REG_SPAN)] for a in ("hr", "ir")},
        bits={a: [rng.random() < 0.5 for _ in range(BIT_SPAN)] for a in ("coil", "di")},
    )


def mutate(truth: Truth, specs: list[Spec], rng: random.Random) -> None:
    """Change some registers and bits, mostly inside items (so that values move)."""
    for _ in range(rng.randrange(1, 12)):
        if specs and rng.random() < 0.8:
            spec = rng.choice(specs)
            where = spec.area, spec.offset + rng.randrange(spec.size)
        elif rng.random() < 0.7:
            where = rng.choice(["hr", "ir"]), rng.randrange(REG_SPAN)
        else:
            where = rng.choice(["coil", "di"]), rng.randrange(BIT_SPAN)
        area, offset = where
        if area in ("coil", "di"):
            truth.bits[area][offset] = not truth.bits[area][offset]
        else:
            truth.regs[area][offset] = register_value(rng)


def load(sim: Simulator, truth: Truth) -> None:
    slave = sim.slave(1)
    for area, values in truth.regs.items():
        slave.set_registers(AREAS[area], 0, values)
    for area, flags in truth.bits.items():
        slave.set_bits(AREAS[area], 0, flags)


AREAS = {"hr": em.Area.HOLDING_REGISTER, "ir": em.Area.INPUT_REGISTER,
         "coil": em.Area.COIL, "di": em.Area.DISCRETE_INPUT}

# -- strategies ----------------------------------------------------------------------------


@st.composite
def item_specs(draw: st.DrawFn, name: str) -> Spec:
    area = draw(st.sampled_from(["hr", "hr", "hr", "ir", "coil", "di"]))
    enabled = draw(st.integers(0, 9)) > 0
    if area in ("coil", "di"):
        offset = draw(st.integers(0, BIT_SPAN - 1))
        converted = draw(st.one_of(st.none(), st.sampled_from(TARGETS)))
        return Spec(name, area, offset, "Boolean", converted=converted, enabled=enabled)
    fmt = draw(st.one_of(st.none(), st.sampled_from(FORMATS)))
    swap16 = draw(st.one_of(st.none(), st.booleans()))
    fmt64 = draw(st.one_of(st.none(), st.none(), st.sampled_from(FORMATS64)))
    kind = draw(st.sampled_from(["fixed", "fixed", "fixed", "bit", "text"]))
    if kind == "bit":
        offset = draw(st.integers(0, REG_SPAN - 1))
        return Spec(name, area, offset, "Boolean", bit=draw(st.integers(0, 15)), fmt=fmt,
                    swap16=swap16, fmt64=fmt64,
                    converted=draw(st.one_of(st.none(), st.sampled_from(TARGETS))),
                    enabled=enabled)
    if kind == "text":
        dtype = draw(st.sampled_from(["String", "Binary"]))
        length = draw(st.one_of(st.integers(1, 8), st.integers(1, 125)))
        encoding = None
        if dtype == "String":
            encoding = draw(st.sampled_from([None, "utf-8", "gbk", "latin-1"]))
        offset = draw(st.integers(0, REG_SPAN - length))
        return Spec(name, area, offset, dtype, quantity=length, fmt=fmt, swap16=swap16,
                    fmt64=fmt64, encoding=encoding, enabled=enabled)
    dtype = draw(st.sampled_from(sorted(WIDTHS)))
    quantity = draw(st.sampled_from(sorted(WIDTHS[dtype], key=lambda q: q or 0)))
    multiplier = 1.0
    if dtype in NUMERIC and draw(st.integers(0, 3)) == 0:
        multiplier = draw(st.sampled_from(MULTIPLIERS))
    add, span, clamp = 0.0, None, False
    if dtype in NUMERIC and draw(st.integers(0, 3)) == 0:  # engineering units
        if draw(st.booleans()):
            add = draw(st.sampled_from(OFFSETS))
        else:
            multiplier = 1.0
            r0, r1 = draw(st.lists(st.sampled_from(RAW_ENDS), min_size=2, max_size=2,
                                   unique=True))
            e0, e1 = draw(st.lists(st.sampled_from(ENG_ENDS), min_size=2, max_size=2,
                                   unique=True))
            span, clamp = (r0, r1, e0, e1), draw(st.booleans())
    converted = None
    if dtype not in UNCONVERTED and draw(st.integers(0, 2)) == 0:
        converted = draw(st.sampled_from(TARGETS))
    spec = Spec(name, area, 0, dtype, quantity=quantity, fmt=fmt, swap16=swap16, fmt64=fmt64,
                multiplier=multiplier, converted=converted, enabled=enabled, add=add,
                span=span, clamp=clamp)
    return replace(spec, offset=draw(st.integers(0, REG_SPAN - spec.size)))


RATES = st.one_of(st.none(), st.integers(10, 60))  # an item's own scan rate, sometimes


@st.composite
def address_lists(draw: st.DrawFn, first: int = 0, rated: bool = False) -> list[Spec]:
    count = draw(st.integers(1, 24))
    specs = [draw(item_specs(f"i{first + k}")) for k in range(count)]
    if draw(st.booleans()):  # in address order: a block's items are stored side by side,
        # so a read that changes them all takes the store's slices (poll/items.py
        # store_changes); in the drawn order they mostly are not
        specs.sort(key=lambda s: (s.area, s.offset, s.bit or 0))
    return [replace(s, rate=draw(RATES)) for s in specs] if rated else specs


@dataclass(frozen=True)
class Setup:
    specs: list[Spec]
    later: list[Spec] | None  # an address list swapped in by update_addresses, or None
    comm: dict[str, Any]
    refused: list[tuple[str, int, int, int]]  # area, start, end, exception code
    faults: dict[str, int]
    seed: int


@st.composite
def setups(draw: st.DrawFn) -> Setup:
    rated = draw(st.integers(0, 2)) == 0
    specs = draw(address_lists(rated=rated))
    later = None
    if draw(st.integers(0, 3)) == 0:
        kept = [s for s in specs if draw(st.booleans())]
        if rated:  # some kept items change their rate: a re-plan
            kept = [replace(s, rate=draw(RATES)) if draw(st.booleans()) else s for s in kept]
        later = kept + draw(address_lists(first=len(specs), rated=rated))
    comm: dict[str, Any] = {
        "dataFormat": draw(st.sampled_from(FORMATS)),
        "byteSwap16": draw(st.booleans()),
        "dataFormat64": draw(st.one_of(st.none(), st.sampled_from(FORMATS64))),
        "maxBlockReadRegisterCount": draw(st.one_of(st.integers(1, 16), st.integers(1, 125))),
        "maxBlockReadBitCount": draw(st.one_of(st.integers(1, 16), st.integers(1, 2000))),
        "maxMergeAddressGap": draw(st.integers(0, 20)),
        "isBlockReadRequireAddressContinuous": draw(st.booleans()),
        "reportMode": draw(st.sampled_from(["change", "cycle"])),
        "readCycle": draw(st.integers(10, 30)),
        "retries": draw(st.integers(0, 2)),
        "encoding": draw(st.sampled_from(["utf-8", "gbk"])),
    }
    refused: list[tuple[str, int, int, int]] = []
    if draw(st.integers(0, 3)) == 0:
        for _ in range(draw(st.integers(1, 3))):
            area = draw(st.sampled_from(["hr", "hr", "ir", "coil"]))
            span = BIT_SPAN if area == "coil" else REG_SPAN
            start = draw(st.integers(0, span - 1))
            end = draw(st.integers(start + 1, min(span, start + 8)))
            refused.append((area, start, end, draw(st.sampled_from([2, 2, 2, 4]))))
    # a wire fault costs 50-150 ms (drain or timeout): keep a cycle to about 80 requests
    limit = comm["maxBlockReadRegisterCount"]
    assume(sum(-(-s.size // limit) for s in specs + (later or []) if s.enabled) <= 80)
    faults: dict[str, int] = {}
    if draw(st.integers(0, 4)) == 0:
        knob = draw(st.sampled_from(["drop_every", "corrupt_crc_every", "corrupt_data_every",
                                     "wrong_byte_count_every"]))
        faults[knob] = draw(st.integers(3, 15))
    return Setup(specs, later, comm, refused, faults, draw(st.integers(0, 2**32 - 1)))


# -- the run ---------------------------------------------------------------------------------


@pytest.fixture
def sim() -> Iterator[tuple[Simulator, int]]:
    with Simulator([1], size=1000) as simulator:
        yield simulator, simulator.serve_tcp("127.0.0.1", 0)


class Checker:
    """Checks items against the reference; called on the driver's worker thread."""

    def __init__(self, setup: Setup, truth: Truth) -> None:
        self.setup = setup
        self.truth = truth
        self.fmt: str = setup.comm["dataFormat"]
        self.encoding: str = setup.comm["encoding"]
        self.swap16: bool = setup.comm["byteSwap16"]
        self.fmt64: str | None = setup.comm["dataFormat64"]
        self.specs: dict[int, Spec] = {}  # id(item) -> its spec, for every list in use
        # with per-item rates: the registers as they were at the end of earlier cycles
        self.rated = any(s.rate is not None for s in setup.specs + (setup.later or []))
        self.past: list[Truth] = []
        self.wrong: list[str] = []
        self.missing: list[str] = []
        self.cycles = 0
        self.faults = ""  # the line's failures over the run, for a failure's message

    def adopt(self, items: list[em.DeviceAddressItem], specs: list[Spec]) -> None:
        for item, spec in zip(items, specs, strict=True):
            self.specs[id(item)] = spec

    def check(self, item: em.DeviceAddressItem, where: str) -> None:
        spec = self.specs[id(item)]
        if item.status is not ItemStatus.OK:
            return
        want = self.reference(spec, self.truth)
        if want is not BAD and same(item.value, want):
            return
        if any(same(item.value, self.reference(spec, past)) for past in self.past):
            return  # read in an earlier cycle and not due since (per-item rates)
        if want is BAD:
            self.wrong.append(f"{where}: {spec} is Ok with {item.value!r}, must not be Ok")
        elif not same(item.value, want):
            self.wrong.append(f"{where}: {spec} holds {item.value!r}, the slave {want!r}")

    def reference(self, spec: Spec, truth: Truth) -> Any:
        return reference(spec, truth, self.fmt, self.encoding, self.swap16, self.fmt64)

    def valid_all_along(self, spec: Spec) -> bool:
        return all(self.reference(spec, t) is not BAD for t in [self.truth, *self.past])

    def on_item(self, item: em.DeviceAddressItem) -> None:
        self.check(item, f"cycle {self.cycles} item callback")

    def on_batch(self, items: list[em.DeviceAddressItem]) -> None:
        for item in items:
            self.check(item, f"cycle {self.cycles} batch")
        if len({id(item) for item in items}) != len(items):
            self.wrong.append(f"cycle {self.cycles}: a batch holds an item twice: "
                              f"{sorted(item.name for item in items)}")


LINKS = {
    # the gateway connects to the slave, a line worker thread of its own
    "connect": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1"},
    # the same on the loop engine (line/loop.py, csrc/emb_loop_link.c)
    "connect-loop": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "engine": "loop",
                     "loopThreads": 1},
    # a DTU that dials in (the simulator's DtuClient), on the loop engine
    "dtu-loop": {"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                 "dtuId": "DIFF1", "registration": "text", "engine": "loop",
                 "loopThreads": 1},
}


def _config(setup: Setup, port: int, specs: list[Spec], link: str = "connect"
            ) -> em.DeviceConfig:
    where = {"listenPort": port} if link == "dtu-loop" else {"tcpPort": port}
    comm = {**LINKS[link], **where,
            "slaveId": 1, "readTimeout": 100, "settleTimeout": 50, "maxBackoff": 200,
            "offlineAfterFailedCycles": 3, "snapshotInterval": 1, **setup.comm}
    return em.load_device_config({"organization": {"deviceCode": "diff"},
                                  "communication": comm,
                                  "addressList": [s.as_json() for s in specs]})


def run(setup: Setup, sim: Simulator, port: int, link: str = "connect") -> Checker:
    """Poll the slave for CYCLES cycles, checking every item and callback on the way;
    ``link``: how the driver reaches it (:data:`LINKS`)."""
    rng = random.Random(setup.seed)
    truth = fresh_truth(rng)
    truth.refused = [(area, start, end) for area, start, end, _ in setup.refused]
    slave = sim.slave(1)
    slave.faults.clear()
    load(sim, truth)
    slave.faults.exception_ranges = [(AREAS[a], start, end, code)
                                     for a, start, end, code in setup.refused]
    for knob, every in setup.faults.items():
        setattr(slave.faults, knob, every)
    clean = not setup.refused and not setup.faults
    if link == "dtu-loop":
        port = free_port()  # the driver listens, the simulator dials in
    cfg = _config(setup, port, setup.specs, link)
    checker = Checker(setup, truth)
    checker.adopt(cfg.address_list, setup.specs)
    items, specs = cfg.address_list, setup.specs  # the list in force
    drv = em.DriverModbusRtu()

    def cycle_ended(_topic: str, _snapshot: dict[str, Any]) -> None:
        nonlocal items, specs
        checker.cycles += 1
        stats = drv.stats()
        errors = stats["timeouts"] + stats["crcErrors"] + stats["protocolErrors"]
        for item, spec in zip(items, specs, strict=True):
            checker.check(item, f"end of cycle {checker.cycles}")
            if clean and not errors and spec.enabled and item.status is not ItemStatus.OK \
                    and checker.valid_all_along(spec):
                checker.missing.append(f"end of cycle {checker.cycles}: {spec} is "
                                       f"{item.status.value} ({item.error_reason})")
        if checker.cycles == 2 and setup.later is not None:
            new = _config(setup, port, setup.later, link).address_list
            checker.adopt(new, setup.later)
            drv.update_addresses(new)  # on the worker: swapped at once, between two reads
            items, specs = new, setup.later
        if checker.cycles < CYCLES:
            if checker.rated:
                checker.past.append(copy.deepcopy(truth))
            mutate(truth, specs, rng)
            load(sim, truth)

    drv.address_updated_callback = checker.on_item
    drv.addresses_updated_callback = checker.on_batch
    drv.snapshot_publisher = cycle_ended
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    client = None
    try:
        if link == "dtu-loop":
            client = sim.dial("127.0.0.1", port, registration=b"DIFF1")
        wait_for(lambda: checker.cycles >= CYCLES, timeout=60, what=f"{CYCLES} cycles")
    finally:
        stats = drv.stats()
        drv.stop_device()
        # a reply later than readTimeout + settleTimeout is taken for the next request's
        # (RTU has no transaction id): a wrong value after timeouts may be one
        checker.faults = ", ".join(f"{k} {stats[k]}" for k in (
            "timeouts", "crcErrors", "protocolErrors", "retries")) + ", " + ", ".join(
            f"{k} {stats['line'][k]}" for k in ("discardedBytes", "droppedFrames"))
        if client is not None:
            client.close()
    return checker


def _describe(setup: Setup) -> None:
    """Hypothesis statistics: which features the examples reached."""
    limit = setup.comm["maxBlockReadRegisterCount"]
    specs = setup.specs + (setup.later or [])
    if any(s.dtype in ("String", "Binary") and s.size > limit for s in specs):
        event("an item larger than a block")
    if setup.refused:
        event("refused address ranges")
    if setup.faults:
        event(f"fault {next(iter(setup.faults))}")
    if setup.later is not None:
        event("update_addresses")
    if any(s.rate is not None for s in specs):
        event("per-item scan rates")
    if setup.comm["byteSwap16"] or any(s.swap16 is not None for s in specs):
        event("byteSwap16 set")
    if setup.comm["dataFormat64"] or any(s.fmt64 is not None for s in specs):
        event("dataFormat64 set")
    if any(s.add for s in specs):
        event("an offset")
    if any(s.span is not None for s in specs):
        event("range scaling")


@pytest.mark.timeout(HANG_GUARD)
@DIFF
@given(setup=setups())
def test_ok_values_equal_an_independent_decode(
    setup: Setup, sim: tuple[Simulator, int]
) -> None:
    _describe(setup)
    checker = run(setup, *sim)
    assert not checker.wrong, "\n".join([*checker.wrong[:5], checker.faults])
    assert not checker.missing, "\n".join([*checker.missing[:5], checker.faults])


@pytest.mark.timeout(HANG_GUARD)
@pytest.mark.parametrize("link", ["connect-loop", "dtu-loop"])
@settings(DIFF, max_examples=max(4, EXAMPLES // 2))
@given(setup=setups())
def test_ok_values_equal_an_independent_decode_on_the_loop_engine(
    setup: Setup, sim: tuple[Simulator, int], link: str
) -> None:
    """The same on the loop engine (engine "loop", also what "auto" picks for a DTU that
    dials in): a connect-mode line and a DTU that dialled in."""
    _describe(setup)
    checker = run(setup, *sim, link=link)
    assert not checker.wrong, "\n".join([*checker.wrong[:5], checker.faults])
    assert not checker.missing, "\n".join([*checker.missing[:5], checker.faults])


def test_reference_decoder_knows_the_documented_cases() -> None:
    """The reference itself, on values worked out by hand (a wrong reference would make
    the differential test meaningless)."""
    truth = Truth(regs={"hr": [0x1234, 0x5678, 0x9ABC, 0xDEF0, 0x4142, 0x4300, 0, 0,
                               0x0000, 0x0123, 0x4567, 0x89AB, 5],
                        "ir": [0] * 13}, bits={"coil": [True], "di": [False]})

    def ref(fmt: str = "ABCD", **kw: Any) -> Any:
        spec = Spec("x", kw.pop("area", "hr"), kw.pop("offset", 0), kw.pop("dtype"), **kw)
        return reference(spec, truth, fmt, "utf-8")

    assert ref(dtype="UInt32") == 0x12345678
    assert ref("CDAB", dtype="UInt32") == 0x56781234
    assert ref("BADC", dtype="UInt32") == 0x34127856
    assert ref("DCBA", dtype="UInt32") == 0x78563412
    assert ref("DCBA", dtype="UInt64") == 0xF0DEBC9A78563412
    assert ref(dtype="Int16", offset=2) == 0x9ABC - 0x10000
    assert ref(dtype="Int64", quantity=2, offset=2) == struct.unpack(">i", bytes.fromhex(
        "9ABCDEF0"))[0]  # Smart Cast: two registers of an Int64 are an Int32
    assert ref(dtype="Double", quantity=1) == float(0x1234)  # one register: an Int16
    assert ref(dtype="Byte") == 0x34 and ref("BADC", dtype="Byte") == 0x34
    assert ref(dtype="Byte", swap16=True) == 0x12 and ref(dtype="Int16", swap16=True) == 0x3412
    assert ref("DCBA", dtype="UInt16") == 0x1234  # one register: dataFormat leaves it
    assert ref("BADC", dtype="UInt64", fmt64="EFGHABCD") == 0x9ABCDEF012345678
    assert ref("CDAB", dtype="UInt64", fmt64="CDABGHEF") == 0x56781234DEF09ABC
    assert ref(dtype="Int24") == 0x345678 and ref("CDAB", dtype="UInt24") == 0x781234
    assert ref(dtype="Int24", offset=2) == 0xBCDEF0 - (1 << 24)
    assert ref(dtype="Char", offset=4) == "B" and ref(dtype="Sbyte", offset=2) == -0x44
    assert ref(dtype="BCD16") == 1234 and ref(dtype="BCD32") == 12345678
    assert ref(dtype="BCD16", offset=2) is BAD  # 0x9ABC: digits above 9
    assert ref(dtype="String", quantity=4, offset=4) == "ABC"  # trailing NULs stripped
    assert ref("CDAB", dtype="String", quantity=2, offset=4) == "C\0AB"
    assert ref(dtype="Binary", quantity=2, offset=4) == b"ABC\0"
    assert ref(dtype="Timestamp") == 0x12345678 * 1000
    assert ref(dtype="DateTime", quantity=4, offset=8) == EPOCH + timedelta(
        milliseconds=0x0123456789AB)
    assert ref(dtype="DateTime", quantity=4) is BAD  # 0x123456789ABCDEF0 ms: past year 9999
    assert ref(dtype="Boolean", bit=4) is True and ref("BADC", dtype="Boolean", bit=4) is True
    assert ref(dtype="Boolean", bit=0) is False and ref("BADC", dtype="Boolean", bit=1) is False
    assert ref(dtype="Boolean", bit=1, swap16=True) is True  # bit 1 of 0x3412
    assert ref(dtype="Int16", multiplier=0.1) == 0x1234 / 10
    assert ref(dtype="Int16", multiplier=0.01, converted="Int16") == 47  # 46.6 rounded
    assert ref(dtype="Int16", offset=12, multiplier=0.5, converted="Int16") == 2  # 2.5: even
    assert ref(dtype="UInt16", converted="Sbyte") is BAD
    assert ref(dtype="UInt16", multiplier=0.5, converted="String") == "2330.0"
    # outside rawMin..rawMax and not clamped: Invalid, whatever it is converted to
    assert ref(dtype="BCD16", span=(0.0, 1000.0, 0.0, 1.0)) is BAD  # 1234
    assert ref(dtype="BCD16", span=(0.0, 1000.0, 0.0, 1.0), converted="Boolean") is BAD
    assert ref(dtype="BCD16", span=(0.0, 1000.0, 0.0, 1.0), clamp=True,
               converted="Boolean") is True
    assert ref(dtype="Boolean", area="coil") is True
    truth.refused.append(("hr", 1, 2))
    assert ref(dtype="UInt32") is BAD and ref(dtype="UInt16") == 0x1234


def test_same_compares_exactly() -> None:
    assert same(math.nan, math.nan) and same(b"a", b"a")
    assert not same(1, 1.0) and not same(True, 1) and not same(0.1 + 0.2, 0.3)
