"""DriverModbusRtu end to end: libmodbus on our side, pymodbus (own process) on the other,
and our simulator where a fault is needed."""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Iterator
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import DeviceDriverStatus, ItemStatus
from edgemodbus.sim import Simulator
from tests.peers import ExceptionRange, PymodbusSlave, default_bit, default_register
from tests.waiting import wait_for

DATA = Path(__file__).resolve().parents[1] / "data"


def comm(port: int, slave: int = 1, **extra: Any) -> dict[str, Any]:
    base: dict[str, Any] = {
        "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
        "slaveId": slave, "readTimeout": 300, "readCycle": 200, "reconnectInterval": 300,
        "connectTimeout": 1000, "byteTimeout": 50,
    }
    base.update(extra)
    return base


def device(port: int, items: list[dict[str, Any]], slave: int = 1, **extra: Any) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"dev{slave}"},
        "communication": comm(port, slave, **extra),
        "addressList": items,
    })


class Running:
    """Start a driver for a config; stop it at the end of the with-block."""

    def __init__(self, cfg: em.DeviceConfig, **callbacks: Any) -> None:
        self.cfg = cfg
        self.drv = em.DriverModbusRtu()
        for name, fn in callbacks.items():
            setattr(self.drv, name, fn)

    def __enter__(self) -> em.DriverModbusRtu:
        assert self.drv.start_device(self.cfg.organization, self.cfg.communication,
                                     self.cfg.address_list)
        return self.drv

    def __exit__(self, *exc: object) -> None:
        self.drv.stop_device()


def all_ok(cfg: em.DeviceConfig) -> Callable[[], bool]:
    return lambda: all(it.status is ItemStatus.OK for it in cfg.address_list)


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1, 2), size=2000) as peer:
        yield peer


def test_seed_device_file_polls_its_tags(slave: PymodbusSlave) -> None:
    raw = json.loads((DATA / "seed-device.json").read_text())
    raw["organization"]["isEnable"] = True
    raw["communication"]["tcpPort"] = slave.port
    raw["communication"]["readTimeout"] = 500
    cfg = em.load_device_config(raw)
    with Running(cfg) as drv:
        wait_for(all_ok(cfg), what="all seed items Ok")
        assert drv.device_driver_status is DeviceDriverStatus.RUNNING
        assert drv.data_item_count == len(cfg.address_list)
    values = {it.name: it.value for it in cfg.address_list}
    # "3:..." is read with FC03 (holding registers) under the default function-code
    # prefix; the seed's slave id is 2; "pooled" is Int16 x0.1 converted to Float
    assert values["pooled"] == pytest.approx(default_register(2, "hr", 5) * 0.1)
    assert isinstance(values["pooled"], float)
    for n in range(1, 13):
        assert values[f"tag{n}"] == default_register(2, "hr", n)
        assert isinstance(values[f"tag{n}"], int)
    assert values["tag99"] == default_register(2, "hr", 99)


def test_disabled_device_is_not_polled(slave: PymodbusSlave) -> None:
    cfg = em.load_device_config(json.loads((DATA / "seed-device.json").read_text()))
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list) is False
    assert drv.device_driver_status is DeviceDriverStatus.DISABLED
    assert drv.stop_device() is False


# every data type and format: write through the driver, check the slave's registers with
# an independent encoder, read back through the driver
ROUND_TRIP = [
    ("Boolean", None, True), ("Byte", None, 200), ("Sbyte", None, -100), ("Int16", None, -1234),
    ("UInt16", None, 54321), ("Int32", None, -123456), ("UInt32", None, 3_000_000_000),
    ("Int64", None, -(2**40) - 7), ("UInt64", None, 2**63 + 11), ("Float", None, 123456.0),
    ("Double", None, -1.0e-3), ("BCD16", None, 1234), ("BCD32", None, 12345678),
    ("String", 5, "héllo"), ("Timestamp", 4, 1_700_000_000_123),
    ("DateTime", 2, datetime(2026, 1, 18, 12, 16, 58, tzinfo=timezone.utc)),
    ("Binary", 3, b"\x01\x02\x03\x04\xfe\xff"),
]


ORDER64 = {"ABCD": "ABCDEFGH", "BADC": "BADCFEHG", "CDAB": "GHEFCDAB", "DCBA": "HGFEDCBA"}


