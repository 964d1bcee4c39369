"""Gateway forward mode, line side: ``DriverModbusRtu.forward`` sends request PDUs to
pymodbus (own process) over RTU on TCP, Modbus TCP and RTU on a socat pty pair, between
the line's own polling; our simulator plays the slave whose replies are corrupted and a
DTU that dials in."""

from __future__ import annotations

import socket
import struct
import time
import urllib.request
from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import Area, DeviceDriverStatus, ItemStatus
from edgemodbus.errors import (
    CrcError,
    ModbusConnectionError,
    ModbusTimeoutError,
    ProtocolError,
    TargetBackoffError,
)
from edgemodbus.northbound.metrics import MetricsExporter
from edgemodbus.protocol.forward import (
    InvalidRequestError,
    UnsupportedFunctionError,
    exception_code_for,
)
from edgemodbus.sim import Simulator
from tests.conftest import SlaveFactory
from tests.engines import with_engine
from tests.peers import ExceptionRange, PymodbusSlave
from tests.waiting import wait_for

TRANSPORTS = ("rtu-over-tcp", "tcp", "serial")
FAILING = ExceptionRange(500, 510, code=4, unit=1)  # "slave device failure"


@pytest.fixture(params=TRANSPORTS)
def peer(request: pytest.FixtureRequest, slave_factory: SlaveFactory) -> PymodbusSlave:
    """A pymodbus slave (units 1 and 2, 2000 of each area) on each kind of line."""
    kw: dict[str, Any] = {"units": (1, 2), "size": 2000, "exception_ranges": [FAILING]}
    if request.param == "serial":
        pty = request.getfixturevalue("pty_pair")
        return slave_factory("serial", device=pty.b, master_path=pty.a, **kw)
    return slave_factory(request.param, **kw)


def comm(peer: PymodbusSlave | int, slave: int, **extra: Any) -> dict[str, Any]:
    """Communication settings for a device on ``peer`` (a port: our simulator)."""
    if isinstance(peer, int):
        base: dict[str, Any] = {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                                "tcpPort": peer}
    elif peer.transport == "serial":
        base = {"transport": "rtu", "comPort": peer.master_path, "baudRate": 19200}
    else:
        base = {"transport": peer.transport, "tcpHost": "127.0.0.1", "tcpPort": peer.port}
    base.update({"slaveId": slave, "readTimeout": 1000, "readCycle": 50, "byteTimeout": 100,
                 "reconnectInterval": 300, "connectTimeout": 2000, "retries": 0})
    base.update(extra)
    return base


class Started:
    """Drivers started for the test, stopped at its end."""

    def __init__(self) -> None:
        self.drivers: list[em.DriverModbusRtu] = []

    def __call__(self, communication: dict[str, Any], items: int = 4) -> em.DriverModbusRtu:
        cfg = em.load_device_config({
            "organization": {"deviceCode": f"dev{communication['slaveId']}"},
            "communication": communication,
            "addressList": [{"name": f"r{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
                            for a in range(items)],
        })
        drv = em.DriverModbusRtu()
        self.drivers.append(drv)
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        return drv


@pytest.fixture
def started() -> Iterator[Started]:
    drivers = Started()
    yield drivers
    for drv in reversed(drivers.drivers):
        drv.stop_device()


def running(drv: em.DriverModbusRtu) -> None:
    wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RUNNING, 15,
             "the device polled")


def forward(drv: em.DriverModbusRtu, pdu: bytes, timeout: float | None = None) -> bytes:
    return drv.forward(pdu, timeout).result(15)


