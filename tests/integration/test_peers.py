"""Tests of the test peers themselves (tests/peers.py, tests/pymodbus_slave.py).

The master here is pymodbus' own sync client, never edgemodbus: these tests show that the
peers behave as documented, so a failing edgemodbus test points at edgemodbus.
"""

from __future__ import annotations

import os
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusIOException

from tests.conftest import SlaveFactory, _leaks, _snapshot
from tests.peers import (
    ExceptionRange,
    PeerError,
    PtyPair,
    PymodbusSlave,
    default_bit,
    default_register,
    free_port,
    normalize_area,
)

Client = ModbusTcpClient | ModbusSerialClient


@contextmanager
def client_for(slave: PymodbusSlave, timeout: float = 1.0) -> Iterator[Client]:
    """A connected pymodbus sync client for the slave's transport; closed afterwards."""
    client: Client
    if slave.transport == "serial":
        assert slave.master_path is not None
        client = ModbusSerialClient(
            slave.master_path, framer=FramerType.RTU, timeout=timeout, retries=0
        )
    else:
        framer = FramerType.RTU if slave.transport == "rtu-over-tcp" else FramerType.SOCKET
        client = ModbusTcpClient(
            slave.host, port=slave.port, framer=framer, timeout=timeout, retries=0
        )
    try:
        assert client.connect(), f"cannot connect to {slave!r}"
        yield client
    finally:
        client.close()


def read_hr(client: Client, address: int, count: int = 1, unit: int = 1) -> list[int]:
    """Holding registers or an AssertionError naming the exception response."""
    response = client.read_holding_registers(address, count=count, device_id=unit)
    assert not response.isError(), f"exception response {response}"
    return list(response.registers)


# --------------------------------------------------------------------------- pure helpers
def test_default_formulas_differ_by_unit_area_and_address() -> None:
    """The defaults must expose a read of the wrong unit, area or offset."""
    assert default_register(1, "hr", 0) == 1000
    assert default_register(2, "holding", 7) == 2007
    assert default_register(1, "ir", 0) == 0x8000 + 1000
    assert default_register(70, "hr", 65535) == (70_000 + 65535) & 0xFFFF
    assert default_register(1, "hr", 5) != default_register(1, "ir", 5)
    assert default_register(1, "hr", 5) != default_register(2, "hr", 5)
    coils = [default_bit(1, "co", a) for a in range(12)]
    inputs = [default_bit(1, "di", a) for a in range(12)]
    assert coils != inputs and any(coils) and not all(coils) and any(inputs)
    assert coils != [default_bit(2, "co", a) for a in range(12)]
    with pytest.raises(ValueError):
        default_register(1, "co", 0)
    with pytest.raises(ValueError):
        default_bit(1, "hr", 0)
    assert [normalize_area(a) for a in ("Coil", "2", "HOLDING", "input")] == [
        "co", "di", "hr", "ir",
    ]  # fmt: skip
    with pytest.raises(ValueError):
        normalize_area("eeprom")
    with pytest.raises(ValueError):
        ExceptionRange(10, 5)
    with pytest.raises(ValueError):
        ExceptionRange(0, 5, code=9)


def test_leak_detector_sees_fds_threads_and_children() -> None:
    """What the autouse no_leaks fixture relies on."""
    before = _snapshot()
    sock = socket.socket()
    stop = threading.Event()
    thread = threading.Thread(target=stop.wait, name="leaky-thread")
    thread.start()
    proc = subprocess.Popen(["sleep", "5"])
    try:
        problems = "\n".join(_leaks(before, _snapshot()))
        assert "leaky-thread" in problems
        assert f"fd {sock.fileno()} -> socket:[" in problems
        assert f"child process {proc.pid} (sleep)" in problems
    finally:
        sock.close()
        stop.set()
        thread.join()
        proc.kill()
        proc.wait()
    assert _leaks(before, _snapshot()) == []


def test_free_port_is_bindable() -> None:
    port = free_port()
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", port))
    assert 1024 <= port <= 65535


