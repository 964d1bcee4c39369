"""DTU streams end to end, framed in C (csrc/emb_stream.c): heartbeats on an RTU-over-TCP
client link in front of pymodbus, and a wrapped-report DTU in listen mode whose socket is
above fd 1024 (the listener used to refuse those: libmodbus's select() stopped there)."""

from __future__ import annotations

import os
import resource
import selectors
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from edgemodbus.datatypes import Area, DeviceDriverStatus
from edgemodbus.line.endpoint import LineTiming, TcpEndpoint
from edgemodbus.line.worker import LineWorker
from edgemodbus.sim import Simulator
from tests.integration.test_dtu import free_port
from tests.integration.test_wrapped_link import running, value_of, wrapped_device
from tests.peers import PymodbusSlave, default_register
from tests.waiting import wait_for


class HeartbeatProxy:
    """A DTU in front of a slave: relays bytes both ways and puts a heartbeat in front of
    every reply segment, another behind it, and one on its own when the link is idle."""

    def __init__(self, slave: tuple[str, int], heartbeat: bytes) -> None:
        self.heartbeat = heartbeat
        self.sent = 0
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = int(self._listener.getsockname()[1])
        self._slave = slave
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="heartbeat-proxy")
        self._thread.start()

    def _run(self) -> None:
        with self._listener, selectors.DefaultSelector() as sel:
            sel.register(self._listener, selectors.EVENT_READ)
            pairs: dict[socket.socket, socket.socket] = {}
            up: set[socket.socket] = set()  # our side of the slave connections
            try:
                while not self._stop.is_set():
                    events = sel.select(0.05)
                    if not events:  # idle: a heartbeat on each master link
                        for master in [s for s in pairs if s not in up]:
                            master.sendall(self.heartbeat)
                            self.sent += 1
                    for key, _ in events:
                        sock = key.fileobj
                        assert isinstance(sock, socket.socket)
                        if sock is self._listener:
                            master, _ = self._listener.accept()
                            slave = socket.create_connection(self._slave)
                            pairs[master], pairs[slave] = slave, master
                            up.add(slave)
                            sel.register(master, selectors.EVENT_READ)
                            sel.register(slave, selectors.EVENT_READ)
                            continue
                        data = sock.recv(4096)
                        if not data:
                            return
                        if sock in up:  # a reply: heartbeats around it
                            data = self.heartbeat + data + self.heartbeat
                            self.sent += 2
                        pairs[sock].sendall(data)
            finally:
                for sock in pairs:
                    sock.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


def test_heartbeats_around_replies_on_a_client_link() -> None:
    with PymodbusSlave("rtu-over-tcp", units=(1, 2)) as slave:
        proxy = HeartbeatProxy(slave.address, b"HB")
        worker = LineWorker(TcpEndpoint("127.0.0.1", proxy.port, heartbeat=b"HB"),
                            LineTiming(response_timeout=1.0, byte_timeout=0.1))
        worker.start()
        try:
            for unit in (1, 2):
                assert worker.read(unit, Area.HOLDING_REGISTER, 0, 125).result(5) == [
                    default_register(unit, "hr", a) for a in range(125)]
            worker.write_register(2, 9, 4242).result(5)
            assert worker.read(2, Area.HOLDING_REGISTER, 9, 1).result(5) == [4242]
            stats = worker.stats
            assert stats.timeouts == stats.crc_errors == stats.protocol_errors == 0
            assert stats.heartbeats >= 6
        finally:
            worker.stop()
            proxy.close()
    assert stats.heartbeats <= proxy.sent


@contextmanager
def fds_taken_below(limit: int) -> Iterator[None]:
    """Every free fd below ``limit`` taken (the soft fd limit raised; put back after)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < limit + 200:
        pytest.skip(f"the hard fd limit {hard} does not allow fds above {limit}")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, limit + 200), hard))
    fds: list[int] = []
    try:
        while not fds or fds[-1] < limit:
            fds.append(os.open(os.devnull, os.O_RDONLY))
        yield
    finally:
        for fd in fds:
            os.close(fd)
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_a_wrapped_dtu_on_an_fd_above_1024_polls_and_reports() -> None:
    """Every fd below 1030 taken: the listener, the DTU's connection and the simulator's
    sockets all get higher ones."""
    port = free_port()
    cfg = wrapped_device({"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "dtuId": "MCU9", "registration": "text",
                          "readCycle": 100, "heartbeatHex": "FE"})
    with fds_taken_below(1030), Simulator(slaves=[1]) as sim, running(cfg) as drv:
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 0, list(range(600, 700)))
        client = sim.dial("127.0.0.1", port, registration=b"MCU9", wrapped=True,
                          heartbeat=b"\xfe", heartbeat_interval=0.02)
        wait_for(lambda: value_of(cfg, "r80") == 680, what="the integrity poll")
        assert drv.device_driver_status is DeviceDriverStatus.RUNNING
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 2, [7])
        client.push_report(1, Area.HOLDING_REGISTER, 2, 1)
        wait_for(lambda: value_of(cfg, "r2") == 7, what="the report applied")
        stats = drv.stats()
        assert stats["timeouts"] == 0 and stats["line"]["heartbeats"] >= 1
        assert stats["line"]["droppedFrames"] == 0
        ok, err = drv.write_address("r30", 4321)
        assert ok, err
        assert sim.slave(1).get_registers(Area.HOLDING_REGISTER, 30) == [4321]
