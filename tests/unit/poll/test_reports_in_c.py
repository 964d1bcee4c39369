"""Wrapped reports applied in C (csrc/emb_report.c) against the Python path (poll/reports.py
ReportDecoders, Poller.on_report), which is the reference: the same stream of reports
gives the same item values, statuses, reasons and per-item callbacks, whichever path the
engine takes for each report.

Two pollers of the same device file: one behind an engine on a wrapped stream context
(the reports fed into its ring, applied by emb_reports_apply and taken by the poller as
the worker does at a handover; those C refuses go to on_report, as the worker hands them
over), the other given every report through on_report.  No I/O: a socketpair only holds
the context.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import edgemodbus as em
from edgemodbus._ffi import Context
from edgemodbus._ffi.engine import Engine, EngineDevice
from edgemodbus._ffi.native import ffi, lib
from edgemodbus._ffi.outcomes import Clean, LineCounters
from edgemodbus._ffi.waker import Waker
from edgemodbus.config import effective_parameters, validate_items
from edgemodbus.datatypes import ItemStatus
from edgemodbus.poll.listeners import Listener
from edgemodbus.poll.poller import Poller
from edgemodbus.poll.sink import ItemCallback, SnapshotPublisher
from edgemodbus.protocol.wrapped import report_of, wrap
from tests.unit.ffi.test_stream_framing import EXAMPLES, stream_context
from tests.value_reference import SIZES, decode, float32_text, same


class Sink:
    """A poller's owner (a PollSink) that records the items each callback got."""

    source: object = None

    def __init__(self) -> None:
        self.items: list[str] = []

    def item_callback(self) -> ItemCallback | None:
        return lambda item: self.items.append(item.name)

    def listeners(self) -> tuple[Listener[Any], ...]:
        return ()

    def snapshot_publisher(self) -> SnapshotPublisher | None:
        return None

    def snapshot(self) -> dict[str, Any]:
        return {}


def poller_of(items: list[dict[str, Any]], **comm: Any) -> tuple[Poller, Sink]:
    """A started poller (no line) of a wrapped-report device with these items."""
    cfg = em.load_device_config({
        "organization": {"deviceCode": "mcu"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": 502, "slaveId": 1, "readCycle": 1000,
                          "framing": "wrapped-report", **comm},
        "addressList": items,
    })
    params = effective_parameters(cfg.organization, cfg.communication)
    sink = Sink()
    poller = Poller(sink, "mcu", params, validate_items(list(cfg.address_list), params),
                    logging.getLogger("test.reports"))
    poller.store.bind()
    poller.active = poller.device.active = True
    return poller, sink


@contextmanager
def engine_of(devices: list[EngineDevice]) -> Iterator[tuple[Context, Engine]]:
    """An engine over ``devices`` on a wrapped stream context (nothing is read)."""
    waker = Waker()
    try:
        with stream_context() as (ctx, _peer):
            engine = Engine(ctx, waker, LineCounters(), 0.0, None, Clean(0.0, 0.0, 0.05, 0.1))
            engine.set_devices(devices)
            yield ctx, engine
    finally:
        waker.close()


def through_engine(ctx: Context, engine: Engine, poller: Poller, frame: bytes) -> bool:
    """Feed one report into the link's ring and let the engine apply it; True if C did
    (the poller takes it as at a handover), False if it went to Python (on_report)."""
    ctx.feed(frame)
    if lib.emb_reports_apply(engine.native, -1, ffi.NULL):
        poller.take_reports()
        return True
    for raw in ctx.take_reports():
        poller.on_report(report_of(raw))
    return False


def state(poller: Poller) -> list[tuple[str, object, object, str | None]]:
    """Each item's name, status, value (floats by their bits, NaN too) and reason."""
    out: list[tuple[str, object, object, str | None]] = []
    for s in poller.items:
        value, status, _, reason = s.item.reading
        if isinstance(value, float):
            value = struct.pack(">d", value) if not math.isnan(value) else "NaN"
        out.append((s.item.name, status, value, reason))
    return out


def register_report(address: int, values: list[int], function: int = 3) -> bytes:
    return wrap(address, 1, struct.pack(f">BB{len(values)}H", function, 2 * len(values),
                                        *values))


def coil_report(address: int, bits: list[int]) -> bytes:
    data = bytes(sum(b << i for i, b in enumerate(bits[k:k + 8]))
                 for k in range(0, len(bits), 8))
    return wrap(address, 1, bytes([1, len(data)]) + data)