def _expected_registers(dtype: str, value: Any, fmt: str, quantity: int | None,
                        swap16: bool = False, fmt64: str | None = None) -> list[int]:
    """A plain struct-based encoder, independent of our C codec: the value's bytes A, B,
    ... (most significant first) put where the order's letters say (docs/device-files.md "Byte
    order"): one register AB (BA with byteSwap16), two dataFormat, four dataFormat64."""
    big = {
        "Int16": lambda v: struct.pack(">h", v), "UInt16": lambda v: struct.pack(">H", v),
        "Int32": lambda v: struct.pack(">i", v), "UInt32": lambda v: struct.pack(">I", v),
        "Int64": lambda v: struct.pack(">q", v), "UInt64": lambda v: struct.pack(">Q", v),
        "Float": lambda v: struct.pack(">f", v), "Double": lambda v: struct.pack(">d", v),
        "Byte": lambda v: struct.pack(">H", v), "Sbyte": lambda v: struct.pack(">H", v & 0xFF),
        "Boolean": lambda v: struct.pack(">H", int(v)),
        "BCD16": lambda v: bytes.fromhex(f"{v:04d}"), "BCD32": lambda v: bytes.fromhex(f"{v:08d}"),
        "Timestamp": lambda v: struct.pack(">q", v),
        "DateTime": lambda v: struct.pack(">I", int(v.timestamp())),
    }
    if dtype in ("String", "Binary"):
        raw = value.encode() if isinstance(value, str) else value
        raw = raw.ljust(2 * (quantity or 0), b"\0")
    else:
        raw = big[dtype](value)
    if dtype in ("String", "Binary"):  # bytes in dataFormat's order, any length
        regs = [raw[i] << 8 | raw[i + 1] for i in range(0, len(raw), 2)]
        if fmt in ("BADC", "DCBA"):
            regs = [((r & 0xFF) << 8) | (r >> 8) for r in regs]
        return regs[::-1] if fmt in ("CDAB", "DCBA") else regs
    order = {2: "BA" if swap16 else "AB", 4: fmt, 8: fmt64 or ORDER64[fmt]}[len(raw)]
    wire = bytes(raw[ord(letter) - ord("A")] for letter in order)
    return [wire[i] << 8 | wire[i + 1] for i in range(0, len(wire), 2)]


@pytest.mark.parametrize(("fmt", "swap16", "fmt64"), [
    ("ABCD", False, None), ("BADC", False, None), ("CDAB", True, None), ("DCBA", True, None),
    ("BADC", True, "EFGHABCD"), ("CDAB", False, "CDABGHEF"), ("ABCD", True, "FEHGBADC"),
])
def test_every_type_and_format_round_trips(
    slave: PymodbusSlave, fmt: str, swap16: bool, fmt64: str | None
) -> None:
    items = []
    address = 100
    for dtype, quantity, _ in ROUND_TRIP:
        item: dict[str, Any] = {"name": dtype, "address": f"hr:{address}",
                                "deviceDataType": dtype, "dataFormat": fmt,
                                "byteSwap16": swap16}
        if fmt64 is not None:
            item["dataFormat64"] = fmt64
        if quantity:
            item["quantity"] = quantity
        items.append(item)
        address += 10
    items.append({"name": "Coil", "address": "coil:7", "deviceDataType": "Boolean"})
    items.append({"name": "Bit", "address": "hr:90.5", "deviceDataType": "Boolean"})
    items.append({"name": "SwappedBit", "address": "hr:91.5", "deviceDataType": "Boolean",
                  "byteSwap16": True, "dataFormat": fmt})
    cfg = device(slave.port, items)
    with Running(cfg) as drv:
        # address-derived values are not all valid BCD: wait for a first verdict only
        wait_for(lambda: all(it.status is not ItemStatus.UNKNOWN for it in cfg.address_list),
                 what="first read")
        for (dtype, quantity, value), item in zip(ROUND_TRIP, cfg.address_list, strict=False):
            ok, err = drv.write_address(dtype, value)
            assert ok, (dtype, err)
            offset = int(item.address.split(":")[1])
            expected = _expected_registers(dtype, value, fmt, quantity, swap16, fmt64)
            if dtype == "Boolean":  # a whole register, != 0 in any byte order
                assert slave.registers(1, "hr", offset, 1) == [1]
            elif dtype in ("Byte", "Sbyte"):
                # one register; Byte/Sbyte live in the low byte after the 16-bit swap
                got = slave.registers(1, "hr", offset, 1)[0]
                if swap16:
                    got = ((got & 0xFF) << 8) | (got >> 8)
                assert got & 0xFF == value & 0xFF, dtype
            else:
                assert slave.registers(1, "hr", offset, len(expected)) == expected, dtype
        assert drv.write_address("Coil", True) == (True, None)
        assert drv.write_address("Bit", "true") == (True, None)
        assert slave.bits(1, "co", 7, 1) == [True]
        assert slave.registers(1, "hr", 90, 1)[0] == default_register(1, "hr", 90) | (1 << 5)
        assert drv.write_address("SwappedBit", True) == (True, None)  # bit 5 of BA: 13 of AB
        assert slave.registers(1, "hr", 91, 1)[0] == default_register(1, "hr", 91) | (1 << 13)
        # the next cycles read back the same values from the slave
        cycles = drv.stats()["cycles"]
        wait_for(lambda: drv.stats()["cycles"] >= cycles + 2 and all_ok(cfg)(),
                 what="two cycles after the writes, every item Ok")
        for (dtype, _, value), item in zip(ROUND_TRIP, cfg.address_list, strict=False):
            if isinstance(value, float):
                assert item.value == pytest.approx(value, rel=1e-6), dtype
            else:
                assert item.value == value, dtype
        assert all(item.value is True for item in cfg.address_list[-3:])


