"""The fault matrix (issue 6), end to end through DriverModbusRtu over RTU-over-TCP on
127.0.0.1: our simulator misbehaves on the wire, the driver must reject what is wrong,
never take a value from the wrong request, count what happened and recover.

Every register of the simulator holds a value derived from its slave and address
(``default_register``), so any value that came from another request, another slave or a
mangled frame shows up in the recorded reports.  Tests are named ``test_NN_...`` after
the scenario numbers of the issue; link-level scenarios (TCP resets, refused and hanging
connects, fd exhaustion, serial unplug, callbacks, writes during outages, Modbus TCP
headers) are in test_faults_link.py, which reuses the helpers below.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import Area, DeviceDriverStatus, ItemStatus
from edgemodbus.errors import (
    Acknowledge,
    GatewayPathUnavailable,
    GatewayTargetFailedToRespond,
    IllegalDataValue,
    IllegalFunction,
    ModbusExceptionResponse,
    SlaveDeviceBusy,
    SlaveDeviceFailure,
)
from edgemodbus.line.endpoint import LineTiming, TcpEndpoint
from edgemodbus.line.link import Link
from edgemodbus.line.worker import LineWorker
from edgemodbus.protocol import rtu
from edgemodbus.sim import Simulator, default_bit, default_register
from tests.waiting import wait_for

HR = Area.HOLDING_REGISTER
OK, INVALID = ItemStatus.OK, ItemStatus.INVALID
RUNNING, OFFLINE = DeviceDriverStatus.RUNNING, DeviceDriverStatus.OFFLINE
FRAME_10_REGS = 25  # slave + FC + byte count + 20 data bytes + CRC


# --------------------------------------------------------------------------- helpers
def hr_items(start: int, count: int) -> list[dict[str, Any]]:
    return [{"name": f"hr{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
            for a in range(start, start + count)]


def coil_items(start: int, count: int) -> list[dict[str, Any]]:
    return [{"name": f"co{a}", "address": f"coil:{a}", "deviceDataType": "Boolean"}
            for a in range(start, start + count)]


def expected_value(slave: int, address: str) -> int | bool:
    """What the simulator holds at an item address ("hr:12", "coil:3")."""
    kind, offset = address.split(":")
    if kind == "coil":
        return default_bit(slave, int(offset))
    return default_register(slave, int(offset))


@dataclass
class Report:
    name: str
    status: ItemStatus
    value: Any
    reason: str | None
    ts: datetime | None


@dataclass
class Polled:
    """A running driver, its config and every item report it made (in order)."""

    drv: em.DriverModbusRtu
    cfg: em.DeviceConfig
    slave: int
    reports: list[Report] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def record(self, item: em.DeviceAddressItem) -> None:
        with self.lock:
            self.reports.append(
                Report(item.name, item.status, item.value, item.error_reason, item.update_ts)
            )

    def snapshot(self) -> list[Report]:
        with self.lock:
            return list(self.reports)

    def item(self, name: str) -> em.DeviceAddressItem:
        return next(it for it in self.cfg.address_list if it.name == name)

    def all_ok(self) -> bool:
        return all(it.status is OK for it in self.cfg.address_list)

    def wrong_values(self) -> list[Report]:
        """Reports whose value is not what the slave holds at the item's address: a
        value from another request or a mangled frame.  (An Invalid report keeps the
        last good value, so it must hold the right value too, or None before any.)"""
        want = {it.name: expected_value(self.slave, it.address) for it in self.cfg.address_list}
        return [r for r in self.snapshot()
                if (r.status is OK or r.value is not None) and r.value != want[r.name]]

    def reasons(self) -> list[str]:
        return [r.reason for r in self.snapshot() if r.status is INVALID and r.reason]

    def invalid_reports(self, since: int = 0) -> list[Report]:
        return [r for r in self.snapshot()[since:] if r.status is INVALID]

    def stats(self) -> dict[str, Any]:
        return self.drv.stats()

    def cycles(self) -> int:
        return int(self.stats()["cycles"])


class Rig:
    """A simulator serving RTU over TCP and the drivers polling it."""

    def __init__(self, slaves: tuple[int, ...] = (1, 2, 3)) -> None:
        self.sim = Simulator(slaves)
        self.port = self.sim.serve_tcp("127.0.0.1", 0)
        self.polled: list[Polled] = []

    def comm(self, slave: int, **extra: Any) -> dict[str, Any]:
        base: dict[str, Any] = {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": self.port,
            "slaveId": slave, "readTimeout": 150, "readCycle": 50, "byteTimeout": 30,
            "reconnectInterval": 200, "connectTimeout": 1000, "retries": 0,
            "offlineAfterFailedCycles": 100,
        }
        base.update(extra)
        return base

    def start(self, items: list[dict[str, Any]], slave: int = 1, *, wait_ok: bool = True,
              **extra: Any) -> Polled:
        cfg = em.load_device_config({
            "organization": {"deviceCode": f"dev{slave}"},
            "communication": self.comm(slave, **extra),
            "addressList": items,
        })
        p = Polled(em.DriverModbusRtu(), cfg, slave)
        p.drv.address_updated_callback = p.record
        assert p.drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        self.polled.append(p)
        if wait_ok:
            wait_for(p.all_ok, what=f"slave {slave}: every item Ok")
        return p

    def faults(self, slave: int = 1) -> dict[str, int]:
        return dict(self.sim.slave(slave).stats()["faults"])

    def wait_faults(self, knob: str, n: int, slave: int = 1, timeout: float = 10.0) -> None:
        wait_for(lambda: self.faults(slave).get(knob, 0) >= n, timeout, f"{n} x {knob}")

    def settle(self, p: Polled, cycles: int = 2) -> None:
        """Let ``cycles`` full polling cycles pass (the fault is cleared by then)."""
        start = p.cycles()
        wait_for(lambda: p.cycles() >= start + cycles + 1, what=f"{cycles} cycles")

    def close(self) -> None:
        for p in self.polled:
            p.drv.stop_device()
        self.sim.stop()

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig()
    try:
        yield r
    finally:
        r.close()


def stop_and_count(rig: Rig, p: Polled, knob: str) -> tuple[dict[str, Any], int]:
    """Clear the slave's faults, let the line recover, stop the driver; then every
    request it sent has been answered or timed out, so counters can be compared."""
    rig.sim.slave(p.slave).faults.clear()
    rig.settle(p)
    wait_for(p.all_ok, what="recovery: every item Ok")
    p.drv.stop_device()
    return p.drv.stats(), rig.faults(p.slave).get(knob, 0)


# --------------------------------------------------------------------------- 1
def test_01_silent_slave_costs_one_timeout_per_backoff_interval(rig: Rig) -> None:
    rig.sim.slave(2).faults.silent = True
    extra = {"readCycle": 100, "readTimeout": 150, "offlineAfterFailedCycles": 1,
             "maxBackoff": 600}
    polled = {s: rig.start(hr_items(0, 4), s, wait_ok=s != 2, **extra) for s in (1, 2, 3)}
    dead = polled[2]
    wait_for(lambda: dead.drv.device_driver_status is OFFLINE, what="slave 2 Offline")
    time.sleep(1.4)  # pacing: the backoff doubles from readCycle: 0.1, 0.2, 0.4, then 0.6 (cap)
    before = {s: p.stats() for s, p in polled.items()}
    asked = rig.sim.slave(2).stats()["requests"]
    window = 2.4
    time.sleep(window)  # pacing: the window the probes are counted in
    after = {s: p.stats() for s, p in polled.items()}
    probes = rig.sim.slave(2).stats()["requests"] - asked
    # one probe (one request) per backoff interval of 0.6 s, never more
    assert 2 <= probes <= window / 0.6 + 1, probes
    timeouts = after[2]["timeouts"] - before[2]["timeouts"]
    assert probes - 1 <= timeouts <= probes + 1, (probes, timeouts)
    # a probe holds the line for one timeout plus its settle time: the others keep
    # their cycle for the rest of the window
    lost = probes * 2 * 0.15
    for s in (1, 3):
        cycles = after[s]["cycles"] - before[s]["cycles"]
        assert cycles >= (window - lost) / 0.1 * 0.6, (s, cycles, probes)
        assert polled[s].all_ok() and not polled[s].wrong_values()
        assert after[s]["failedCycles"] == 0
    for item in dead.cfg.address_list:
        assert item.status is INVALID
        assert "not responding" in (item.error_reason or "")
        assert item.update_ts is not None
        assert datetime.now(timezone.utc) - item.update_ts < timedelta(seconds=30)
    # a silent slave never reopens the link
    line = after[1]["line"]
    assert (line["connects"], line["reconnects"], line["linkErrors"]) == (1, 0, 0)


# --------------------------------------------------------------------------- 2
@pytest.mark.parametrize("n", [3, 10])
def test_02_every_nth_reply_dropped(rig: Rig, n: int) -> None:
    # two blocks of ten registers: a reply to the other block would fit the byte count
    # a response timeout a loaded machine's slow reply does not reach (CI saw a 5th
    # timeout with 100 ms): every timeout counted below is a dropped reply
    p = rig.start(hr_items(0, 10) + hr_items(100, 10), retries=1, readCycle=20,
                  readTimeout=400)
    mark = len(p.snapshot())
    rig.sim.slave(1).set_faults(drop_every=n)
    rig.wait_faults("drop_every", 4 if n == 3 else 2)
    stats, drops = stop_and_count(rig, p, "drop_every")
    assert drops >= 2
    assert stats["timeouts"] == drops  # one timeout per dropped reply, no more
    assert stats["retries"] == drops  # each retried once (bounded) and the retry got through
    assert stats["failedCycles"] == 0
    assert stats["requests"] == stats["responses"] + stats["timeouts"]
    assert stats["crcErrors"] == stats["protocolErrors"] == 0
    assert not p.invalid_reports(mark)  # the retry hid every drop from the items
    assert not p.wrong_values()


# --------------------------------------------------------------------------- 3
@pytest.mark.parametrize("lateness", [1.1, 1.45, 1.75])
def test_03_late_reply_is_never_taken_for_the_next_answer(rig: Rig, lateness: float) -> None:
    """A reply up to one more response timeout late is settled away: the next request
    (often the other block, same byte count) gets its own answer."""
    timeout = 0.2
    p = rig.start(hr_items(0, 10) + hr_items(200, 10), readTimeout=200, readCycle=20)
    rig.sim.slave(1).set_faults(delay=lateness * timeout, delay_every=3)
    rig.wait_faults("delay", 5)
    stats, late = stop_and_count(rig, p, "delay")
    assert not p.wrong_values()
    assert stats["timeouts"] == late
    assert stats["crcErrors"] == stats["protocolErrors"] == 0
    # the late replies were read and thrown away by the settle step
    assert stats["line"]["discardedBytes"] >= FRAME_10_REGS * (late - 1)
    for r in p.invalid_reports():
        assert "not responding" in (r.reason or "")


# --------------------------------------------------------------------------- 4
def test_04_late_reply_still_arriving_when_the_settle_time_ends(rig: Rig) -> None:
    """The late reply starts inside the settle window but trickles past its end, into
    the time of the next request: it is drained whole, never read as the next answer."""
    # every reply trickles one byte per 6 ms (150 ms per frame, fine for a 40 ms byte
    # timeout); every 3rd starts 200 ms late: 200..350 ms, the settle window ends at 300
    p = rig.start(hr_items(0, 10) + hr_items(200, 10), readTimeout=150, byteTimeout=40,
                  readCycle=20)
    rig.sim.slave(1).set_faults(byte_delay=0.006, delay=0.2, delay_every=3)
    rig.wait_faults("delay", 3)
    stats, late = stop_and_count(rig, p, "delay")
    assert not p.wrong_values()
    # every late reply is a timeout (one taken as the next answer would make fewer); a
    # loaded machine stretching the 6 ms trickle past the 40 ms byte timeout adds some
    # (6 for 3 late in a run beside two busy processes)
    assert stats["timeouts"] >= late
    assert stats["crcErrors"] == stats["protocolErrors"] == 0
    assert stats["line"]["discardedBytes"] >= FRAME_10_REGS * (late - 1)


# --------------------------------------------------------------------------- 5
@pytest.mark.parametrize("knob", ["corrupt_data_every", "corrupt_crc_every"])
def test_05_flipped_bit_in_data_or_crc(rig: Rig, knob: str) -> None:
    p = rig.start(hr_items(0, 10))
    mark = len(p.snapshot())
    rig.sim.slave(1).set_faults(**{knob: 3})
    rig.wait_faults(knob, 3)
    stats, flips = stop_and_count(rig, p, knob)
    invalid = p.invalid_reports(mark)
    assert invalid and all("CRC" in (r.reason or "") for r in invalid)
    # each bad frame invalidates its block's ten items once; the next cycle is fine
    assert len(invalid) == 10 * flips
    assert stats["crcErrors"] == flips
    assert not p.wrong_values()  # the value stays the last good one
    last = {r.name: r.status for r in p.snapshot()}
    assert set(last.values()) == {OK}


# --------------------------------------------------------------------------- 6, 7
@pytest.mark.parametrize(
    ("patch", "reason"),
    [
        ({0: 0x03}, "wrong slave id"),  # slave 1 -> 3 (one bit), CRC recomputed
        ({1: 0x01}, "function code of the reply is not the request's (0x01"),  # FC 03 -> 01
        ({1: 0x83}, "CRC"),  # FC 03 -> 83: framed as an exception, its CRC cannot hold
        ({2: 0xFF}, "byte count too large"),  # 0xFF: never read past 256 bytes
        ({2: 0x12}, "CRC"),  # 20 -> 18: framed short, so the CRC is at the wrong place
        ({2: 0x16}, "incomplete reply"),  # 20 -> 22: waits for bytes that never come
    ],
    ids=["slave-id", "function", "function-0x83", "count-0xff", "count-short", "count-long"],
)
def test_06_flipped_slave_id_function_or_byte_count(
    rig: Rig, patch: dict[int, int], reason: str
) -> None:
    p = rig.start(hr_items(0, 10))
    rig.sim.slave(1).set_faults(patch=patch, patch_every=2)
    rig.wait_faults("patch_every", 3)
    stats, bad = stop_and_count(rig, p, "patch_every")
    reasons = p.reasons()
    assert reasons and all(reason in r for r in reasons), reasons
    assert stats["protocolErrors"] + stats["crcErrors"] + stats["timeouts"] == bad
    assert not p.wrong_values()


@pytest.mark.parametrize("claimed", [3, 0, 248])
def test_07_valid_crc_wrong_slave_id(rig: Rig, claimed: int) -> None:
    p = rig.start(hr_items(0, 10))
    rig.sim.slave(1).set_faults(answer_as=claimed)
    rig.wait_faults("answer_as", 3)
    reasons = p.reasons()
    assert reasons and all("wrong slave id" in r for r in reasons), reasons
    stats, bad = stop_and_count(rig, p, "answer_as")
    assert stats["protocolErrors"] == bad
    assert not p.wrong_values()


# --------------------------------------------------------------------------- 8
def test_08_exception_response_for_another_function(rig: Rig) -> None:
    p = rig.start(hr_items(0, 10))
    rig.sim.slave(1).set_faults(exception_for_other_function=True)
    rig.wait_faults("exception_for_other_function", 3)
    reasons = p.reasons()
    assert reasons and all("exception response for another function code (0x84" in r
                           for r in reasons), reasons
    stats, bad = stop_and_count(rig, p, "exception_for_other_function")
    assert stats["protocolErrors"] == bad
    assert stats["exceptions"] == {}  # not taken for an exception to our request
    assert not p.wrong_values()


# --------------------------------------------------------------------------- 9
EXCEPTIONS: list[tuple[int, type[ModbusExceptionResponse], str]] = [
    (0x01, IllegalFunction, "0x01 (illegal function)"),
    (0x03, IllegalDataValue, "0x03 (illegal data value)"),
    (0x04, SlaveDeviceFailure, "0x04 (slave device failure)"),
    (0x05, Acknowledge, "0x05 (acknowledge)"),
    (0x06, SlaveDeviceBusy, "0x06 (slave device busy)"),
    (0x0A, GatewayPathUnavailable, "0x0a (gateway path unavailable)"),
    (0x0B, GatewayTargetFailedToRespond, "0x0b (gateway target device failed to respond)"),
    (0x0C, ModbusExceptionResponse, "undefined exception code 0x0c"),
    (0xA5, ModbusExceptionResponse, "undefined exception code 0xa5"),
]


@pytest.mark.parametrize(("code", "cls", "text"), EXCEPTIONS, ids=[f"{c:#04x}" for c, *_ in
                                                                    EXCEPTIONS])
def test_09_exception_codes(
    rig: Rig, code: int, cls: type[ModbusExceptionResponse], text: str
) -> None:
    # hr:50 is a block of its own (the gap to hr:0-4 is larger than maxMergeAddressGap)
    p = rig.start(hr_items(0, 5) + hr_items(50, 1))
    rig.sim.slave(1).faults.exception_ranges = [(HR, 50, 51, code)]
    # answered with the exception in every cycle: the read is tried again each time,
    # and the slave, which answers, stays Running
    wait_for(lambda: p.stats()["exceptions"].get(code, 0) >= 3, what="3 exceptions")
    assert p.drv.device_driver_status is RUNNING
    bad = p.item("hr50")
    assert bad.status is INVALID and text in (bad.error_reason or ""), bad.error_reason
    assert all(p.item(f"hr{a}").status is OK for a in range(5))
    # the typed error, as the line worker hands it over (the driver shows its text)
    worker = LineWorker(TcpEndpoint("127.0.0.1", rig.port), LineTiming(response_timeout=1.0))
    worker.start()
    try:
        with pytest.raises(cls) as info:
            worker.read(1, HR, 50, 1).result(5)
        assert type(info.value) is cls and info.value.code == code
    finally:
        worker.stop()
    rig.sim.slave(1).faults.exception_ranges = []  # 5 (acknowledge), 6 (busy): try later
    wait_for(lambda: bad.status is OK, what="hr50 Ok on a later cycle")
    assert bad.value == default_register(1, 50)
    assert not p.wrong_values()


def test_09_illegal_address_splits_the_block_down_to_the_bad_addresses(rig: Rig) -> None:
    p = rig.start(hr_items(0, 10))
    assert len(p.drv.read_plan()) == 1
    rig.sim.slave(1).faults.exception_ranges = [(HR, 4, 6, 0x02)]
    wait_for(lambda: p.item("hr4").status is INVALID and p.item("hr5").status is INVALID,
             what="hr4, hr5 Invalid")
    rig.settle(p)
    for a in range(10):
        item = p.item(f"hr{a}")
        if a in (4, 5):
            assert item.status is INVALID
            assert "0x02 (illegal data address)" in (item.error_reason or "")
        else:
            assert item.status is OK and item.value == default_register(1, a), a
    plan = p.drv.read_plan()
    assert len(plan) > 1
    for block in plan:  # the split is kept: the bad addresses are read on their own
        if {"hr4", "hr5"} & set(block["items"]):
            assert set(block["items"]) <= {"hr4", "hr5"}, plan
    assert sum(b["count"] for b in plan) == 10
    assert not p.wrong_values()


# --------------------------------------------------------------------------- 10
def test_10_byte_count_inconsistent_with_the_request(rig: Rig) -> None:
    p = rig.start(hr_items(0, 10) + coil_items(0, 16))
    rig.sim.slave(1).set_faults(wrong_byte_count_every=2)
    rig.wait_faults("wrong_byte_count_every", 4)
    reasons = set(p.reasons())
    assert reasons
    assert all("byte count does not match the request" in r for r in reasons), reasons
    stats, bad = stop_and_count(rig, p, "wrong_byte_count_every")
    assert stats["protocolErrors"] == bad
    assert not p.wrong_values()


# --------------------------------------------------------------------------- 11
def test_11_truncated_frame_then_silence(rig: Rig) -> None:
    p = rig.start(hr_items(0, 10))
    rig.sim.slave(1).set_faults(truncate_every=2)
    rig.wait_faults("truncate_every", 3)
    reasons = p.reasons()
    assert reasons and all("incomplete reply (byte timeout)" in r for r in reasons), reasons
    stats, cut = stop_and_count(rig, p, "truncate_every")
    assert stats["timeouts"] == cut
    assert stats["crcErrors"] == stats["protocolErrors"] == 0
    assert not p.wrong_values()  # no partial values


# --------------------------------------------------------------------------- 12
@pytest.mark.parametrize("garbage", [b"\xde\xad\xbe\xef", b"\x01\x03\xff\x00\x00\x00\x00"],
                         ids=["noise", "frame-like"])
def test_12_trailing_garbage_after_a_good_frame(rig: Rig, garbage: bytes) -> None:
    p = rig.start(hr_items(0, 10) + hr_items(200, 10))
    mark = len(p.snapshot())
    rig.sim.slave(1).set_faults(trailing_garbage=garbage)
    rig.wait_faults("trailing_garbage", 10)
    stats, sent = stop_and_count(rig, p, "trailing_garbage")
    # every frame accepted, the garbage drained: the next request never saw it
    assert stats["crcErrors"] == stats["protocolErrors"] == stats["timeouts"] == 0
    assert not p.invalid_reports(mark)
    assert stats["line"]["discardedBytes"] >= 4 * (sent - 1)
    assert not p.wrong_values()


# --------------------------------------------------------------------------- 13
def test_13_noise_bytes_before_a_frame(rig: Rig) -> None:
    p = rig.start(hr_items(0, 10))
    rig.sim.slave(1).set_faults(noise_before=b"\x00\xff\x13")
    rig.wait_faults("noise_before", 3)
    assert p.reasons()  # rejected (it cannot be framed)
    stats, _ = stop_and_count(rig, p, "noise_before")
    assert stats["crcErrors"] + stats["protocolErrors"] + stats["timeouts"] >= 1
    assert not p.wrong_values()


# --------------------------------------------------------------------------- 14
def test_14_local_echo_without_the_option_is_a_clear_error(rig: Rig) -> None:
    p = rig.start(hr_items(0, 10))
    rig.sim.slave(1).set_faults(echo_request=True)
    rig.wait_faults("echo_request", 3)
    reasons = p.reasons()
    assert reasons and all("set the 'echo' option" in r for r in reasons), reasons
    stats, _ = stop_and_count(rig, p, "echo_request")
    assert stats["protocolErrors"] >= 1
    assert not p.wrong_values()


def test_14_local_echo_is_skipped_with_the_echo_option(rig: Rig) -> None:
    rig.sim.slave(1).set_faults(echo_request=True)
    p = rig.start(hr_items(0, 10) + coil_items(0, 8), echo=True)
    start = p.stats()
    rig.settle(p, 3)
    assert p.drv.write_address("hr3", 777) == (True, None)
    assert p.drv.write_addresses([("hr4", 1), ("hr5", 2)]) == (True, None)
    assert p.drv.write_address("co1", True) == (True, None)
    assert rig.sim.slave(1).get_registers(HR, 3, 3) == [777, 1, 2]
    assert rig.sim.slave(1).get_bits(Area.COIL, 1) == [True]
    stats = p.stats()
    assert stats["crcErrors"] == stats["protocolErrors"] == stats["timeouts"] == 0
    assert stats["writeErrors"] == 0
    assert all(it.status is OK for it in p.cfg.address_list)
    # each request came back as its echo first: 8 bytes per read, read and skipped
    reads = stats["requests"] - start["requests"]
    assert stats["line"]["discardedBytes"] - start["line"]["discardedBytes"] >= 8 * reads
    assert rig.faults()["echo_request"] >= reads


# --------------------------------------------------------------------------- 15
def test_15_one_byte_every_5_ms_within_the_byte_timeout(rig: Rig) -> None:
    p = rig.start(hr_items(0, 10), byteTimeout=100)
    mark = len(p.snapshot())
    rig.sim.slave(1).set_faults(byte_delay=0.005)
    rig.wait_faults("byte_delay", 5)
    stats, _ = stop_and_count(rig, p, "byte_delay")
    assert stats["crcErrors"] == stats["protocolErrors"] == stats["timeouts"] == 0
    assert not p.invalid_reports(mark) and not p.wrong_values()


def test_15_one_byte_every_5_ms_past_the_byte_timeout(rig: Rig) -> None:
    p = rig.start(hr_items(0, 10), byteTimeout=1)
    rig.sim.slave(1).set_faults(byte_delay=0.005)
    rig.wait_faults("byte_delay", 4)
    reasons = p.reasons()
    assert reasons and all("incomplete reply (byte timeout)" in r for r in reasons), reasons
    rig.sim.slave(1).faults.clear()
    rig.settle(p)
    stats = p.stats()
    # a clean timeout: the rest of each slow frame was drained, the next request
    # never read it
    assert stats["timeouts"] >= 3
    assert stats["crcErrors"] == stats["protocolErrors"] == 0
    assert not p.wrong_values()


# --------------------------------------------------------------------------- 16
OVERSIZED = {
    # byte count 0xFF: libmodbus stops at the 256-byte RTU limit, nothing overflows
    "count-0xff": b"\x01\x03\xff" + bytes(range(256)) + bytes(41),
    # a well-formed 250-data-byte frame (valid CRC) then 45 more bytes: 300 in all
    "valid-crc": rtu.frame(1, b"\x03\xfa" + bytes(250)) + b"\x55" * 45,
}


@pytest.mark.parametrize("raw", OVERSIZED.values(), ids=OVERSIZED.keys())
def test_16_a_300_byte_reply(rig: Rig, raw: bytes) -> None:
    assert len(raw) == 300
    p = rig.start(hr_items(0, 10))
    rig.sim.slave(1).set_faults(raw_reply=raw, raw_reply_every=2)
    rig.wait_faults("raw_reply_every", 3)
    reasons = p.reasons()
    assert reasons and all("byte count" in r for r in reasons), reasons
    stats, bad = stop_and_count(rig, p, "raw_reply_every")
    assert stats["protocolErrors"] == bad
    assert stats["line"]["discardedBytes"] >= 40 * bad  # the rest of each was drained
    assert not p.wrong_values()


# --------------------------------------------------------------------------- 17
def test_17_a_slave_answering_a_broadcast_is_ignored_and_the_turnaround_kept(
    rig: Rig,
) -> None:
    """DriverModbusRtu never broadcasts (slaveId is 1..247 on RTU lines), so this goes
    through the line worker the driver uses."""
    rig.sim.slave(1).set_faults(answer_broadcast=True, delay=0.05)
    rig.sim.slave(2).set_faults(answer_broadcast=True)
    turnaround = 0.2
    worker = LineWorker(TcpEndpoint("127.0.0.1", rig.port),
              LineTiming(response_timeout=0.5, turnaround_delay=turnaround))
    worker.start()

    def job(link: Link) -> tuple[float, list[int], list[int]]:
        link.write_register(0, 7, 4242)  # broadcast: every slave executes it
        sent = time.monotonic()
        first = link.read(1, HR, 7, 1).to_list()
        waited = time.monotonic() - sent
        return waited, first, link.read(2, HR, 6, 2).to_list()

    try:
        waited, one, two = worker.submit(job).result(10)
    finally:
        worker.stop()
    assert waited >= turnaround * 0.95  # the next request waited for the turnaround
    assert one == [4242]  # the read got its own answer, not a slave's broadcast answer
    assert two == [default_register(2, 6), 4242]
    assert worker.stats.discarded_bytes >= 2 * 8  # both answers (8-byte echoes) dropped
    assert worker.stats.protocol_errors == worker.stats.crc_errors == worker.stats.timeouts == 0


# --------------------------------------------------------------------------- 20
def test_20_reply_split_across_tcp_segments(rig: Rig) -> None:
    # timeouts far above a loaded machine's stall of the simulator between two segments
    # (the rig's 30 ms byte timeout is not: the test failed in a run beside two busy
    # processes); the 4 ms pause is what the link must join
    p = rig.start(hr_items(0, 10) + hr_items(200, 10), readTimeout=3000, byteTimeout=1000)
    mark = len(p.snapshot())
    rig.sim.slave(1).set_faults(split_reply=5, split_pause=0.004)
    rig.wait_faults("split_reply", 6)
    stats, _ = stop_and_count(rig, p, "split_reply")
    assert stats["crcErrors"] == stats["protocolErrors"] == stats["timeouts"] == 0
    assert not p.invalid_reports(mark) and not p.wrong_values()


def test_20_two_replies_in_one_segment(rig: Rig) -> None:
    """A DTU holds a reply the master gave up on and sends it with the next one: the
    stale frame (to the other block, same byte count) is recognised and skipped."""
    p = rig.start(hr_items(0, 10) + hr_items(200, 10))
    rig.sim.slave(1).set_faults(hold_reply_every=3)
    rig.wait_faults("hold_reply_every", 4)
    stats, held = stop_and_count(rig, p, "hold_reply_every")
    assert not p.wrong_values()
    assert stats["timeouts"] == held  # the held replies' requests timed out
    assert stats["crcErrors"] == stats["protocolErrors"] == 0
    assert stats["line"]["discardedBytes"] >= FRAME_10_REGS * (held - 1)


# --------------------------------------------------------------------------- fuzz-like
def test_random_bytes_for_n_requests_then_recovery(rig: Rig) -> None:
    p = rig.start(hr_items(0, 10) + hr_items(200, 10) + coil_items(0, 16))
    rig.sim.slave(1).set_faults(random_reply_count=40)
    wait_for(lambda: rig.sim.slave(1).faults.random_reply_count == 0, what="40 random replies")
    rig.settle(p, 3)
    wait_for(p.all_ok, what="recovery")
    stats = p.stats()
    assert stats["protocolErrors"] + stats["crcErrors"] >= 10
    assert p.drv.device_driver_status is RUNNING
    assert not p.wrong_values()
