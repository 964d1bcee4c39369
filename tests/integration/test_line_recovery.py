"""A line worker never dies (issue #25): an unexpected exception on it is logged once,
the link closed, the devices told why, the waiting jobs failed with the reason, and the
line restarts with backoff.  Real libmodbus, pymodbus (own process) as the slaves."""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.config import ConfigError
from edgemodbus.datatypes import Area
from edgemodbus.errors import ModbusConnectionError
from edgemodbus.line.connect import open_link
from edgemodbus.line.endpoint import LineTiming, TcpEndpoint
from edgemodbus.line.jobs import PollLag
from edgemodbus.line.link import ContextLink
from edgemodbus.line.worker import LineWorker
from tests.conftest import SlaveFactory
from tests.integration.test_line_fairness import (
    BYSTANDER,
    SERVED,
    SERVED_UNIT,
    TARGET,
    Line,
    mbap,
    recv_adu,
)
from tests.peers import PymodbusSlave
from tests.waiting import wait_for


@pytest.fixture
def peer(slave_factory: SlaveFactory) -> PymodbusSlave:
    return slave_factory("rtu-over-tcp", units=(BYSTANDER, TARGET, SERVED), size=200)


@pytest.fixture
def line(peer: PymodbusSlave) -> Iterator[Line]:
    gw = Line(peer)
    try:
        yield gw
    finally:
        gw.close()

# -- a line worker never dies ----------------------------------------------------------------
FAST = LineTiming(response_timeout=0.5, byte_timeout=0.05, reconnect_interval=0.2,
                  connect_timeout=1.0, max_backoff=0.5)


def line_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("edgemodbus-line")]


@pytest.mark.parametrize("host", ["plc..local", "a" * 64 + ".local"])
def test_a_host_name_idna_refuses_fails_the_connect_not_the_worker(host: str) -> None:
    worker = LineWorker(TcpEndpoint(host, 502), FAST)
    worker.start()
    try:
        thread = worker._thread
        for _ in range(2):  # every job gets an answer, with the reason
            with pytest.raises(ModbusConnectionError, match="not a valid DNS name"):
                worker.read(1, Area.HOLDING_REGISTER, 0, 1).result(10)
        wait_for(lambda: worker.stats.connect_failures >= 3, 15, "connects tried again")
        assert thread is not None and thread.is_alive()
    finally:
        worker.stop()


def test_a_device_on_a_bad_host_name_is_told_why_and_forwards_are_answered() -> None:
    """A device file is refused at load with the field named; a host name that reaches
    the line anyway (set on the model after validation, as a library caller may) costs
    the line its link, never its worker."""
    data: dict[str, Any] = {
        "organization": {"deviceCode": "badhost"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "plc..local",
                          "tcpPort": 502, "slaveId": 1, "reconnectInterval": 200},
        "addressList": [{"name": "a", "address": "hr:0", "deviceDataType": "UInt16"}],
    }
    with pytest.raises(ConfigError, match=r"communication\.tcpHost 'plc\.\.local'"):
        em.load_device_config(data)
    data["communication"]["tcpHost"] = "plc.local"
    cfg = em.load_device_config(data)
    cfg.communication.tcp_host = "plc..local"  # not validated on assignment
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        wait_for(lambda: drv.device_driver_status is em.DeviceDriverStatus.RECONNECTING, 15,
                 "the device told the link is down")
        reason = str(drv.snapshot()["items"]["a"]["errorReason"])
        assert "plc..local" in reason and "not a valid DNS name" in reason, reason
        with pytest.raises(ModbusConnectionError):  # a gateway answers 0A at once
            drv.forward(struct.pack(">BHH", 3, 0, 1), 0.5).result(10)
    finally:
        drv.stop_device()


def test_an_unexpected_error_on_the_worker_restarts_the_line(
        line: Line, monkeypatch: pytest.MonkeyPatch) -> None:
    threads = line_threads()
    run_engine = ContextLink.run_engine
    armed = threading.Event()
    reasons: list[str] = []
    previous = line.bystander.addresses_updated_callback

    def record(items: list[Any]) -> None:
        reasons.extend(str(it.error_reason) for it in items if it.error_reason)
        if previous is not None:
            previous(items)

    def failing(self: ContextLink, *args: Any, **kw: Any) -> tuple[int, int, int] | None:
        if armed.is_set():
            armed.clear()
            raise RuntimeError("injected")
        return run_engine(self, *args, **kw)

    line.bystander.addresses_updated_callback = record
    monkeypatch.setattr(ContextLink, "run_engine", failing)
    armed.set()
    # a job brings the worker out of the engine (which runs in C while nothing changes)
    line.target.forward(struct.pack(">BHH", 3, 0, 1), 3.0).result(15)
    wait_for(lambda: line.line_stats()["workerErrors"] == 1, 15, "the injected error")
    # the link closed and reopened, the devices told why, polling again
    wait_for(lambda: line.line_stats()["reconnects"] >= 1, 15, "the line restarted")
    cycles = line.bystander.stats()["cycles"]
    wait_for(lambda: line.bystander.stats()["cycles"] >= cycles + 5, 15, "polling again")
    assert line.bystander.device_driver_status is em.DeviceDriverStatus.RUNNING
    assert any("line worker error: RuntimeError: injected" in r for r in reasons), reasons
    assert line_threads() == threads  # the same worker thread, alive
    assert line.target.forward(struct.pack(">BHH", 3, 0, 1), 3.0).result(15)[0] == 3