def test_two_slaves_share_a_line_and_a_dead_one_costs_one_timeout_per_backoff(
    slave: PymodbusSlave,
) -> None:
    items = [{"name": f"r{i}", "address": f"hr:{i * 3}", "deviceDataType": "UInt16"}
             for i in range(4)]
    cycle_ms, timeout_ms = 200, 300
    extra = {"readCycle": cycle_ms, "readTimeout": timeout_ms, "retries": 0,
             "offlineAfterFailedCycles": 2, "maxBackoff": 1600}
    cfgs = [device(slave.port, items, slave=s, **extra) for s in (1, 2, 3)]
    drivers = [em.DriverModbusRtu() for _ in cfgs]
    try:
        for drv, cfg in zip(drivers, cfgs, strict=True):
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        wait_for(lambda: drivers[2].device_driver_status is DeviceDriverStatus.OFFLINE,
                 timeout=20, what="slave 3 offline")
        # one line for the three devices
        assert len(em.DriverModbusRtu.registry.lines()) == 1
        window = 3.0
        before = {s: drv.stats() for s, drv in zip((1, 2, 3), drivers, strict=True)}
        time.sleep(window)  # pacing: the window the probes are counted in
        after = {s: drv.stats() for s, drv in zip((1, 2, 3), drivers, strict=True)}
        # backoff doubles from readCycle (0.2 s) up to maxBackoff (1.6 s): within 3 s at
        # most 0.2 + 0.4 + 0.8 + 1.6 -> 4 probes, one request (one timeout) each
        probes = after[3]["requests"] - before[3]["requests"]
        assert 1 <= probes <= 4, probes
        # (a snapshot may fall between a probe's request and its timeout)
        assert probes - 1 <= after[3]["timeouts"] - before[3]["timeouts"] <= probes
        # each probe holds the line for one timeout plus its settle time, nothing more:
        # the others keep their cycle for the rest of the window
        lost = probes * 2 * timeout_ms / 1000
        for sid in (1, 2):
            assert all(it.status is ItemStatus.OK for it in cfgs[sid - 1].address_list)
            cycles = after[sid]["cycles"] - before[sid]["cycles"]
            assert cycles >= (window - lost) / (cycle_ms / 1000) * 0.7, (cycles, probes)
        dead = cfgs[2].address_list[0]
        assert dead.status is ItemStatus.INVALID
        assert "not responding" in (dead.error_reason or "")
        assert dead.update_ts is not None
        # no reconnects: a silent slave never reopens the link
        assert after[1]["line"]["reconnects"] == 0
    finally:
        for drv in drivers:
            drv.stop_device()


def test_cycle_gap_of_good_slave_with_dead_neighbour(slave: PymodbusSlave) -> None:
    """Measured: the good slave's cycle start-to-start never exceeds readCycle plus one
    response timeout plus its settle time (plus slack) once the dead one is Offline."""
    items = [{"name": "a", "address": "hr:0", "deviceDataType": "UInt16"}]
    extra = {"readCycle": 100, "readTimeout": 200, "retries": 0, "offlineAfterFailedCycles": 1,
             "maxBackoff": 1000, "reportMode": "cycle"}
    good, dead = device(slave.port, items, 1, **extra), device(slave.port, items, 3, **extra)
    stamps: list[float] = []
    with Running(good, address_updated_callback=lambda it: stamps.append(time.monotonic())), \
            Running(dead) as dead_drv:
        wait_for(lambda: dead_drv.device_driver_status is DeviceDriverStatus.OFFLINE)
        time.sleep(1.5)  # pacing: let the backoff grow to its cap (0.1, 0.2, 0.4, 0.8, 1.0 s)
        stamps.clear()
        probes = dead_drv.stats()["requests"]
        time.sleep(3.0)  # pacing: the window the gaps are measured in
        probes = dead_drv.stats()["requests"] - probes
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    assert 2 <= probes <= 4, probes  # one probe per backoff interval (1 s)
    assert len(gaps) >= 15, gaps
    limit = 0.1 + 0.2 + 0.2 + 0.15  # cycle + one timeout + its settle + slack
    assert max(gaps) < limit, gaps
    slow = [g for g in gaps if g > 0.16]
    assert len(slow) <= probes, gaps  # only cycles that met a probe are late


def test_server_restart_then_resume(slave: PymodbusSlave) -> None:
    cfg = device(slave.port, [{"name": "x", "address": "hr:4", "deviceDataType": "UInt16"}])
    with Running(cfg) as drv:
        wait_for(all_ok(cfg))
        slave.kill()
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RECONNECTING)
        item = cfg.address_list[0]
        assert item.status is ItemStatus.INVALID and "link" in (item.error_reason or "")
        assert item.value == default_register(1, "hr", 4)  # the last good value stays
        ok, err = drv.write_address("x", 5)
        assert not ok and err
        slave.restart()
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RUNNING, timeout=20)
        wait_for(all_ok(cfg))
        assert drv.stats()["reconnects"] >= 1