# -- the paths, by hand ----------------------------------------------------------------


ITEMS: list[dict[str, Any]] = [{"name": f"r{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                               for a in range(10)]


def test_a_report_inside_a_block_is_applied_in_c() -> None:
    """A one-register report inside the block [0, 10): C applies it, the poller takes
    the one item it changed; the same report again is no news (no callback); the
    device and line counters count both."""
    poller, sink = poller_of(ITEMS)
    with engine_of([poller.device]) as (ctx, engine):
        assert through_engine(ctx, engine, poller, register_report(0, list(range(10))))
        sink.items.clear()
        assert through_engine(ctx, engine, poller, register_report(4, [77]))
        assert sink.items == ["r4"]
        assert poller.store.by_name()["r4"].item.value == 77
        assert through_engine(ctx, engine, poller, register_report(4, [77]))
        assert sink.items == ["r4"]
        assert poller.device.counts().reports == 3
        assert engine.native.lc.reports == 3
        assert poller.counters.reports == 0  # none went through Python


@pytest.mark.parametrize(("frame", "why"), [
    (register_report(8, [1, 2, 3]), "it runs past the block's end"),
    (register_report(0, [1, 2], function=4), "input registers: no block reads them"),
])
def test_what_c_does_not_apply_goes_to_python(frame: bytes, why: str) -> None:
    poller, _ = poller_of(ITEMS)
    reference, _ = poller_of(ITEMS)
    with engine_of([poller.device]) as (ctx, engine):
        assert not through_engine(ctx, engine, poller, frame), why
        reference.on_report(report_of(frame))
    assert state(poller) == state(reference)


def test_a_block_holding_a_report_takes_no_second_one() -> None:
    """Two reports with news for one block before the poller took the first: C applies
    the first and leaves the second to Python (its changes would overwrite the first's),
    and the reports behind it too; Python takes the first before it applies them."""
    poller, sink = poller_of(ITEMS)
    with engine_of([poller.device]) as (ctx, engine):
        ctx.feed(register_report(1, [5]))
        ctx.feed(register_report(1, [6]))
        ctx.feed(register_report(3, [8]))
        assert not lib.emb_reports_apply(engine.native, -1, ffi.NULL)
        assert ctx.reports_waiting == 2
        ctx.feed(register_report(2, [7]))
        for raw in ctx.take_reports():
            poller.on_report(report_of(raw))
    assert sink.items == ["r1", "r1", "r3", "r2"]
    assert poller.store.by_name()["r1"].item.value == 6


def test_items_of_another_rate_inside_the_block_keep_reports_in_python() -> None:
    """r5 is read at its own rate in a block of its own inside [0, 10)'s range: a
    report there would set it too, so the big block takes no report in C."""
    items: list[dict[str, Any]] = [dict(it) for it in ITEMS]
    items[5]["readCycle"] = 5000
    poller, _ = poller_of(items)
    reference, _ = poller_of(items)
    with engine_of([poller.device]) as (ctx, engine):
        for frame in (register_report(3, [1, 2, 3]), register_report(5, [9])):
            assert not through_engine(ctx, engine, poller, frame) or frame[3] == 5
            reference.on_report(report_of(frame))
    assert state(poller) == state(reference)


# -- the differential test --------------------------------------------------------------

TYPES = [("UInt16", 1), ("Int16", 1), ("Int32", 2), ("Float", 2), ("BCD16", 1),
         ("Double", 4), ("UInt32", 2), ("Int24", 2), ("UInt24", 2), ("Int64", 4),
         ("UInt64", 4)]
FORMATS64 = ["ABCDEFGH", "BADCFEHG", "CDABGHEF", "DCBAHGFE", "EFGHABCD", "FEHGBADC",
             "GHEFCDAB", "HGFEDCBA"]


def units(draw: st.DrawFn, data_type: str) -> dict[str, Any]:
    """Engineering-unit keys (docs/engineering-units.md) for a numeric item, or none:
    a multiplier and an offset, or a range map (reversed too, clamped or not)."""
    kind = draw(st.sampled_from(["none", "none", "linear", "range"]))
    if kind == "linear" and data_type != "BCD16":
        return {"dataMultiplier": draw(st.sampled_from([0.1, 0.5, 2, -3, 0.01])),
                "offset": draw(st.sampled_from([0, -40, 273.15, 0.5]))}
    if kind == "range":
        r0, r1 = draw(st.sampled_from([(0, 27648), (4000, 20000), (100, -100), (0, 9999)]))
        e0, e1 = draw(st.sampled_from([(0, 100), (-50, 150), (10, 0)]))
        return {"rawMin": r0, "rawMax": r1, "engMin": e0, "engMax": e1,
                "clamp": draw(st.booleans())}
    return {}


@st.composite
def devices(draw: st.DrawFn, differential: bool = True
            ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Items over holding registers 0..40 (no two overlapping, some of them bits of one
    register, some with a deadband, engineering units, a quantity or a rate of their
    own; byte orders of every width: dataFormat, dataFormat64, byteSwap16, per item and
    per device) and coils 0..40; a plan's gaps and block sizes.  ``differential``
    False: items an independent decode can check after each report (no deadband, no
    Smart Cast, no string, no scale factor)."""
    items: list[dict[str, Any]] = []
    at = draw(st.integers(0, 3))
    while at < 40:
        kind = draw(st.sampled_from(["type", "type", "bits", "string", "gap"]))
        name = f"h{at}"
        if kind == "gap":
            at += draw(st.integers(1, 4))
            continue
        if kind == "bits":
            for bit in sorted(draw(st.sets(st.integers(0, 15), min_size=1, max_size=3))):
                items.append({"name": f"{name}.{bit}", "address": f"3:{at}.{bit}",
                              "deviceDataType": "Boolean"})
            at += 1
            continue
        if kind == "string" and differential:
            n = draw(st.integers(1, 3))
            items.append({"name": name, "address": f"3:{at}", "deviceDataType": "String",
                          "quantity": n})
            at += n
            continue
        data_type, size = draw(st.sampled_from(TYPES))
        item: dict[str, Any] = {"name": name, "address": f"3:{at}",
                                "deviceDataType": data_type}
        if size > 1:
            item["dataFormat"] = draw(st.sampled_from(["ABCD", "BADC", "CDAB", "DCBA"]))
        if size == 4 and draw(st.booleans()):
            item["dataFormat64"] = draw(st.sampled_from(FORMATS64))
        if size == 1 and draw(st.booleans()):
            item["byteSwap16"] = draw(st.booleans())
        item.update(units(draw, data_type))
        if differential and draw(st.booleans()) and data_type != "BCD16":
            item["deadband"] = draw(st.sampled_from([0.5, 3, 100]))
        if differential and size == 1 and draw(st.integers(0, 5)) == 0:
            item["quantity"] = 2  # Smart Cast: two registers read, the item its type
            size = 2
        if draw(st.integers(0, 6)) == 0:
            item["readCycle"] = 5000  # a block of another rate, maybe inside one's range
        items.append(item)
        at += size
    for coil in sorted(draw(st.sets(st.integers(0, 40), max_size=6))):
        items.append({"name": f"c{coil}", "address": f"1:{coil}", "deviceDataType": "Boolean"})
    if differential and draw(st.integers(0, 3)) == 0:  # a SunSpec-style scale factor
        scaled = [it for it in items if it["deviceDataType"] in ("Int16", "UInt16", "Int32")
                  and "rawMin" not in it and "." not in it["address"]]
        items.append({"name": "sf", "address": "3:44", "deviceDataType": "Int16"})
        if scaled:
            draw(st.sampled_from(scaled))["scaleFactor"] = "sf"
    comm: dict[str, Any] = {"maxMergeAddressGap": draw(st.integers(0, 6)),
                            "maxBlockReadRegisterCount": draw(st.integers(3, 40))}
    if draw(st.booleans()):
        comm["byteSwap16"] = draw(st.booleans())
    if draw(st.booleans()):
        comm["dataFormat64"] = draw(st.sampled_from(FORMATS64))
    if draw(st.booleans()):
        comm["dataFormat"] = draw(st.sampled_from(["ABCD", "BADC", "CDAB", "DCBA"]))
    return items, comm


@st.composite
def streams(draw: st.DrawFn) -> list[tuple[str, bytes | None]]:
    """Reports of holding registers and coils at random places, values that repeat
    (no news), move a little (a deadband) or are anything (BCD digits above 9, NaN);
    between them, resets of the C side's block decoders (what a write does to them)."""
    out: list[tuple[str, bytes | None]] = []
    small = st.sampled_from([0, 1, 2, 0x8000, 0xFFFF, 0x7FC0, 9])
    for _ in range(draw(st.integers(1, 14))):
        kind = draw(st.sampled_from(["regs", "regs", "regs", "coils", "reset"]))
        if kind == "reset":
            out.append(("reset", None))
        elif kind == "coils":
            address = draw(st.integers(0, 40))
            bits = draw(st.lists(st.integers(0, 1), min_size=8, max_size=16))
            out.append(("report", coil_report(address, bits[:8 * (len(bits) // 8)])))
        else:
            address = draw(st.integers(0, 42))
            n = draw(st.integers(1, 8))
            values = draw(st.lists(small | st.integers(0, 0xFFFF), min_size=n, max_size=n))
            out.append(("report", register_report(address, values)))
    return out


@settings(max_examples=EXAMPLES, deadline=None)
@given(devices(), streams(), st.randoms(use_true_random=False))
def test_reports_in_c_match_the_python_path(device: tuple[list[dict[str, Any]], dict[str, Any]],
                                            stream: list[tuple[str, bytes | None]],
                                            rng: Any) -> None:
    items, comm = device
    poller, sink = poller_of(items, **comm)  # (a skip here once made the test a no-op)
    reference, ref_sink = poller_of(items, **comm)
    with engine_of([poller.device]) as (ctx, engine):
        for op, frame in stream:
            if op == "reset":
                slots = [s for s in poller.slots if s.decoder is not None]
                if slots:
                    slot = rng.choice(slots)
                    slot.decoder.reset()
                    slot.recheck = True
                continue
            assert frame is not None
            sink.items.clear()
            ref_sink.items.clear()
            through_engine(ctx, engine, poller, frame)
            reference.on_report(report_of(frame))
            assert state(poller) == state(reference), frame.hex()
            assert sorted(sink.items) == sorted(ref_sink.items), frame.hex()


# -- against an independent decode ------------------------------------------------------


def _span(item: dict[str, Any]) -> tuple[int, int, int | None]:
    """(first register, registers, bit) of a holding-register item of devices()."""
    where = item["address"].split(":", 1)[1]
    register, _, bit = where.partition(".")
    size = 1 if item["deviceDataType"] == "Boolean" else SIZES[item["deviceDataType"]]
    return int(register), size, int(bit) if bit else None


@settings(max_examples=EXAMPLES, deadline=None)
@given(devices(differential=False), streams())
def test_reports_in_c_read_what_the_contract_says(
        device: tuple[list[dict[str, Any]], dict[str, Any]],
        stream: list[tuple[str, bytes | None]]) -> None:
    """Every holding-register item wholly inside a report (its bytes in dataFormat's,
    dataFormat64's or byteSwap16's order, item's key over the device's; Int24, bits,
    engineering units) reads the value tests/value_reference.py decodes from the
    report's registers, or is Invalid where the contract says so; the C path and the
    Python path alike (the test above holds them equal)."""
    items, comm = device
    poller, _ = poller_of(items, **comm)
    by_name = poller.store.by_name()
    with engine_of([poller.device]) as (ctx, engine):
        for op, frame in stream:
            if op == "reset" or frame is None or frame[5] != 3:
                if frame is not None:
                    through_engine(ctx, engine, poller, frame)
                continue
            through_engine(ctx, engine, poller, frame)
            start, n = frame[2] << 8 | frame[3], frame[6] // 2
            registers = list(struct.unpack(f">{n}H", frame[7:7 + 2 * n]))
            for it in items:
                if not it["address"].startswith("3:"):
                    continue
                first, size, bit = _span(it)
                if first < start or first + size > start + n:
                    continue
                spec = {**it, "bit": bit}
                ok, expected = decode(registers[first - start:first - start + size],
                                      spec, comm)
                value, status, _, reason = by_name[it["name"]].item.reading
                if not ok:
                    assert status is ItemStatus.INVALID, (it, frame.hex(), value)
                    continue
                assert status is ItemStatus.OK, (it, comm, frame.hex(), reason)
                assert same(value, expected), (it, comm, frame.hex(), value, expected)
                if it["deviceDataType"] == "Float" and "rawMin" not in it and \
                        "dataMultiplier" not in it:  # written as its float32 (Float32)
                    assert repr(value) == float32_text(value), (it, value)