# --------------------------------------------------------------------------- defaults served
@pytest.mark.parametrize("transport", ["rtu-over-tcp", "tcp", "serial"])
def test_default_values_at_zero_and_elsewhere(
    transport: str, slave_factory: SlaveFactory, request: pytest.FixtureRequest
) -> None:
    """All four areas answer the formula values at address 0, in the middle and at the end."""
    kwargs: dict[str, object] = {"units": (1, 2)}
    if transport == "serial":
        pty: PtyPair = request.getfixturevalue("pty_pair")
        kwargs.update(device=pty.b, master_path=pty.a)
    slave = slave_factory(transport, **kwargs)
    with client_for(slave) as client:
        for unit in (1, 2):
            for address, count in ((0, 10), (1234, 3), (9990, 10)):
                hr = client.read_holding_registers(address, count=count, device_id=unit)
                ir = client.read_input_registers(address, count=count, device_id=unit)
                co = client.read_coils(address, count=count, device_id=unit)
                di = client.read_discrete_inputs(address, count=count, device_id=unit)
                span = range(address, address + count)
                assert hr.registers == [default_register(unit, "hr", a) for a in span]
                assert ir.registers == [default_register(unit, "ir", a) for a in span]
                assert co.bits[:count] == [default_bit(unit, "co", a) for a in span]
                assert di.bits[:count] == [default_bit(unit, "di", a) for a in span]