def test_update_addresses_while_running(slave: PymodbusSlave) -> None:
    cfg = device(slave.port, [{"name": "a", "address": "hr:1", "deviceDataType": "UInt16"},
                              {"name": "b", "address": "hr:2", "deviceDataType": "UInt16"}])
    with Running(cfg) as drv:
        wait_for(all_ok(cfg))
        new = em.load_device_config({
            "communication": comm(slave.port),
            "addressList": [{"name": "b", "address": "hr:2", "deviceDataType": "UInt16"},
                            {"name": "c", "address": "ir:7", "deviceDataType": "UInt16"}],
        }).address_list
        assert new[1].status is ItemStatus.UNKNOWN
        drv.update_addresses(new)
        assert new[0].status is ItemStatus.OK  # unchanged item keeps its state
        wait_for(lambda: new[1].status is ItemStatus.OK)
        assert new[1].value == default_register(1, "ir", 7)
        assert [b["items"] for b in drv.read_plan()] == [["b"], ["c"]]
        assert set(drv.snapshot()["items"]) == {"b", "c"}
        with pytest.raises(ValueError, match="addressList"):
            drv.update_addresses(
                [em.DeviceAddressItem(name="bad", address="hr:1.3", device_data_type="Int32")]
            )


def test_stop_with_a_write_pending_fails_cleanly() -> None:
    with Simulator([1]) as sim:
        port = sim.serve_tcp("127.0.0.1", 0)
        cfg = device(port, [{"name": "w", "address": "hr:1", "deviceDataType": "UInt16"}],
                     readTimeout=1000)
        with Running(cfg) as drv:
            wait_for(all_ok(cfg))
            sim.slave(1).faults.delay = 0.4
            results: list[tuple[bool, str | None]] = []
            blocker = threading.Thread(target=lambda: results.append(drv.write_address("w", 7)))
            second = threading.Thread(target=lambda: results.append(drv.write_address("w", 8)))
            blocker.start()
            time.sleep(0.05)  # pacing: the first write in flight first
            second.start()
            time.sleep(0.05)  # pacing: the second queued behind it
            drv.stop_device()
            blocker.join(5)
            second.join(5)
        assert len(results) == 2
        failed = [r for r in results if not r[0]]
        assert failed and all(r[1] for r in failed)
        assert sim.slave(1).get_registers(em.Area.HOLDING_REGISTER, 1)[0] != 8


def test_raising_callback_is_counted_and_polling_goes_on(slave: PymodbusSlave) -> None:
    calls = []

    def boom(item: em.DeviceAddressItem) -> None:
        calls.append(item.name)
        raise RuntimeError("host bug")

    cfg = device(slave.port, [{"name": "a", "address": "hr:1", "deviceDataType": "UInt16"}],
                 reportMode="cycle")
    with Running(cfg, address_updated_callback=boom) as drv:
        wait_for(lambda: len(calls) >= 3)
        stats = drv.stats()
        assert stats["callbackErrors"] >= 3
        assert drv.device_driver_status is DeviceDriverStatus.RUNNING


def test_callbacks_set_while_polling_are_called_and_their_failures_logged_and_counted(
    slave: PymodbusSlave, caplog: pytest.LogCaptureFixture
) -> None:
    """The poller asks for the host's callbacks at each delivery: the item, batch and
    snapshot callbacks set after start_device are called; each failure is logged, and
    the item and batch ones counted; no callback time is counted before one is set."""
    cfg = device(slave.port, [{"name": "a", "address": "hr:1", "deviceDataType": "UInt16"}],
                 reportMode="cycle", snapshotInterval=100)
    items: list[str] = []
    batches: list[int] = []
    topics: list[str] = []

    def item_bug(item: em.DeviceAddressItem) -> None:
        items.append(item.name)
        raise RuntimeError("item callback bug")

    def batch_bug(batch: list[em.DeviceAddressItem]) -> None:
        batches.append(len(batch))
        raise RuntimeError("batch callback bug")

    def publisher_bug(topic: str, snapshot: dict[str, Any]) -> None:
        topics.append(topic)
        raise RuntimeError("publisher bug")

    drv = em.DriverModbusRtu()
    with caplog.at_level(logging.ERROR, logger="edgemodbus.driver"):
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        try:
            wait_for(lambda: drv.stats()["cycles"] >= 2)
            quiet = drv.stats()
            assert (quiet["callbackErrors"], quiet["callbackTime"]) == (0, 0.0)
            drv.address_updated_callback = item_bug
            drv.addresses_updated_callback = batch_bug
            drv.snapshot_publisher = publisher_bug
            wait_for(lambda: len(items) >= 2 and len(batches) >= 2 and len(topics) >= 2)
            assert drv.device_driver_status is DeviceDriverStatus.RUNNING
        finally:
            drv.stop_device()  # joins the line's worker: no callback runs after this
    stats = drv.stats()
    assert stats["callbackErrors"] == len(items) + len(batches)
    assert stats["callbackTime"] > 0
    assert set(items) == {"a"} and set(batches) == {1} and set(topics) == {"/real/dev1"}
    logged = [r.getMessage() for r in caplog.records if r.exc_info is not None]
    assert logged.count("dev1: address_updated_callback failed for item 'a'") == len(items)
    assert logged.count("dev1: addresses_updated_callback failed (1 items)") == len(batches)
    assert logged.count("dev1: snapshot publisher failed") == len(topics)