def packed(bits: list[bool]) -> bytes:
    """Bits LSB first in each byte (Modbus Application Protocol v1.1b3, 6.1)."""
    out = bytearray((len(bits) + 7) // 8)
    for i, bit in enumerate(bits):
        if bit:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def regs(values: list[int]) -> bytes:
    return struct.pack(f">{len(values)}H", *values)


# -- reads and writes ------------------------------------------------------------------
def test_reads_of_every_area_are_the_slaves_values(peer: PymodbusSlave,
                                                   started: Started) -> None:
    drv = started(comm(peer, 1))
    running(drv)
    coils, inputs = peer.bits(1, "co", 3, 19), peer.bits(1, "di", 1990, 10)
    holding, input_regs = peer.registers(1, "hr", 100, 125), peer.registers(1, "ir", 0, 7)
    assert forward(drv, struct.pack(">BHH", 1, 3, 19)) == b"\x01\x03" + packed(coils)
    assert forward(drv, struct.pack(">BHH", 2, 1990, 10)) == b"\x02\x02" + packed(inputs)
    assert forward(drv, struct.pack(">BHH", 3, 100, 125)) == b"\x03\xfa" + regs(holding)
    assert forward(drv, struct.pack(">BHH", 4, 0, 7)) == b"\x04\x0e" + regs(input_regs)
    # and the other unit on the same line, through its own device
    other = started(comm(peer, 2))
    assert forward(other, struct.pack(">BHH", 3, 0, 3)) == b"\x03\x06" + regs(
        peer.registers(2, "hr", 0, 3))
    line = drv.stats()["line"]
    assert line["forwarded"] == 5
    assert line["forwardTimeouts"] == line["forwardExceptions"] == line["forwardErrors"] == 0


def test_writes_of_each_kind_land(peer: PymodbusSlave, started: Started) -> None:
    drv = started(comm(peer, 1))
    running(drv)
    requests = [
        (struct.pack(">BHH", 5, 40, 0xFF00), 5),  # FC05 on
        (struct.pack(">BHH", 5, 41, 0x0000), 5),  # FC05 off
        (struct.pack(">BHH", 6, 300, 0xBEEF), 5),
        (struct.pack(">BHHB", 15, 50, 11, 2) + packed([True, False] * 5 + [True]), 5),
        (struct.pack(">BHHB3H", 16, 310, 3, 6, 1, 0x8000, 65535), 5),
        (struct.pack(">BHHH", 22, 300, 0x00F2, 0x0025), 7),  # 6.16's own example masks
    ]
    peer.set_bits(1, "co", 41, [True])
    for pdu, echo in requests:
        assert forward(drv, pdu) == pdu[:echo], pdu.hex()
    assert peer.bits(1, "co", 40, 2) == [True, False]
    assert peer.bits(1, "co", 50, 11) == [True, False] * 5 + [True]
    assert peer.registers(1, "hr", 310, 3) == [1, 0x8000, 65535]
    assert peer.registers(1, "hr", 300, 1) == [(0xBEEF & 0x00F2) | (0x0025 & ~0x00F2 & 0xFFFF)]
    # FC17: the write happens before the read (6.17), so the read sees it
    reply = forward(drv, struct.pack(">BHHHHB2H", 23, 320, 2, 321, 2, 4, 7, 8))
    assert reply == b"\x17\x04" + regs([peer.registers(1, "hr", 320, 1)[0], 7])
    assert peer.registers(1, "hr", 321, 2) == [7, 8]


def test_an_exception_reply_passes_through_unchanged(peer: PymodbusSlave,
                                                     started: Started) -> None:
    drv = started(comm(peer, 1))
    running(drv)
    assert forward(drv, struct.pack(">BHH", 3, 505, 2)) == b"\x83\x04"  # the failing range
    assert forward(drv, struct.pack(">BHH", 4, 1999, 2)) == b"\x84\x02"  # past the map
    assert forward(drv, struct.pack(">BHH", 6, 2000, 1)) == b"\x86\x02"
    line = drv.stats()["line"]
    assert line["forwardExceptions"] == 3
    assert line["exceptions"].get(2, 0) >= 2 and line["exceptions"].get(4, 0) >= 1
    stats = drv.stats()
    assert stats["failedCycles"] == 0 and stats["exceptions"] == {}  # not the device's
    assert drv.device_driver_status is DeviceDriverStatus.RUNNING


# -- a dead slave --------------------------------------------------------------------------
@pytest.mark.parametrize("peer", ["rtu-over-tcp", "serial"], indirect=True)
def test_a_dead_slave_times_out_while_the_line_keeps_polling(peer: PymodbusSlave,
                                                             started: Started) -> None:
    live = started(comm(peer, 1, settleTimeout=1000))
    running(live)
    # its readTimeout (3 s) is not what a forward with its own timeout waits
    dead = started(comm(peer, 9, readCycle=3_600_000, readTimeout=3000,
                        offlineAfterFailedCycles=1000), items=1)
    wait_for(lambda: dead.stats().get("timeouts", 0) >= 1, 15, "the dead slave's first poll")
    dead_before = dead.stats()
    timeout = 0.4
    for n in range(3):
        cycles = live.stats()["cycles"]
        start = time.monotonic()
        future = dead.forward(struct.pack(">BHH", 3, 0, 1), timeout)
        with pytest.raises(ModbusTimeoutError) as info:
            future.result(15)
        elapsed = time.monotonic() - start
        assert exception_code_for(info.value) == 0x0B
        print(f"forward to a dead slave: {elapsed:.3f} s")
        if n == 0:  # the forward's timeout; the line's settle (1 s) comes after the answer
            assert timeout - 0.02 <= elapsed < timeout + 0.8, elapsed
        else:  # then the slave is backing off: 0B at once, nothing sent
            assert isinstance(info.value, TargetBackoffError), info.value
            assert elapsed < timeout, elapsed
        wait_for(lambda c=cycles: live.stats()["cycles"] >= c + 3, 10,
                 "the live device polling on after the forward")
    line = live.stats()["line"]
    assert line["forwarded"] == line["forwardTimeouts"] == 1
    assert line["targetBackoffs"] == 2
    assert line["timeouts"] >= 1
    # not counted against either device: the live one polls on, the dead one's
    # counters and status are its own polling's
    assert live.stats()["failedCycles"] == 0
    assert live.device_driver_status is DeviceDriverStatus.RUNNING
    dead_after = dead.stats()
    for key in ("timeouts", "failedCycles", "requests"):
        assert dead_after[key] == dead_before[key], key


def test_forwards_interleave_with_polling(started: Started,
                                          slave_factory: SlaveFactory) -> None:
    peer = slave_factory("rtu-over-tcp", units=(1, 2), size=2000)
    poller = started(comm(peer, 2, readCycle=20))
    drv = started(comm(peer, 1))
    running(poller)
    running(drv)
    cycles = poller.stats()["cycles"]
    deadline = time.monotonic() + 1.0
    n = 0
    while time.monotonic() < deadline or n < 20:
        value = n & 0xFFFF
        assert forward(drv, struct.pack(">BHH", 6, 7, value)) == struct.pack(">BHH", 6, 7, value)
        n += 1
    assert peer.registers(1, "hr", 7, 1) == [(n - 1) & 0xFFFF]
    assert poller.stats()["cycles"] > cycles + 5  # polled between the forwards
    assert all(it["status"] == ItemStatus.OK.value for it in poller.snapshot()["items"].values())
    assert drv.stats()["line"]["forwarded"] == n


# -- bad replies -----------------------------------------------------------------------------
@pytest.fixture
def sim() -> Iterator[tuple[Simulator, int]]:
    simulator = Simulator((1,))
    port = simulator.serve_tcp("127.0.0.1", 0)
    try:
        yield simulator, port
    finally:
        simulator.stop()


def test_a_crc_bad_or_malformed_reply_fails_with_the_librarys_error(
        sim: tuple[Simulator, int], started: Started) -> None:
    simulator, port = sim
    drv = started(comm(port, 1, readCycle=3_600_000, settleTimeout=100))
    running(drv)
    read = struct.pack(">BHH", 3, 0, 4)
    good = forward(drv, read)
    simulator.slave(1).set_faults(corrupt_crc_every=1)
    with pytest.raises(CrcError) as crc:
        forward(drv, read)
    assert exception_code_for(crc.value) == 0x0B
    # a write whose echo names another address (CRC recomputed): not what was asked
    simulator.slave(1).set_faults(corrupt_crc_every=0, patch={3: 0x63}, patch_every=1)
    with pytest.raises(ProtocolError, match="echo"):
        forward(drv, struct.pack(">BHH", 6, 1, 5))
    simulator.slave(1).set_faults(patch={}, patch_every=0)
    assert forward(drv, read)[:2] == good[:2]  # the line is clean again
    line = drv.stats()["line"]
    assert line["forwarded"] == 4 and line["forwardErrors"] == 2
    assert line["crcErrors"] >= 1 and line["protocolErrors"] >= 1
    assert drv.stats()["failedCycles"] == 0


# -- refused requests, a stopped device, counters in Prometheus ----------------------------
def test_refused_requests_raise_before_anything_is_sent(started: Started,
                                                        slave_factory: SlaveFactory) -> None:
    peer = slave_factory("rtu-over-tcp", units=(1,))
    drv = started(comm(peer, 1))
    running(drv)
    with pytest.raises(UnsupportedFunctionError) as fn:
        drv.forward(bytes.fromhex("2b0e0100"))  # read device identification: not framed
    assert exception_code_for(fn.value) == 0x01
    with pytest.raises(InvalidRequestError) as bad:
        drv.forward(struct.pack(">BHH", 3, 0, 126))
    assert exception_code_for(bad.value) == 0x03
    with pytest.raises(ValueError, match="timeout"):
        drv.forward(struct.pack(">BHH", 3, 0, 1), timeout=0)
    assert drv.stats()["line"]["forwarded"] == 0
    drv.stop_device()
    with pytest.raises(ModbusConnectionError, match="not running") as down:
        drv.forward(struct.pack(">BHH", 3, 0, 1)).result(5)
    assert exception_code_for(down.value) == 0x0A


def test_forward_counters_are_in_prometheus(started: Started,
                                            slave_factory: SlaveFactory) -> None:
    peer = slave_factory("rtu-over-tcp", units=(1,), size=100)
    drv = started(comm(peer, 1))
    dead = started(comm(peer, 7, readCycle=3_600_000, offlineAfterFailedCycles=1000), items=1)
    running(drv)
    # (a forward's timeout counts from its arrival: not behind the dead slave's first
    # poll, its timeout and the settle)
    wait_for(lambda: dead.stats().get("timeouts", 0) >= 1, 15, "the dead slave's first poll")
    forward(drv, struct.pack(">BHH", 3, 0, 2), 3.0)
    assert forward(drv, struct.pack(">BHH", 3, 99, 2), 3.0) == b"\x83\x02"
    with pytest.raises(ModbusTimeoutError):
        forward(dead, struct.pack(">BHH", 3, 0, 1), 0.2)
    line = f"rtu-over-tcp://127.0.0.1:{peer.port}"
    exporter = MetricsExporter({"port": 0})
    try:
        exporter.attach(drv, "dev1", line)
        port = exporter.start()
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
            text = resp.read().decode()
    finally:
        exporter.stop()
    want = {"forwarded_requests": 3, "forward_timeouts": 1, "forward_exceptions": 1,
            "forward_errors": 0}
    for name, value in want.items():
        assert f'edgemodbus_line_{name}_total{{line="{line}"}} {float(value)}' in text, name


def test_a_forward_cancelled_while_queued_is_not_sent(started: Started,
                                                      slave_factory: SlaveFactory) -> None:
    peer = slave_factory("rtu-over-tcp", units=(1,), size=100)
    drv = started(comm(peer, 1, readCycle=3_600_000, settleTimeout=500))
    dead = started(comm(peer, 5, readCycle=3_600_000), items=1)
    running(drv)
    busy = dead.forward(struct.pack(">BHH", 3, 0, 1), 0.5)  # holds the line ~1 s
    queued = drv.forward(struct.pack(">BHH", 6, 9, 4321))
    assert queued.cancel()
    with pytest.raises(ModbusTimeoutError):
        busy.result(15)
    assert forward(drv, struct.pack(">BHH", 3, 9, 1)) == b"\x03\x02" + regs(
        peer.registers(1, "hr", 9, 1))
    assert peer.registers(1, "hr", 9, 1) != [4321]
    assert drv.stats()["line"]["forwarded"] == 2


@pytest.mark.usefixtures("engine")
def test_forward_to_a_slave_behind_a_dtu_that_dialled_in_with_heartbeats(
        started: Started) -> None:
    """Listen mode: the DTU's stream (heartbeats before the replies) frames the reply."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = int(probe.getsockname()[1])
    drv = started(with_engine({
        "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
        "dtuId": "DTU9", "registration": "text", "heartbeat": "HB", "slaveId": 1,
        "readTimeout": 1000, "readCycle": 50, "byteTimeout": 100, "reconnectInterval": 300}))
    with Simulator(slaves=[1]) as simulator:
        simulator.dial("127.0.0.1", port, registration=b"DTU9", heartbeat=b"HB",
                       heartbeat_interval=0.03, heartbeat_before_reply=True)
        running(drv)
        want = simulator.slave(1).get_registers(Area.HOLDING_REGISTER, 0, 5)
        assert forward(drv, struct.pack(">BHH", 3, 0, 5)) == b"\x03\x0a" + regs(want)
        pdu = struct.pack(">BHHB2H", 16, 20, 2, 4, 0xCAFE, 0x0102)
        assert forward(drv, pdu) == pdu[:5]
        assert simulator.slave(1).get_registers(Area.HOLDING_REGISTER, 20, 2) == [0xCAFE,
                                                                               0x0102]
        assert forward(drv, struct.pack(">BHH", 4, 60000, 1))[0] == 0x84  # an exception
        line = drv.stats()["line"]
        assert line["forwarded"] == 3 and line["forwardExceptions"] == 1
        assert line["heartbeats"] >= 1
