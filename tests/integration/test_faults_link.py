"""The fault matrix (issue 6), link-level scenarios: TCP resets and closes, refused and
hanging connects, fd exhaustion, a serial adapter that disappears, slow and raising
callbacks, writes during outages, and Modbus TCP header checks.  Everything goes
through DriverModbusRtu; helpers come from test_faults.py."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import resource
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import DeviceDriverStatus, ItemStatus
from edgemodbus.sim import Simulator, default_register
from tests.integration.test_faults import HR, OK, RUNNING, Polled, Rig, hr_items, wait_for

RECONNECTING = DeviceDriverStatus.RECONNECTING


@pytest.fixture
def rig() -> Iterator[Rig]:
    with Rig() as r:
        yield r


def start_driver(comm: dict[str, Any], items: list[dict[str, Any]], slave: int = 1) -> Polled:
    base: dict[str, Any] = {"slaveId": slave, "readTimeout": 200, "readCycle": 50,
                            "byteTimeout": 30, "retries": 0}
    base.update(comm)
    cfg = em.load_device_config({"organization": {"deviceCode": f"dev{slave}"},
                                 "communication": base, "addressList": items})
    p = Polled(em.DriverModbusRtu(), cfg, slave)
    p.drv.address_updated_callback = p.record
    assert p.drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    return p


def tcp_comm(port: int, **extra: Any) -> dict[str, Any]:
    comm: dict[str, Any] = {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                            "tcpPort": port, "connectTimeout": 500, "reconnectInterval": 100,
                            "maxBackoff": 400}
    comm.update(extra)
    return comm


def cpu_while(seconds: float) -> float:
    """CPU seconds this process used (all threads) while sleeping ``seconds``."""
    cpu = time.process_time()
    time.sleep(seconds)  # pacing: the window measured
    return time.process_time() - cpu


def connect_failure_times(caplog: pytest.LogCaptureFixture) -> list[float]:
    return [r.created for r in caplog.records
            if r.name == "edgemodbus.line" and "connect failed" in r.getMessage()]


# --------------------------------------------------------------------------- 18
@pytest.mark.parametrize("reset", [True, False], ids=["rst", "fin"])
def test_18_tcp_reset_or_close_mid_frame(reset: bool) -> None:
    with Rig((1,)) as broken, Rig((1,)) as other:
        p = broken.start(hr_items(0, 10), reconnectInterval=300)
        q = other.start(hr_items(0, 10))
        cycles, q_mark = q.cycles(), len(q.snapshot())
        mark = len(p.snapshot())
        broken.sim.slave(1).set_faults(cut_every=1, cut_with_reset=reset)
        broken.wait_faults("cut_every", 1)
        broken.sim.slave(1).faults.cut_every = 0
        wait_for(lambda: p.drv.device_driver_status is RECONNECTING, 20, "Reconnecting")
        down = [r for r in p.snapshot()[mark:] if r.status is ItemStatus.INVALID]
        assert down and all("link down" in (r.reason or "") for r in down)
        assert "link error" in (down[0].reason or "")
        # the link comes back after the reconnect interval (jittered, never early)
        wait_for(lambda: p.drv.device_driver_status is RUNNING, 20, "Running again")
        wait_for(p.all_ok, what="polling resumed")
        up = next(r for r in p.snapshot()[mark:] if r.status is OK)
        assert down[0].ts is not None and up.ts is not None
        assert (up.ts - down[0].ts).total_seconds() >= 0.8 * 0.3
        stats = p.stats()
        assert stats["line"]["reconnects"] == 1 and stats["line"]["linkErrors"] == 1
        assert not p.wrong_values()  # the half frame never reached an item
        # the other line did not notice
        assert q.cycles() > cycles + 3
        assert not q.invalid_reports(q_mark)
        assert q.stats()["line"]["reconnects"] == 0


# --------------------------------------------------------------------------- 19
def test_19_connect_refused_backs_off_with_jitter_at_no_cpu(
    free_tcp_port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="edgemodbus.line")
    p = start_driver(tcp_comm(free_tcp_port), hr_items(0, 4))
    try:
        wait_for(lambda: p.drv.device_driver_status is RECONNECTING, 20, "Reconnecting")
        item = p.item("hr0")
        assert item.status is ItemStatus.INVALID and "refused" in (item.error_reason or "")
        cpu = cpu_while(2.0)
        failures = p.stats()["line"]["connectFailures"]
    finally:
        p.drv.stop_device()
    assert cpu < 0.25, cpu  # no busy loop while waiting to reconnect
    # reconnectInterval 0.1 s doubling to maxBackoff 0.4 s: about 7 tries in 2.1 s, not 21
    assert 4 <= failures <= 12, failures
    gaps = [b - a for a, b in itertools.pairwise(connect_failure_times(caplog))]
    assert len(gaps) >= 4, gaps
    assert gaps[0] < 0.2 and max(gaps) > 1.5 * gaps[0], gaps  # it backs off ...
    capped = gaps[3:]
    assert all(0.28 <= g <= 0.6 for g in capped), gaps  # ... to 0.4 s +- 20 %
    assert len({round(g, 3) for g in gaps}) > 1  # jittered, not in step


@pytest.fixture
def hanging_port() -> Iterator[int]:
    """A listener whose accept queue is full (listen(0), one connection never accepted):
    Linux drops further SYNs, so a connect never completes."""
    listener = socket.socket()
    fillers: list[socket.socket] = []
    try:
        listener.bind(("127.0.0.1", 0))
        listener.listen(0)
        port = listener.getsockname()[1]
        for _ in range(8):
            filler = socket.socket()
            filler.settimeout(0.2)
            try:
                filler.connect(("127.0.0.1", port))
            except OSError:
                filler.close()
                break
            fillers.append(filler)
        else:  # pragma: no cover - depends on the kernel
            pytest.fail("the accept queue never filled")
        yield port
    finally:
        for filler in fillers:
            filler.close()
        listener.close()


def test_19_connect_that_never_completes_is_bounded(
    hanging_port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="edgemodbus.line")
    started = time.monotonic()
    p = start_driver(tcp_comm(hanging_port, connectTimeout=400, maxBackoff=200), hr_items(0, 4))
    try:
        wait_for(lambda: p.drv.device_driver_status is RECONNECTING, 20, "Reconnecting")
        first = time.monotonic() - started
        item = p.item("hr0")
        assert "connect timed out after 0.4 s" in (item.error_reason or ""), item.error_reason
        assert p.drv.device_driver_status is RECONNECTING
        cpu = cpu_while(1.5)
        failures = p.stats()["line"]["connectFailures"]
    finally:
        p.drv.stop_device()
    assert 0.35 <= first <= 1.5, first  # bounded by connectTimeout
    assert cpu < 0.2, cpu
    # each try lasts the connect timeout, then waits 0.1-0.2 s: at most 3 more in 1.5 s
    assert 2 <= failures <= 5, failures
    assert p.stats()["line"]["connects"] == 0


# --------------------------------------------------------------------------- 21
def _socket_fds() -> list[int]:
    found = []
    for name in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):  # the listdir's own fd, closed meanwhile
            if os.readlink(f"/proc/self/fd/{name}").startswith("socket:"):
                found.append(int(name))
    return found


def test_21_more_than_1024_open_fds() -> None:
    """Every fd below 1030 taken: the line's socket gets a higher one and polls as any
    other (replies are received with poll(), not libmodbus's select())."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < 1100:
        if hard != resource.RLIM_INFINITY and hard < 1100:
            pytest.skip(f"the hard fd limit {hard} does not allow more than 1024 fds")
        resource.setrlimit(resource.RLIMIT_NOFILE, (1400, hard))
    fds: list[int] = []
    try:
        with Rig((1,)) as rig:
            while not fds or fds[-1] < 1030:  # every fd below 1024 taken
                fds.append(os.open(os.devnull, os.O_RDONLY))
            p = rig.start(hr_items(0, 4), wait_ok=False, reconnectInterval=100, maxBackoff=200)
            wait_for(p.all_ok, 20, "polling on a high fd")
            assert p.item("hr3").value == default_register(1, 3)
            assert p.stats()["line"]["connectFailures"] == 0
            assert max(_socket_fds()) > 1030  # the line's (the simulator's are older)
    finally:
        for fd in fds:
            os.close(fd)
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


# --------------------------------------------------------------------------- 22
def test_22_serial_adapter_disappears_and_returns(tmp_path: Path) -> None:
    port = str(tmp_path / "ttyUSB0")
    with Simulator([1]) as sim:
        sim.serve_pty(baudrate=115200, link=port)
        p = start_driver({"transport": "rtu", "comPort": port, "baudRate": 115200,
                          "reconnectInterval": 100, "maxBackoff": 400}, hr_items(0, 4))
        try:
            wait_for(p.all_ok, what="polling on the pty")
            mark = len(p.snapshot())
            sim.close_pty(port)  # the pty master closes: the adapter is gone
            wait_for(lambda: p.drv.device_driver_status is RECONNECTING, 20, "Reconnecting")
            down = p.invalid_reports(mark)
            assert down and "Input/output error" in (down[0].reason or ""), down
            wait_for(lambda: p.stats()["line"]["connectFailures"] >= 2, 20, "retries")
            assert "does not exist" in (p.item("hr0").error_reason or "")
            sim.serve_pty(baudrate=115200, link=port)  # plugged in again, same name
            wait_for(lambda: p.drv.device_driver_status is RUNNING, 20, "Running again")
            wait_for(p.all_ok, what="polling resumed")
            stats = p.stats()["line"]
            assert stats["reconnects"] == 1 and stats["linkErrors"] == 1
            assert not p.wrong_values()
        finally:
            p.drv.stop_device()


# --------------------------------------------------------------------------- 23
def test_23_slow_or_raising_callback(rig: Rig) -> None:
    slow_calls: list[str] = []

    def slow(item: em.DeviceAddressItem) -> None:
        slow_calls.append(item.name)
        time.sleep(0.01)  # pacing: a slow callback

    def boom(items: list[em.DeviceAddressItem]) -> None:
        raise RuntimeError("a bug in the host application")

    p = rig.start(hr_items(0, 5), reportMode="cycle")
    q = rig.start(hr_items(0, 5), slave=2)  # on the same line
    p.drv.address_updated_callback = slow
    p.drv.addresses_updated_callback = boom
    start_p, start_q = p.stats(), q.stats()
    time.sleep(1.0)  # pacing: the window the cycles are counted in
    end_p, end_q = p.stats(), q.stats()
    cycles = end_p["cycles"] - start_p["cycles"]
    assert cycles >= 5  # the worker keeps polling, 5 x 10 ms of callbacks per cycle
    assert end_p["callbackErrors"] - start_p["callbackErrors"] >= cycles - 1
    spent = end_p["callbackTime"] - start_p["callbackTime"]
    assert spent >= 0.01 * (len(slow_calls) - 10)  # the time spent in callbacks is counted
    assert end_q["cycles"] - start_q["cycles"] >= 5  # a neighbour on the line goes on too
    assert p.drv.device_driver_status is RUNNING and q.all_ok()


# --------------------------------------------------------------------------- 24
def test_24_write_while_the_link_is_down_fails_and_is_never_replayed() -> None:
    sim = Simulator([1])
    port = sim.serve_tcp("127.0.0.1", 0)
    p = start_driver(tcp_comm(port, reconnectInterval=100), hr_items(0, 4))
    try:
        wait_for(p.all_ok)
        sim.stop()  # the DTU goes away: the port refuses
        wait_for(lambda: p.drv.device_driver_status is RECONNECTING, 20, "Reconnecting")
        ok, err = p.drv.write_address("hr2", 4321)
        assert not ok and err and "link is down" in err, err

        async def write_async() -> tuple[bool, str | None]:
            return await p.drv.write_address_async("hr3", 1234)
        ok, err = asyncio.run(write_async())
        assert not ok and err and "link is down" in err, err
        sim = Simulator([1])  # back on the same port
        sim.serve_tcp("127.0.0.1", port)
        wait_for(lambda: p.drv.device_driver_status is RUNNING, 20, "Running again")
        cycles = p.drv.stats()["cycles"]  # several cycles: nothing queued may reach the slave
        wait_for(lambda: p.drv.stats()["cycles"] >= cycles + 3, what="three more cycles")
        assert sim.slave(1).get_registers(HR, 2, 2) == [default_register(1, 2),
                                                        default_register(1, 3)]
        wait_for(p.all_ok)
        assert p.item("hr2").value == default_register(1, 2)
        stats = p.stats()
        assert stats["writes"] == 2 and stats["writeErrors"] == 2
    finally:
        p.drv.stop_device()
        sim.stop()


@pytest.mark.parametrize(("knob", "executed", "reason"),
                         [("close_every", False, "link error"),
                          ("drop_every", True, "no response (timeout)")],
                         ids=["link-breaks", "reply-lost"])
def test_24_write_whose_link_breaks_or_reply_is_lost_is_reported_failed(
    rig: Rig, knob: str, executed: bool, reason: str
) -> None:
    # a long cycle: after the first one, the write is the only request on the line
    p = rig.start(hr_items(0, 4), readCycle=60_000, reconnectInterval=100)
    asked = rig.sim.slave(1).stats()["requests"]
    rig.sim.slave(1).set_faults(**{knob: 1})
    ok, err = p.drv.write_address("hr2", 4321)
    rig.sim.slave(1).faults.clear()
    assert not ok and err and reason in err, err
    assert rig.sim.slave(1).stats()["requests"] - asked == 1  # sent once, no retry
    # past a reconnect (the link that broke) and the re-read that follows it: nothing is
    # replayed behind the caller's back
    if executed:
        time.sleep(0.4)  # pacing: no reconnect follows a lost reply; a replay's window
    else:
        wait_for(lambda: p.stats()["line"]["reconnects"] == 1 and p.all_ok(),
                 what="the reconnect and the re-read after it")
    value = rig.sim.slave(1).get_registers(HR, 2)[0]
    assert value == (4321 if executed else default_register(1, 2))
    if not executed:
        assert p.stats()["line"]["reconnects"] == 1
        wait_for(p.all_ok)
    else:  # a lost reply is no link error: no reconnect, no other request
        assert rig.sim.slave(1).stats()["requests"] - asked == 1
    assert p.item("hr2").value == default_register(1, 2)  # not taken as written
    stats = p.stats()
    assert stats["writes"] == 1 and stats["writeErrors"] == 1


# --------------------------------------------------------------------------- 25
Mutation = Callable[[bytes], bytes]


def _set_u16(adu: bytes, at: int, value: int) -> bytes:
    return adu[:at] + struct.pack(">H", value & 0xFFFF) + adu[at + 2:]


MUTATIONS: dict[str, tuple[Mutation, str]] = {
    "transaction-id": (lambda a: _set_u16(a, 0, struct.unpack_from(">H", a)[0] + 1),
                       "another MBAP transaction id"),
    "protocol-id-0001": (lambda a: _set_u16(a, 2, 0x0001), "MBAP protocol id is not 0 (0x0001)"),
    "protocol-id-0100": (lambda a: _set_u16(a, 2, 0x0100), "MBAP protocol id is not 0 (0x0100)"),
    "unit-id": (lambda a: a[:6] + bytes([a[6] + 1]) + a[7:], "wrong slave id (2)"),
    "length-long": (lambda a: _set_u16(a, 4, len(a) - 5), "MBAP length does not match"),
    "length-short": (lambda a: _set_u16(a, 4, len(a) - 7), "MBAP length does not match"),
}


class FakeModbusTcp:
    """A Modbus TCP server answering FC03 for unit 1 from default_register; every
    ``every``-th reply is passed through ``mutate`` first."""

    def __init__(self, mutate: Mutation, every: int = 2) -> None:
        self.mutate, self.every = mutate, every
        self.listener = socket.socket()
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(4)
        self.listener.settimeout(0.1)
        self.port = self.listener.getsockname()[1]
        self.replies = 0
        self.mutated = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fake-modbus-tcp")
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            with conn:
                conn.settimeout(0.1)
                self._serve(conn)

    def _recv(self, conn: socket.socket, n: int) -> bytes | None:
        data = b""
        while len(data) < n:
            if self._stop.is_set():
                return None
            try:
                chunk = conn.recv(n - len(data))
            except TimeoutError:
                continue
            if not chunk:
                return None
            data += chunk
        return data

    def _serve(self, conn: socket.socket) -> None:
        while (head := self._recv(conn, 7)) is not None:
            tid, _proto, length, unit = struct.unpack(">HHHB", head)
            pdu = self._recv(conn, length - 1)
            if pdu is None:
                return
            fc, address, count = struct.unpack(">BHH", pdu[:5])
            body = struct.pack(f">BB{count}H", fc, 2 * count,
                               *(default_register(unit, a) for a in range(address,
                                                                          address + count)))
            adu = struct.pack(">HHHB", tid, 0, len(body) + 1, unit) + body
            self.replies += 1
            if self.replies % self.every == 0:
                adu = self.mutate(adu)
                self.mutated += 1
            conn.sendall(adu)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.listener.close()


@pytest.mark.parametrize(("mutate", "reason"), MUTATIONS.values(), ids=MUTATIONS.keys())
def test_25_modbus_tcp_header_mismatches_are_rejected(mutate: Mutation, reason: str) -> None:
    server = FakeModbusTcp(mutate)
    p = start_driver({"transport": "tcp", "tcpHost": "127.0.0.1", "tcpPort": server.port,
                      "readTimeout": 150, "connectTimeout": 1000, "reconnectInterval": 100},
                     hr_items(0, 10))
    try:
        wait_for(lambda: server.mutated >= 3 and p.all_ok(), what="3 bad replies, then Ok")
        reasons = p.reasons()
        assert reasons and all(reason in r for r in reasons), reasons
        assert p.stats()["protocolErrors"] >= 2
        assert not p.wrong_values()
    finally:
        p.drv.stop_device()
        server.close()