def test_write_to_input_register_or_unknown_item_fails_at_once(slave: PymodbusSlave) -> None:
    cfg = device(slave.port, [{"name": "ir", "address": "ir:1", "deviceDataType": "UInt16"},
                              {"name": "di", "address": "di:1", "deviceDataType": "Boolean"},
                              {"name": "i16", "address": "hr:1", "deviceDataType": "Int16"}])
    with Running(cfg) as drv:
        ok, err = drv.write_address("ir", 1)
        assert not ok and "read-only" in (err or "") and "input register" in (err or "")
        ok, err = drv.write_address("di", True)
        assert not ok and "discrete input" in (err or "")
        ok, err = drv.write_address("nope", 1)
        assert not ok and "unknown item 'nope'" in (err or "")
        ok, err = drv.write_address("i16", 40000)
        assert not ok and "i16" in (err or "") and "40000" in (err or "")
        ok, err = drv.write_address("i16", "abc")
        assert not ok and "'abc'" in (err or "")


def test_write_addresses_merges_and_async_variants(slave: PymodbusSlave) -> None:
    items = [{"name": f"r{i}", "address": f"hr:{300 + i}", "deviceDataType": "UInt16"}
             for i in range(5)]
    items.append({"name": "f", "address": "hr:305", "deviceDataType": "Float"})
    cfg = device(slave.port, items)
    with Running(cfg) as drv:
        before = slave.request_count(1)
        ok, err = drv.write_addresses([(f"r{i}", 10 + i) for i in range(5)] + [("f", 1.5)])
        assert (ok, err) == (True, None)
        assert slave.registers(1, "hr", 300, 7) == [10, 11, 12, 13, 14, *(
            struct.unpack(">2H", struct.pack(">f", 1.5)))]
        assert drv.stats()["writes"] == 1  # one FC16 for six items
        assert slave.request_count(1) - before >= 1

        async def go() -> tuple[tuple[bool, str | None], tuple[bool, str | None]]:
            return (await drv.write_address_async("r0", "42"),
                    await drv.write_addresses_async([("r1", 43), ("f", math.pi)]))

        one, two = asyncio.run(go())
        assert one == (True, None) and two == (True, None)
        assert slave.registers(1, "hr", 300, 2) == [42, 43]
        assert cfg.address_list[0].value == 42


def test_fc16_refused_falls_back_to_fc06() -> None:
    with Simulator([1]) as sim:
        sim.slave(1).faults.refused_functions = frozenset({16})
        port = sim.serve_tcp("127.0.0.1", 0)
        cfg = device(port, [{"name": "v", "address": "hr:10", "deviceDataType": "UInt32"}])
        with Running(cfg) as drv:
            assert drv.write_address("v", 0x12345678) == (True, None)
            assert sim.slave(1).get_registers(em.Area.HOLDING_REGISTER, 10, 2) == [0x1234, 0x5678]
            assert drv.write_address("v", 7) == (True, None)
            assert sim.slave(1).get_registers(em.Area.HOLDING_REGISTER, 10, 2) == [0, 7]
            # refused once (exception 01), remembered: the second write went FC06 directly
            assert drv.stats()["line"]["exceptions"] == {1: 1}


def test_the_first_snapshot_names_the_device_even_before_start_returns(
        slave: PymodbusSlave, monkeypatch: pytest.MonkeyPatch) -> None:
    """The line may run the first pass and publish its snapshot before start_device
    returns: the snapshot said deviceCode "device" (the driver's organization was set
    after the line started).  Here start_device waits for that snapshot first."""
    published: list[dict[str, Any]] = []
    acquire = em.DriverModbusRtu._acquire

    def acquire_then_wait(self: em.DriverModbusRtu, *args: Any) -> Any:
        got = acquire(self, *args)
        wait_for(lambda: bool(published), what="the first snapshot, before start returns")
        return got

    monkeypatch.setattr(em.DriverModbusRtu, "_acquire", acquire_then_wait)
    cfg = device(slave.port, [{"name": "a", "address": "hr:2", "deviceDataType": "UInt16"}],
                 snapshotInterval=100)
    with Running(cfg, snapshot_publisher=lambda _t, snap: published.append(snap)):
        pass
    assert published[0]["deviceCode"] == "dev1"
    assert published[0]["readCycle"] == cfg.communication.read_cycle


