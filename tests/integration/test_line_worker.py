"""The line worker (libmodbus through our binding) against pymodbus in its own process:
RTU framing over TCP, Modbus TCP, and RTU over a socat pty pair."""

from __future__ import annotations

import time
from collections.abc import Iterator
from concurrent.futures import Future

import pytest

from edgemodbus.datatypes import Area
from edgemodbus.errors import (
    IllegalDataAddress,
    ModbusConnectionError,
    ModbusExceptionResponse,
    ModbusTimeoutError,
    SlaveDeviceBusy,
)
from edgemodbus.line.endpoint import LineTiming, SerialPort, TcpEndpoint
from edgemodbus.line.registry import LineRegistry
from edgemodbus.line.worker import LineWorker
from tests.peers import ExceptionRange, PtyPair, PymodbusSlave, default_bit, default_register

FAST = LineTiming(response_timeout=0.5, byte_timeout=0.05, reconnect_interval=0.3,
                  connect_timeout=1.0)


def _worker_for(slave: PymodbusSlave, pty: PtyPair | None, timing: LineTiming = FAST) -> LineWorker:
    if slave.transport == "serial":
        assert pty is not None
        endpoint: SerialPort | TcpEndpoint = SerialPort(pty.a, baudrate=115200)
    else:
        endpoint = TcpEndpoint("127.0.0.1", slave.port, slave.transport)
    worker = LineWorker(endpoint, timing)
    worker.start()
    return worker


@pytest.fixture(params=["rtu-over-tcp", "tcp", "serial"])
def line(request: pytest.FixtureRequest, tmp_path) -> Iterator[tuple[LineWorker, PymodbusSlave]]:
    """A worker and the pymodbus slave (units 1 and 2) at its other end."""
    transport = request.param
    if transport == "serial":
        with PtyPair(tmp_path) as pty, PymodbusSlave(
            "serial", units=(1, 2), device=pty.b, baudrate=115200, size=2000
        ) as slave:
            worker = _worker_for(slave, pty)
            try:
                yield worker, slave
            finally:
                worker.stop()
    else:
        with PymodbusSlave(transport, units=(1, 2), size=2000) as slave:
            worker = _worker_for(slave, None)
            try:
                yield worker, slave
            finally:
                worker.stop()


def test_reads_every_area(line: tuple[LineWorker, PymodbusSlave]) -> None:
    worker, _ = line
    for unit in (1, 2):
        assert worker.read(unit, Area.HOLDING_REGISTER, 0, 125).result(5) == [
            default_register(unit, "hr", a) for a in range(125)
        ]
        assert worker.read(unit, Area.INPUT_REGISTER, 1000, 7).result(5) == [
            default_register(unit, "ir", a) for a in range(1000, 1007)
        ]
        assert worker.read(unit, Area.COIL, 3, 200).result(5) == [
            int(default_bit(unit, "co", a)) for a in range(3, 203)
        ]
        assert worker.read(unit, Area.DISCRETE_INPUT, 0, 17).result(5) == [
            int(default_bit(unit, "di", a)) for a in range(17)
        ]


def test_every_write_function(line: tuple[LineWorker, PymodbusSlave]) -> None:
    worker, slave = line
    worker.write_register(1, 10, 0xBEEF).result(5)                      # FC06
    worker.write_registers(1, 20, [1, 2, 3, 65535]).result(5)           # FC16
    worker.write_coil(1, 5, True).result(5)                             # FC05
    worker.write_coil(1, 6, False).result(5)
    worker.write_coils(1, 100, [True, False, True, True, False, True, False, True, True]).result(5)
    worker.write_register(1, 30, 0x1234).result(5)
    worker.mask_write_register(1, 30, 0x00F0, 0x0F05).result(5)         # FC22
    assert slave.registers(1, "hr", 10, 1) == [0xBEEF]
    assert slave.registers(1, "hr", 20, 4) == [1, 2, 3, 65535]
    assert slave.bits(1, "co", 5, 2) == [True, False]
    assert slave.bits(1, "co", 100, 9) == [True, False, True, True, False, True, False, True, True]
    # (current AND and_mask) OR (or_mask AND NOT and_mask): Application Protocol 6.16
    assert slave.registers(1, "hr", 30, 1) == [(0x1234 & 0x00F0) | (0x0F05 & ~0x00F0 & 0xFFFF)]
    assert worker.read(1, Area.HOLDING_REGISTER, 20, 4).result(5) == [1, 2, 3, 65535]
    # unit 2 untouched
    assert slave.registers(2, "hr", 10, 1) == [default_register(2, "hr", 10)]