def test_beyond_size_is_illegal_address(slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp", size={"hr": 100, "co": 20})
    with client_for(slave) as client:
        assert read_hr(client, 99) == [default_register(1, "hr", 99)]
        over = client.read_holding_registers(95, count=10, device_id=1)
        assert over.isError() and over.exception_code == 2
        assert client.read_coils(19, count=1, device_id=1).bits[0] == default_bit(1, "co", 19)
        bits_over = client.read_coils(16, count=5, device_id=1)
        assert bits_over.isError() and bits_over.exception_code == 2
        # the other areas keep the default size
        assert not client.read_input_registers(9999, count=1, device_id=1).isError()


def test_fill_zero_and_initial_overrides(slave_factory: SlaveFactory) -> None:
    slave = slave_factory(
        "tcp",
        units=(5,),
        fill="zero",
        initial={5: {"hr": {10: 0x4142, 11: 0x4344}, "di": {3: True}}},
    )
    with client_for(slave) as client:
        assert read_hr(client, 9, 4, unit=5) == [0, 0x4142, 0x4344, 0]
        assert client.read_discrete_inputs(0, count=5, device_id=5).bits[:5] == [
            False, False, False, True, False,
        ]  # fmt: skip


# --------------------------------------------------------------------------- units
def test_unknown_unit_is_silent(rtu_tcp_slave: PymodbusSlave) -> None:
    """ignore_missing_devices (default): no answer at all, like an RS-485 line."""
    with client_for(rtu_tcp_slave, timeout=0.3) as client:
        started = time.monotonic()
        with pytest.raises(ModbusIOException):
            client.read_holding_registers(0, count=1, device_id=9)
        assert time.monotonic() - started >= 0.25
        assert read_hr(client, 0, unit=3) == [3000]  # the line still works
    counts = rtu_tcp_slave.stats()["requests"]
    assert counts[9] == 1 and counts[3] == 1


def test_unknown_unit_answers_exception_without_ignore(slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp", ignore_missing_devices=False)
    with client_for(slave, timeout=1.0) as client:
        response = client.read_holding_registers(0, count=1, device_id=9)
        assert response.isError() and response.exception_code == 4


def test_set_offline_and_back(rtu_tcp_slave: PymodbusSlave) -> None:
    with client_for(rtu_tcp_slave, timeout=0.3) as client:
        rtu_tcp_slave.set_offline(2)
        with pytest.raises(ModbusIOException):
            client.read_holding_registers(0, count=1, device_id=2)
        assert read_hr(client, 0, unit=1) == [1000]
        rtu_tcp_slave.set_offline(2, False)
        assert read_hr(client, 0, unit=2) == [2000]


# --------------------------------------------------------------------------- writes
def test_writes_round_trip(tcp_slave: PymodbusSlave) -> None:
    with client_for(tcp_slave) as client:
        assert not client.write_register(7, 0xBEEF, device_id=2).isError()
        assert not client.write_registers(100, [1, 2, 3], device_id=2).isError()
        assert not client.write_coil(5, True, device_id=2).isError()
        assert not client.write_coils(20, [True, False, True], device_id=2).isError()
        assert read_hr(client, 7, unit=2) == [0xBEEF]
        assert read_hr(client, 99, 5, unit=2) == [2099, 1, 2, 3, 2103]
        assert client.read_coils(20, count=3, device_id=2).bits[:3] == [True, False, True]
        assert read_hr(client, 7, unit=1) == [1007]  # other units untouched
    # ...and the slave's datastore says the same, seen from outside
    assert tcp_slave.registers(2, "hr", 99, 5) == [2099, 1, 2, 3, 2103]
    assert tcp_slave.bits(2, "co", 5, 1) == [True]


def test_set_from_outside_is_served(rtu_tcp_slave: PymodbusSlave) -> None:
    rtu_tcp_slave.set_registers(1, "ir", 0, [11, 22])
    rtu_tcp_slave.set_bits(1, "di", 0, [True, True, False])
    with client_for(rtu_tcp_slave) as client:
        assert client.read_input_registers(0, count=3, device_id=1).registers == [
            11, 22, default_register(1, "ir", 2),
        ]  # fmt: skip
        assert client.read_discrete_inputs(0, count=3, device_id=1).bits[:3] == [
            True, True, False,
        ]  # fmt: skip
    with pytest.raises(PeerError):
        rtu_tcp_slave.registers(1, "hr", 9999, 2)  # outside the datastore
    with pytest.raises(PeerError):
        rtu_tcp_slave.registers(42, "hr", 0, 1)  # unit not served
    with pytest.raises(ValueError):
        rtu_tcp_slave.registers(1, "co", 0, 1)  # a bit area


# --------------------------------------------------------------------------- faults
def test_exception_ranges(rtu_tcp_slave: PymodbusSlave) -> None:
    rtu_tcp_slave.set_exception_ranges(
        [ExceptionRange(100, 110, code=3, area="hr"), ExceptionRange(0, 10, code=6, unit=2)]
    )
    with client_for(rtu_tcp_slave) as client:
        hit = client.read_holding_registers(95, count=6, device_id=1)
        assert hit.isError() and hit.exception_code == 3
        assert read_hr(client, 90, 10) == [1000 + a for a in range(90, 100)]
        assert not client.read_input_registers(100, count=5, device_id=1).isError()
        busy = client.read_coils(0, count=1, device_id=2)
        assert busy.isError() and busy.exception_code == 6
        rtu_tcp_slave.set_exception_ranges([])
        assert read_hr(client, 100) == [1100]


@pytest.mark.parametrize("rtu_tcp_slave", [{"response_delay": 0.5}], indirect=True)
def test_response_delay(rtu_tcp_slave: PymodbusSlave) -> None:
    """The slave answers late: a short client timeout misses it, a long one gets it."""
    with client_for(rtu_tcp_slave, timeout=1.5) as client:
        started = time.monotonic()
        assert read_hr(client, 3) == [1003]
        assert time.monotonic() - started >= 0.48
    with client_for(rtu_tcp_slave, timeout=0.15) as client, pytest.raises(ModbusIOException):
        client.read_holding_registers(3, count=1, device_id=1)
    rtu_tcp_slave.set_response_delay(0)
    with client_for(rtu_tcp_slave, timeout=1.0) as client:
        started = time.monotonic()
        assert read_hr(client, 4) == [1004]
        assert time.monotonic() - started < 0.4


def test_drop_connections(rtu_tcp_slave: PymodbusSlave) -> None:
    with client_for(rtu_tcp_slave, timeout=0.5) as client:
        assert read_hr(client, 0) == [1000]
        assert rtu_tcp_slave.stats()["active"] == 1
        assert rtu_tcp_slave.drop_connections() == 1
        with pytest.raises((ConnectionException, ModbusIOException, OSError)):
            read_hr(client, 0)
    stats = rtu_tcp_slave.stats()
    assert stats["connections"] == 1 and stats["active"] == 0


# --------------------------------------------------------------------------- lifecycle
def test_kill_and_restart_on_same_port(rtu_tcp_slave: PymodbusSlave) -> None:
    port = rtu_tcp_slave.port
    pid = rtu_tcp_slave.pid
    rtu_tcp_slave.set_registers(1, "hr", 0, [7])
    with client_for(rtu_tcp_slave, timeout=0.5) as client:
        assert read_hr(client, 0) == [7]
        rtu_tcp_slave.kill()
        assert not rtu_tcp_slave.running
        assert pid is not None and not os.path.exists(f"/proc/{pid}")
        with pytest.raises((ConnectionException, ModbusIOException, OSError)):
            read_hr(client, 0)
    with pytest.raises(ConnectionRefusedError), socket.create_connection(("127.0.0.1", port)):
        pass
    rtu_tcp_slave.restart()
    assert rtu_tcp_slave.port == port and rtu_tcp_slave.pid != pid
    with client_for(rtu_tcp_slave) as client:
        assert read_hr(client, 0) == [1000]  # the datastore starts afresh


def test_stop_with_connected_client_then_restart(tcp_slave: PymodbusSlave) -> None:
    """A graceful stop closes connections first (TIME_WAIT on the slave's side)."""
    port = tcp_slave.port
    with client_for(tcp_slave) as client:
        assert read_hr(client, 1) == [1001]
        tcp_slave.stop()
    tcp_slave.restart()
    assert tcp_slave.port == port
    with client_for(tcp_slave) as client:
        assert read_hr(client, 1) == [1001]
        assert tcp_slave.request_count(1) == 1


def test_start_failure_reports_stderr() -> None:
    slave = PymodbusSlave("tcp", units=(1,), initial={7: {"hr": {0: 1}}})
    with pytest.raises(PeerError, match="unit 7"):
        slave.start()
    assert not slave.running
    assert "bad configuration" in slave.stderr_text


def test_busy_port_fails_cleanly() -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        slave = PymodbusSlave("rtu-over-tcp", port=holder.getsockname()[1], bind_patience=0.3)
        with pytest.raises(PeerError, match="could not listen"):
            slave.start()
    assert not slave.running


# --------------------------------------------------------------------------- serial / pty
def test_serial_slave_fixture(serial_slave: PymodbusSlave, pty_pair: PtyPair) -> None:
    assert serial_slave.master_path == pty_pair.a
    with client_for(serial_slave) as client:
        assert read_hr(client, 0, 2, unit=3) == [3000, 3001]
        assert not client.write_register(1, 42, device_id=3).isError()
    assert serial_slave.registers(3, "hr", 1, 1) == [42]


def test_pty_pair_links_and_close(tmp_path: Path) -> None:
    pair = PtyPair(tmp_path, "left", "right").start()
    try:
        pid = pair.pid
        assert pid is not None and os.path.exists(f"/proc/{pid}")
        assert os.path.realpath(pair.a).startswith("/dev/pts/")
        fd_a = os.open(pair.a, os.O_RDWR | os.O_NOCTTY)
        fd_b = os.open(pair.b, os.O_RDWR | os.O_NOCTTY)
        try:
            os.write(fd_a, b"\x01\x03ping")
            deadline = time.monotonic() + 2
            got = b""
            while len(got) < 6 and time.monotonic() < deadline:
                got += os.read(fd_b, 64)
            assert got == b"\x01\x03ping"
        finally:
            os.close(fd_a)
            os.close(fd_b)
    finally:
        pair.close()
    assert not pair.running
    assert not os.path.exists(f"/proc/{pid}")
    assert not os.path.lexists(pair.a) and not os.path.lexists(pair.b)


def test_pty_unplug_and_replug_with_serial_slave(
    pty_pair: PtyPair, slave_factory: SlaveFactory
) -> None:
    """The adapter disappears (socat killed) and comes back: the slave reopens its end."""
    slave = slave_factory("serial", device=pty_pair.b, master_path=pty_pair.a)
    with client_for(slave, timeout=0.5) as client:
        assert read_hr(client, 5) == [1005]
    old_pid = pty_pair.pid
    pty_pair.unplug()
    assert not os.path.lexists(pty_pair.a)
    assert old_pid is not None and not os.path.exists(f"/proc/{old_pid}")
    pty_pair.replug()
    assert pty_pair.running and pty_pair.pid != old_pid
    deadline = time.monotonic() + 5
    while True:  # the slave polls for its device every 0.1 s
        with client_for(slave, timeout=0.3) as client:
            try:
                assert read_hr(client, 6) == [1006]
                break
            except ModbusIOException:
                if time.monotonic() > deadline:
                    raise
    assert slave.running