def test_snapshot_and_stats_keys(slave: PymodbusSlave) -> None:
    published: list[tuple[str, dict[str, Any]]] = []
    cfg = device(slave.port, [{"name": "a", "address": "coil:2", "deviceDataType": "Boolean"}],
                 snapshotInterval=100)
    with Running(cfg, snapshot_publisher=lambda t, s: published.append((t, s))) as drv:
        wait_for(all_ok(cfg))
        wait_for(lambda: bool(published))
        snap = drv.snapshot()
        stats = drv.stats()
    assert published[0][0] == "/real/dev1"
    json.dumps(published[-1][1])  # JSON-able
    assert snap["deviceCode"] == "dev1" and snap["dataItemCount"] == 1
    assert snap["items"]["a"]["value"] is default_bit(1, "co", 2)
    assert snap["items"]["a"]["status"] == "Ok"
    for key in ("requests", "responses", "timeouts", "crcErrors", "protocolErrors", "exceptions",
                "retries", "reconnects", "cycles", "overruns", "lastCycleTime", "avgCycleTime",
                "maxCycleTime", "avgRoundTrip", "callbackErrors", "valuesChanged"):
        assert key in stats, key
    assert stats["cycles"] >= 1 and stats["requests"] >= 1
    hist = stats["cycleTimeHistogram"]
    counts = [n for _, n in hist["buckets"]]
    assert counts == sorted(counts) and hist["buckets"][-1] == ["+Inf", stats["cycles"]]
    assert hist["count"] == stats["cycles"]
    assert hist["sum"] == pytest.approx(stats["avgCycleTime"] * stats["cycles"])


def test_callbacks_may_update_addresses_but_not_wait_for_a_write(slave: PymodbusSlave) -> None:
    """A callback runs on the line worker: a blocking write there would wait for itself."""
    cfg = device(slave.port, [{"name": "a", "address": "hr:1", "deviceDataType": "UInt16"}])
    results: list[tuple[bool, str | None]] = []
    new_items = em.load_device_config({
        "communication": comm(slave.port),
        "addressList": [{"name": "b", "address": "hr:2", "deviceDataType": "UInt16"}],
    }).address_list

    runner = Running(cfg)

    def on_item(item: em.DeviceAddressItem) -> None:
        if not results:
            results.append(runner.drv.write_address("a", 1))
            runner.drv.update_addresses(new_items)

    runner.drv.address_updated_callback = on_item
    with runner:
        wait_for(lambda: new_items[0].status is ItemStatus.OK, what="re-planned from a callback")
    assert results[0][0] is False and "line worker" in (results[0][1] or "")
    assert slave.registers(1, "hr", 1, 1) == [default_register(1, "hr", 1)]  # not written


# -- items larger than a block, and what a write publishes ------------------------------

def _cycles_later(drv: em.DriverModbusRtu, n: int) -> None:
    """Wait until ``n`` more poll cycles of ``drv`` have ended."""
    target = drv.stats()["cycles"] + n
    wait_for(lambda: drv.stats()["cycles"] >= target, what=f"{n} more cycles")


def _text_registers(text: str, quantity: int) -> list[int]:
    raw = text.encode().ljust(2 * quantity, b"\0")
    return [raw[i] << 8 | raw[i + 1] for i in range(0, len(raw), 2)]


def _binary_registers(seed: int, quantity: int) -> list[int]:
    return [(seed * 7919 + 257 * i) & 0xFFFF for i in range(quantity)]


def _binary(registers: list[int]) -> bytes:
    return b"".join(r.to_bytes(2, "big") for r in registers)


def test_items_larger_than_a_block_are_read_whole(slave: PymodbusSlave) -> None:
    """A String of 60 registers and a Binary of 100, read in blocks of at most 40: every
    Ok report, on every cycle and after a change, holds the whole item.  (The pieces of
    one item used to get a buffer each: from the second cycle on the item was decoded
    from one piece and zeros, and reported Ok.)"""
    texts = ["".join(chr(97 + (i * k) % 26) for i in range(120)) for k in (1, 3)]
    blobs = [_binary_registers(seed, 100) for seed in (1, 2)]
    slave.set_registers(1, "hr", 500, _text_registers(texts[0], 60))
    slave.set_registers(1, "hr", 600, blobs[0])
    cfg = device(slave.port, [
        {"name": "s", "address": "hr:500", "deviceDataType": "String", "quantity": 60},
        {"name": "b", "address": "hr:600", "deviceDataType": "Binary", "quantity": 100},
    ], readCycle=30, maxBlockReadRegisterCount=40)
    reports: list[tuple[str, ItemStatus, Any]] = []
    record = lambda it: reports.append((it.name, it.status, it.value))  # noqa: E731
    good = {"s": {texts[0]}, "b": {_binary(blobs[0])}}
    with Running(cfg, address_updated_callback=record) as drv:
        assert [(b["start"], b["count"]) for b in drv.read_plan()] == [
            (500, 40), (540, 20), (600, 40), (640, 40), (680, 20)]
        wait_for(all_ok(cfg), what="first read")
        _cycles_later(drv, 4)
        slave.set_registers(1, "hr", 500, _text_registers(texts[1], 60))
        slave.set_registers(1, "hr", 600, blobs[1])
        good = {"s": {texts[0], texts[1]}, "b": {_binary(blobs[0]), _binary(blobs[1])}}
        wait_for(lambda: [it.value for it in cfg.address_list] == [texts[1], _binary(blobs[1])],
                 what="the changed values")
        _cycles_later(drv, 4)
    ok_reports = [(name, value) for name, status, value in reports if status is ItemStatus.OK]
    assert {name for name, _ in ok_reports} == {"s", "b"}
    wrong = [(name, value) for name, value in ok_reports if value not in good[name]]
    assert not wrong, wrong[:2]