def test_illegal_address_and_recovery(line: tuple[LineWorker, PymodbusSlave]) -> None:
    worker, _ = line
    with pytest.raises(IllegalDataAddress) as info:
        worker.read(1, Area.HOLDING_REGISTER, 1990, 20).result(5)
    assert info.value.code == 2
    with pytest.raises(IllegalDataAddress):
        worker.write_register(1, 5000, 1).result(5)
    assert worker.read(1, Area.HOLDING_REGISTER, 1980, 20).result(5) == [
        default_register(1, "hr", a) for a in range(1980, 2000)
    ]
    assert worker.stats.exceptions[2] == 2


def test_unknown_slave_times_out_without_reopening(line: tuple[LineWorker, PymodbusSlave]) -> None:
    worker, _ = line
    started = time.monotonic()
    with pytest.raises(ModbusTimeoutError):
        worker.read(7, Area.HOLDING_REGISTER, 0, 4).result(5)
    elapsed = time.monotonic() - started
    # one response timeout, then the settle time (one more timeout): never a reconnect
    assert 0.45 <= elapsed < 2.0
    assert worker.read(2, Area.HOLDING_REGISTER, 4, 4).result(5) == [
        default_register(2, "hr", a) for a in range(4, 8)
    ]
    assert worker.stats.timeouts == 1
    assert worker.stats.reconnects == 0 and worker.stats.link_errors == 0


@pytest.mark.parametrize("transport", ["rtu-over-tcp", "tcp"])
def test_exception_codes_are_typed(transport: str) -> None:
    codes = [1, 2, 3, 4, 5, 6, 7, 8, 10, 11]
    ranges = [ExceptionRange(100 + 10 * i, 105 + 10 * i, code) for i, code in enumerate(codes)]
    with PymodbusSlave(transport, units=(1,), exception_ranges=ranges) as slave:
        worker = _worker_for(slave, None)
        try:
            for i, code in enumerate(codes):
                with pytest.raises(ModbusExceptionResponse) as info:
                    worker.read(1, Area.HOLDING_REGISTER, 100 + 10 * i, 2).result(5)
                assert info.value.code == code
                assert f"{code:#04x}" in str(info.value)
            with pytest.raises(SlaveDeviceBusy):
                worker.read(1, Area.HOLDING_REGISTER, 150, 1).result(5)
            assert worker.read(1, Area.HOLDING_REGISTER, 0, 2).result(5) == [1000, 1001]
        finally:
            worker.stop()


@pytest.mark.parametrize("transport", ["rtu-over-tcp", "serial"])
def test_late_reply_is_never_taken_for_the_next_answer(transport: str, tmp_path) -> None:
    """RTU has no transaction id: a reply that comes after the timeout must be settled
    away, not returned as the answer to the next read of the same length."""
    timing = LineTiming(response_timeout=0.2, byte_timeout=0.05, reconnect_interval=0.3)
    pty = PtyPair(tmp_path).start() if transport == "serial" else None
    try:
        kwargs = {"device": pty.b, "baudrate": 115200} if pty else {}
        with PymodbusSlave(transport, units=(1,), **kwargs) as slave:  # type: ignore[arg-type]
            worker = _worker_for(slave, pty, timing)
            try:
                slave.set_response_delay(0.3)  # later than the timeout, within the settle
                with pytest.raises(ModbusTimeoutError):
                    worker.read(1, Area.HOLDING_REGISTER, 0, 5).result(5)
                slave.set_response_delay(0.0)
                for start in (100, 200, 300):
                    assert worker.read(1, Area.HOLDING_REGISTER, start, 5).result(5) == [
                        default_register(1, "hr", a) for a in range(start, start + 5)
                    ]
                assert worker.stats.discarded_bytes > 0  # the late reply was seen and dropped
            finally:
                worker.stop()
    finally:
        if pty is not None:
            pty.close()


def test_server_killed_and_restarted_reconnects() -> None:
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        worker = _worker_for(slave, None)
        try:
            assert worker.read(1, Area.HOLDING_REGISTER, 0, 2).result(5) == [1000, 1001]
            slave.kill()
            with pytest.raises(ModbusConnectionError):
                worker.read(1, Area.HOLDING_REGISTER, 0, 2).result(5)
            assert not worker.link_up
            # while the link is down, requests fail at once instead of queueing up
            started = time.monotonic()
            with pytest.raises(ModbusConnectionError):
                worker.read(1, Area.HOLDING_REGISTER, 0, 2).result(5)
            assert time.monotonic() - started < 0.2
            slave.restart()
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline:
                try:
                    values = worker.read(1, Area.HOLDING_REGISTER, 2, 2).result(5)
                    break
                except ModbusConnectionError:
                    time.sleep(0.1)  # poll: until it reconnects (deadline above)
            else:
                pytest.fail("the worker did not reconnect")
            assert values == [1002, 1003]
            assert worker.stats.reconnects >= 1
        finally:
            worker.stop()