class FlakyConnector:
    """Opens the line's link, after raising a bug's exception ``fails`` times."""

    def __init__(self, endpoint: TcpEndpoint, fails: int) -> None:
        self.endpoint, self.fails, self.calls = endpoint, fails, 0

    def open(self, line: LineWorker) -> ContextLink:
        self.calls += 1
        if self.calls <= self.fails:
            raise RuntimeError("injected connect bug")
        return open_link(self.endpoint, line.timing, line.stats)


def test_a_repeated_error_is_logged_once_and_jobs_fail_with_it(
        peer: PymodbusSlave, caplog: pytest.LogCaptureFixture) -> None:
    endpoint = TcpEndpoint("127.0.0.1", peer.port)
    connector = FlakyConnector(endpoint, fails=4)
    worker = LineWorker(endpoint, FAST, connector)
    worker.start()
    try:
        with pytest.raises(ModbusConnectionError, match="RuntimeError: injected connect bug"):
            worker.read(BYSTANDER, Area.HOLDING_REGISTER, 0, 2).result(10)
        # the line restarts (with backoff) until the connector works
        wait_for(lambda: worker.link_up, 15, "the link up after the injected errors")
        assert worker.read(BYSTANDER, Area.HOLDING_REGISTER, 0, 2).result(10) == \
            peer.registers(BYSTANDER, "hr", 0, 2)
        assert worker.stats.worker_errors == 4
        errors = [r for r in caplog.records
                  if r.levelno >= logging.ERROR and "injected connect bug" in r.getMessage()]
        assert len(errors) == 1, errors  # logged once while it repeats
    finally:
        worker.stop()


class StatusLog(em.Listener[em.DriverModbusRtu]):
    """A device's status changes, timed (``time.monotonic()``)."""

    def __init__(self) -> None:
        self.seen: list[tuple[float, em.DeviceDriverStatus, str | None]] = []

    def on_changes(self, source: em.DriverModbusRtu, items: list[Any]) -> None:
        return None

    def on_status(self, source: em.DriverModbusRtu, status: em.DeviceDriverStatus,
                  reason: str | None) -> None:
        self.seen.append((time.monotonic(), status, reason))


def offline_since(status: StatusLog) -> list[tuple[float, str | None]]:
    return [(t, r) for t, s, r in status.seen if s is em.DeviceDriverStatus.OFFLINE]


@pytest.mark.parametrize("engine", ["thread", "loop"])
def test_a_worker_error_sets_the_devices_offline_and_fails_the_job_it_took(
        peer: PymodbusSlave, engine: str, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """Issue #25: the devices are Offline with the error's one-line reason until the
    line is back (not Reconnecting); the job the worker had taken fails at once (a
    served write answered 0B, not never); the error logged once while it repeats; the
    line restarts after the reconnect backoff, on both engines (line/loop.py calls the
    same recovery)."""
    gw = Line(peer, engine=engine)
    try:
        status = StatusLog()
        gw.bystander.subscribe(status)
        job_ran = PollLag.job_ran
        crashes: list[float] = []

        def failing(self: PollLag, *args: Any) -> None:  # a bug in the worker's own code
            if len(crashes) < 2:
                crashes.append(time.monotonic())
                raise RuntimeError("injected\nsecond line of the message")
            job_ran(self, *args)

        monkeypatch.setattr(PollLag, "job_ran", failing)  # (class level: __slots__)
        with socket.create_connection(("127.0.0.1", gw.port), timeout=15) as master:
            for tid in (1, 2):  # each crashes the worker once, with the same reason
                start = time.monotonic()
                master.sendall(mbap(tid, SERVED_UNIT, struct.pack(">BHH", 6, 1, 4321)))
                assert recv_adu(master)[7:] == b"\x86\x0b"  # answered, at once
                assert time.monotonic() - start < 5.0
                wait_for(lambda n=tid: len(offline_since(status)) == n, 15, "Offline")
                wait_for(lambda: gw.bystander.device_driver_status
                         is em.DeviceDriverStatus.RUNNING, 15, "the line back, polling")
            master.sendall(mbap(3, SERVED_UNIT, struct.pack(">BHH", 6, 1, 4321)))
            assert recv_adu(master)[7:] == struct.pack(">BHH", 6, 1, 4321)
        reason = "line worker error: RuntimeError: injected"
        offline = offline_since(status)
        assert [r for _, r in offline] == [reason, reason], status.seen
        assert not any(s is em.DeviceDriverStatus.RECONNECTING for _, s, _ in status.seen)
        item = gw.bystander.address_items[0]
        # each Offline lasts until the line is back: at least the reconnect backoff
        # (reconnectInterval 300 ms, +-20 %), Running again after it
        for when, _ in offline:
            back = [t for t, s, _ in status.seen
                    if s is em.DeviceDriverStatus.RUNNING and t > when]
            assert back and back[0] - when >= 0.8 * 0.3, status.seen
        assert item.status is em.ItemStatus.OK
        assert gw.line_stats()["workerErrors"] == 2
        logged = [r for r in caplog.records
                  if r.levelno >= logging.ERROR and "injected" in r.getMessage()]
        assert len(logged) == 1, logged  # once while it repeats
        assert peer.registers(SERVED, "hr", 1) == [4321]
    finally:
        gw.close()