def test_item_larger_than_a_block_is_not_ok_while_a_piece_fails(slave: PymodbusSlave) -> None:
    """The second piece of a 60-register String always fails (exception 04): the item is
    never reported Ok, whatever its first piece brings (it used to be reported Ok from
    the first piece and zeros after two cycles)."""
    slave.set_registers(1, "hr", 500, _text_registers("x" * 120, 60))
    slave.set_exception_ranges([ExceptionRange(545, 546, code=4, unit=1)])
    cfg = device(slave.port, [
        {"name": "s", "address": "hr:500", "deviceDataType": "String", "quantity": 60},
        {"name": "n", "address": "hr:400", "deviceDataType": "UInt16"},
    ], readCycle=30, maxBlockReadRegisterCount=40)
    statuses: list[ItemStatus] = []
    record = lambda it: it.name == "s" and statuses.append(it.status)  # noqa: E731
    with Running(cfg, address_updated_callback=record) as drv:
        wait_for(lambda: cfg.address_list[1].status is ItemStatus.OK, what="the small item")
        _cycles_later(drv, 6)
        item = cfg.address_list[0]
        assert item.status is ItemStatus.INVALID and "exception" in (item.error_reason or "")
        assert item.value is None
        # the slave is mended: the next complete cycle brings the whole item
        slave.set_exception_ranges([])
        wait_for(lambda: item.status is ItemStatus.OK, what="the whole item")
        assert item.value == "x" * 120
    assert statuses and ItemStatus.OK not in statuses[:-1], statuses


def test_update_addresses_reads_a_large_item_whole(slave: PymodbusSlave) -> None:
    """The same for an item that arrives by update_addresses (re-planned while running)."""
    text = "".join(chr(65 + i % 26) for i in range(100))
    slave.set_registers(1, "hr", 800, _text_registers(text, 50))
    cfg = device(slave.port, [{"name": "a", "address": "hr:1", "deviceDataType": "UInt16"}],
                 readCycle=30, maxBlockReadRegisterCount=20)
    new = em.load_device_config({
        "communication": comm(slave.port, readCycle=30, maxBlockReadRegisterCount=20),
        "addressList": [{"name": "a", "address": "hr:1", "deviceDataType": "UInt16"},
                        {"name": "s", "address": "hr:800", "deviceDataType": "String",
                         "quantity": 50}],
    }).address_list
    values: list[Any] = []
    record = lambda it: it.name == "s" and values.append((it.status, it.value))  # noqa: E731
    with Running(cfg, address_updated_callback=record) as drv:
        wait_for(all_ok(cfg))
        drv.update_addresses(new)
        wait_for(lambda: new[1].status is ItemStatus.OK, what="the large item")
        _cycles_later(drv, 4)
    assert values and all(v == (ItemStatus.OK, text) for v in values), values[:2]


def test_one_write_publishes_one_update(slave: PymodbusSlave) -> None:
    """A confirmed write reports the item once: one item callback and, at once, one
    batch holding it once; the reads that follow find the written value and report
    nothing more.  (The next read used to report the written value a second time, in
    the same batch, which waited for the end of the next cycle.)"""
    cfg = device(slave.port, [
        {"name": "w", "address": "hr:700", "deviceDataType": "UInt16"},
        {"name": "f", "address": "hr:702", "deviceDataType": "Float", "dataFormat": "CDAB"},
        {"name": "k", "address": "coil:9", "deviceDataType": "Boolean"},
    ], readCycle=30)
    items: list[tuple[str, Any]] = []
    batches: list[list[tuple[str, Any]]] = []
    with Running(cfg,
                 address_updated_callback=lambda it: items.append((it.name, it.value)),
                 addresses_updated_callback=lambda b: batches.append(
                     [(it.name, it.value) for it in b])) as drv:
        wait_for(all_ok(cfg))
        _cycles_later(drv, 2)
        items.clear()
        batches.clear()
        assert drv.write_address("w", 4242) == (True, None)
        assert (items, batches) == ([("w", 4242)], [[("w", 4242)]])
        assert drv.write_addresses([("f", 2.5), ("k", not cfg.address_list[2].value)]) == (
            True, None)
        _cycles_later(drv, 4)
    flag = cfg.address_list[2].value
    assert sorted(items) == sorted([("w", 4242), ("f", 2.5), ("k", flag)]), items
    assert sorted(x for batch in batches for x in batch) == sorted(items), batches