def test_stop_fails_pending_requests() -> None:
    with PymodbusSlave("rtu-over-tcp", units=(1,), response_delay=0.1) as slave:
        worker = _worker_for(slave, None)
        futures: list[Future[list[int]]] = [
            worker.read(1, Area.HOLDING_REGISTER, i, 1) for i in range(20)
        ]
        time.sleep(0.05)  # pacing: the first request under way
        worker.stop()
        done = [f for f in futures if f.exception(5) is None]
        failed = [f for f in futures if f.exception(5) is not None]
        assert failed, "every request finished although the worker was stopped"
        assert len(done) < 3
        for f in failed:
            exc = f.exception()
            assert isinstance(exc, ModbusConnectionError) and "stopped" in str(exc)
        with pytest.raises(ModbusConnectionError):
            worker.read(1, Area.HOLDING_REGISTER, 0, 1).result(1)


def test_connect_refused_reports_and_retries() -> None:
    from tests.peers import free_port

    worker = LineWorker(TcpEndpoint("127.0.0.1", free_port()), FAST)
    worker.start()
    try:
        with pytest.raises(ModbusConnectionError, match="connect failed"):
            worker.read(1, Area.HOLDING_REGISTER, 0, 1).result(5)
        assert worker.last_link_error is not None and "refused" in worker.last_link_error.lower()
    finally:
        worker.stop()


def test_broadcast_write_expects_no_reply() -> None:
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        worker = _worker_for(slave, None)
        try:
            started = time.monotonic()
            worker.write_register(0, 3, 42).result(5)
            assert time.monotonic() - started < FAST.response_timeout
            # the next request waits the turnaround delay and still gets its own answer
            assert worker.read(1, Area.HOLDING_REGISTER, 7, 1).result(5) == [1007]
        finally:
            worker.stop()


def test_registry_shares_a_line_and_rejects_conflicting_serial_settings(tmp_path) -> None:
    registry = LineRegistry()
    with PymodbusSlave("rtu-over-tcp", units=(1, 2)) as slave:
        ep = TcpEndpoint("127.0.0.1", slave.port)
        a = registry.acquire(ep, FAST)
        b = registry.acquire(TcpEndpoint("127.0.0.1", slave.port), FAST)
        assert a is b
        assert b.read(2, Area.HOLDING_REGISTER, 0, 1).result(5) == [2000]
        registry.release(a)
        assert a.running  # still used by the second user
        registry.release(b)
        assert not a.running
    port = str(tmp_path / "ttyFAKE")
    s1 = registry.acquire(SerialPort(port, 9600), FAST)
    try:
        with pytest.raises(ValueError) as info:
            registry.acquire(SerialPort(port, 19200, parity="E"), FAST)
        assert "9600 8N1" in str(info.value) and "19200 8E1" in str(info.value)
    finally:
        registry.release(s1)


def test_missing_serial_port_says_what_to_do(tmp_path) -> None:
    worker = LineWorker(SerialPort(str(tmp_path / "ttyUSB9")), FAST)
    worker.start()
    try:
        with pytest.raises(ModbusConnectionError, match="does not exist"):
            worker.read(1, Area.HOLDING_REGISTER, 0, 1).result(5)
    finally:
        worker.stop()


def test_frame_trace_at_debug(caplog: pytest.LogCaptureFixture) -> None:
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        caplog.set_level("DEBUG", logger="edgemodbus.line")
        worker = _worker_for(slave, None)
        try:
            worker.read(1, Area.HOLDING_REGISTER, 0, 10).result(5)
            worker.write_register(1, 1, 3).result(5)
        finally:
            worker.stop()
    lines = [r.getMessage() for r in caplog.records]
    # read 10 holding registers from slave 1 at 0: slave, FC, address, count, CRC low/high
    assert any(line.endswith("TX 01 03 00 00 00 0A C5 CD") for line in lines), lines
    rx = [line for line in lines if " RX 01 03 14 03 E8 03 E9" in line]
    assert rx, lines
    assert any(line.endswith("TX 01 06 00 01 00 03 98 0B") for line in lines), lines
    assert any(line.endswith("RX 01 06 00 01 00 03 98 0B") for line in lines), lines