def test_item_read_in_pieces_is_reported_once_per_cycle_when_they_fail(
    slave: PymodbusSlave,
) -> None:
    """reportMode cycle, every piece of a 60-register String fails: the item is reported
    Invalid once per cycle (once per failed piece, it used to be: twice in a batch)."""
    slave.set_exception_ranges([ExceptionRange(500, 560, code=4, unit=1)])
    cfg = device(slave.port, [
        {"name": "s", "address": "hr:500", "deviceDataType": "String", "quantity": 60},
        {"name": "n", "address": "hr:400", "deviceDataType": "UInt16"},
    ], readCycle=30, maxBlockReadRegisterCount=40, reportMode="cycle")
    batches: list[list[str]] = []
    with Running(cfg, addresses_updated_callback=lambda b: batches.append(
            [it.name for it in b])) as drv:
        wait_for(lambda: len(batches) >= 2, what="two cycles")
        _cycles_later(drv, 4)
    assert cfg.address_list[0].status is ItemStatus.INVALID
    assert all(sorted(batch) == ["n", "s"] for batch in batches), batches


def test_a_value_the_slave_goes_back_to_after_a_write_is_read() -> None:
    """A confirmed write sets the item; when the slave then holds its old value again (it
    clamped the write, another master undid it), the next read reports that value.  (The
    poll decoder kept the old value as its last report, saw no change, and the item
    stayed Ok with the written value.)"""
    with Simulator([1]) as sim:
        port = sim.serve_tcp("127.0.0.1", 0)
        slave1 = sim.slave(1)
        slave1.set_registers(em.Area.HOLDING_REGISTER, 40, [5])

        def undo(item: em.DeviceAddressItem) -> None:
            # on the worker, as the write is confirmed: no read comes in between
            if item.value == 77:
                slave1.set_registers(em.Area.HOLDING_REGISTER, 40, [5])

        cfg = device(port, [{"name": "sp", "address": "hr:40", "deviceDataType": "UInt16"},
                            {"name": "nb", "address": "hr:41", "deviceDataType": "UInt16"}],
                     readCycle=30)
        with Running(cfg, address_updated_callback=undo) as drv:
            wait_for(all_ok(cfg))
            assert drv.write_address("sp", 77) == (True, None)
            _cycles_later(drv, 3)
            assert cfg.address_list[0].value == 5
            assert cfg.address_list[0].status is ItemStatus.OK


def test_a_value_the_slave_goes_back_to_after_a_report_is_read() -> None:
    """The same for a wrapped report: a report sets the item, the slave goes back to the
    value the integrity poll read before; the next poll reports it."""
    with Simulator([1]) as sim:
        port = sim.serve_tcp("127.0.0.1", 0, wrapped=True)
        slave1 = sim.slave(1)
        slave1.set_registers(em.Area.HOLDING_REGISTER, 2, [502])
        cfg = device(port, [{"name": "r2", "address": "hr:2", "deviceDataType": "UInt16"}],
                     readCycle=200, framing="wrapped-report")
        with Running(cfg) as drv:
            wait_for(all_ok(cfg))
            item = cfg.address_list[0]
            assert item.value == 502
            slave1.set_registers(em.Area.HOLDING_REGISTER, 2, [7])
            (client,) = sim.clients()
            client.push_report(1, em.Area.HOLDING_REGISTER, 2, 1)  # carries 7
            slave1.set_registers(em.Area.HOLDING_REGISTER, 2, [502])
            wait_for(lambda: drv.stats()["reports"] == 1, what="the report")
            _cycles_later(drv, 2)
            assert (item.status, item.value) == (ItemStatus.OK, 502)


def test_a_report_is_applied_after_a_poll_changed_the_item() -> None:
    """A report repeats a value the last report brought, while a poll in between set the
    item to another one: the report is news and applied.  (The report decoder compared
    with its own last report only, saw no change, and dropped it.)"""
    with Simulator([1]) as sim:
        port = sim.serve_tcp("127.0.0.1", 0, wrapped=True)
        hr = em.Area.HOLDING_REGISTER
        slave1 = sim.slave(1)
        slave1.set_registers(hr, 2, [502])
        cfg = device(port, [{"name": "r2", "address": "hr:2", "deviceDataType": "UInt16"}],
                     readCycle=100, framing="wrapped-report")
        seen: list[int] = []
        with Running(cfg, address_updated_callback=lambda it: seen.append(it.value)) as drv:
            wait_for(all_ok(cfg))
            (client,) = sim.clients()
            for _ in range(2):
                slave1.set_registers(hr, 2, [7])
                client.push_report(1, hr, 2, 1)  # carries 7
                slave1.set_registers(hr, 2, [502])
                wait_for(lambda: seen[-1] == 7, what="the report applied")
                wait_for(lambda: seen[-1] == 502, what="the poll after it")
            assert drv.stats()["reports"] == 2
        assert seen == [502, 7, 502, 7, 502]
