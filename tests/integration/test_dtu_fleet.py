"""A fleet of simulated DTUs (``DtuFleet``: one asyncio loop, one thread) dialling in to
listen-mode drivers: every DTU registers, answers from its own register map, keeps
dialling when dropped, and the fleet stops without leaving tasks, sockets or threads."""

from __future__ import annotations

import contextlib
import os
import resource
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

import edgemodbus as em
from edgemodbus.datatypes import Area, ItemStatus
from edgemodbus.line import dtu_registry
from edgemodbus.sim import DtuFleet, default_register
from tests.integration.test_dtu import dtu_device, free_port, ok, running, values
from tests.waiting import wait_for

HR = Area.HOLDING_REGISTER


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def tcp_fds(port: int) -> tuple[int, int]:
    """(our sockets connected to ``port``, our sockets whose local port is ``port``): the
    DTUs' ends and the listener's ends of the connections (from /proc/net/tcp)."""
    ours: set[int] = set()
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            target = os.readlink(f"/proc/self/fd/{fd}")
            if target.startswith("socket:["):
                ours.add(int(target[8:-1]))
    to_port = at_port = 0
    with open("/proc/net/tcp") as table:
        for row in list(table)[1:]:
            fields = row.split()
            local, remote, inode = fields[1], fields[2], int(fields[9])
            remote_port = int(remote.split(":")[1], 16)
            if inode in ours and remote_port:  # not the listening socket
                to_port += remote_port == port
                at_port += int(local.split(":")[1], 16) == port
    return to_port, at_port


def fleet_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if "fleet" in t.name]


@pytest.mark.usefixtures("engine")
def test_fifty_dtus_each_answer_from_their_own_registers() -> None:
    port = free_port()
    n = 50
    cfgs = [dtu_device(port, f"F{k:03d}", 1, registrationTimeout=5000) for k in range(n)]
    fleet = DtuFleet("127.0.0.1", port, n, registration="F{n:03d}", size=16)
    for dtu in fleet.dtus:  # a value that only this DTU has
        dtu.slave(1).set_registers(HR, 0, [1000 + dtu.number])
    with running(*cfgs):
        fds, threads = open_fds(), threading.active_count()
        with fleet:
            assert fleet_threads() == ["edgemodbus-dtu-fleet"]  # one thread for 50 DTUs
            for cfg in cfgs:
                wait_for(ok(cfg), timeout=20, what=f"{cfg.organization.device_code} Ok")
            for k, cfg in enumerate(cfgs):
                assert values(cfg) == [1000 + k, default_register(1, 1), default_register(1, 7)]
            listener = dtu_registry.listener("127.0.0.1", port)
            assert listener is not None
            assert listener.stats["accepted"] == listener.stats["registered"] == n
            assert listener.stats["unknown"] == listener.stats["silent"] == 0
            stats = fleet.stats()
            assert stats["connected"] == stats["connections"] == n
            assert stats["requests"] >= n and stats["dial_failures"] == 0
            assert stats["unknown_slave"] == stats["discarded_bytes"] == 0
            # one end each side per DTU (waited for: an end another test's line closes at
            # its next read may still hold a port number reused for this listener)
            wait_for(lambda: tcp_fds(port) == (n, n), timeout=10, what="one end per DTU")
        # Stopped: the loop's thread is gone and so is every socket and fd of the fleet;
        # the drivers close their ends as their lines see the hang-ups (a line worker at
        # its next read, a loop worker at its next turn): waited for, not read once.
        assert fleet_threads() == []
        assert threading.active_count() == threads
        assert fleet.connected == 0
        assert tcp_fds(port)[0] == 0  # the DTUs' ends
        wait_for(lambda: tcp_fds(port) == (0, 0), timeout=30, what="the drivers' ends closed")
        assert open_fds() == fds
        fleet.stop()  # idempotent


@pytest.mark.usefixtures("engine")
def test_the_fleet_dials_again_when_dropped_and_after_the_master_comes_back() -> None:
    port = free_port()
    cfgs = [dtu_device(port, f"R{k}", 1) for k in range(4)]
    with DtuFleet("127.0.0.1", port, 4, registration="R{n}", size=16,
                  reconnect=0.1, reconnect_max=0.4) as fleet:
        wait_for(lambda: fleet.stats()["dial_failures"] >= 4, what="refused dials")
        with running(*cfgs):
            for cfg in cfgs:
                wait_for(ok(cfg), timeout=15, what="values")
            listener = dtu_registry.listener("127.0.0.1", port)
            assert listener is not None
            fleet.dtu(2).slave(1).set_registers(HR, 1, [4242])
            fleet.drop(2)  # its connection breaks; it dials again and registers
            wait_for(lambda: listener.stats["registered"] >= 5, what="DTU 2 registered again")
            wait_for(lambda: values(cfgs[2])[1] == 4242, what="DTU 2's new value")
            assert fleet.dtu(2).connections == 2
        # The drivers stop: the listener closes, every DTU's connection ends, dials fail.
        wait_for(lambda: fleet.connected == 0, what="every DTU disconnected")
        failures = fleet.stats()["dial_failures"]
        wait_for(lambda: fleet.stats()["dial_failures"] > failures, what="dialling on")
        fresh = [dtu_device(port, f"R{k}", 1) for k in range(4)]
        with running(*fresh):
            for cfg in fresh:
                wait_for(ok(cfg), timeout=15, what="values after the master came back")
        assert fleet.stats()["reconnects"] >= 5


@pytest.mark.usefixtures("engine")
def test_heartbeats_go_out_between_replies() -> None:
    port = free_port()
    cfgs = [dtu_device(port, f"H{k}", 1, heartbeat="PING") for k in range(3)]
    with running(*cfgs) as drivers, DtuFleet(
        "127.0.0.1", port, 3, registration="H{n}", size=16, heartbeat=b"PING",
        heartbeat_interval=0.05,
    ) as fleet:
        for cfg in cfgs:
            wait_for(ok(cfg), what="values")
        wait_for(lambda: all(d.stats()["line"]["heartbeats"] >= 3 for d in drivers),
                 what="heartbeats seen by every line")
        assert all(d.stats()["timeouts"] == d.stats()["protocolErrors"] == 0 for d in drivers)
        assert all(it.status is ItemStatus.OK for cfg in cfgs for it in cfg.address_list)
        assert fleet.stats()["heartbeats"] >= 9


def test_stop_closes_connections_nobody_accepted_and_pending_dials() -> None:
    """Connections still in a listener's backlog and dials waiting for their turn under
    ``dial_rate`` end with the fleet: no task, socket or thread is left."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(64)  # never accepts: the kernel completes the handshakes
        port = int(server.getsockname()[1])
        fds = open_fds()
        fleet = DtuFleet("127.0.0.1", port, 40, dial_rate=20.0).start()
        wait_for(lambda: fleet.connected >= 5, what="first connections")
        assert fleet.connected < 40  # the rest wait for their turn
        started = time.monotonic()
        fleet.stop()
        assert time.monotonic() - started < 2.0
        assert fleet_threads() == []
        assert fleet.connected == 0
        assert open_fds() == fds


@pytest.mark.usefixtures("engine")
def test_fault_knobs_act_on_one_dtu_only() -> None:
    """The fleet's slaves are the simulator's slaves: their fault knobs work per DTU."""
    port = free_port()
    cfgs = [dtu_device(port, f"S{k}", 1) for k in range(2)]
    fleet = DtuFleet("127.0.0.1", port, 2, registration="S{n}", size=16)
    fleet.dtu(1).slave(1).faults.silent = True
    with running(*cfgs) as drivers, fleet:
        wait_for(ok(cfgs[0]), what="the talking DTU's values")
        wait_for(lambda: drivers[1].stats()["timeouts"] >= 1, what="the silent one times out")
        assert not any(it.status is ItemStatus.OK for it in cfgs[1].address_list)
        assert all(it.status is ItemStatus.OK for it in cfgs[0].address_list)


def test_simulate_dial_dtus_plays_a_fleet_from_the_command_line() -> None:
    """`edgemodbus simulate --dial HOST:PORT --dtus N`: N DTUs from one process."""
    port = free_port()
    cfgs = [em.load_device_config({
        "communication": {"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "registration": "text", "dtuId": f"C{k}",
                          "slaveId": 2, "readCycle": 200, "readTimeout": 500},
        "addressList": [{"name": "r", "address": "hr:42", "deviceDataType": "UInt16"}],
    }) for k in (5, 6, 7)]
    with running(*cfgs):
        proc = subprocess.Popen(
            [sys.executable, "-m", "edgemodbus.cli", "simulate", "--dial", f"127.0.0.1:{port}",
             "--dtus", "3", "--first-dtu", "5", "--registration", "C{n}", "--slaves", "2",
             "--size", "50"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        try:
            for cfg in cfgs:
                wait_for(ok(cfg), timeout=15, what="a value via each DTU")
                assert values(cfg) == [2 * 1000 + 42]  # the simulator's address-derived value
        finally:
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=10)
    assert proc.returncode == 130, err  # Ctrl-C (docs/command-line.md, "Exit codes")
    assert out.splitlines()[0] == f"dialling 127.0.0.1:{port} with 3 DTUs (C5..C7)"


def test_simulate_dtus_says_when_the_hard_open_files_limit_is_too_low() -> None:
    def low_limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (100, 100))

    out = subprocess.run(
        [sys.executable, "-m", "edgemodbus.cli", "simulate", "--dial", "127.0.0.1:9",
         "--dtus", "500"],
        capture_output=True, text=True, timeout=30, preexec_fn=low_limit, check=False,
    )
    assert out.returncode == 1
    assert "564 open files needed" in out.stderr and "hard RLIMIT_NOFILE" in out.stderr
    for args in (["--dtus", "3"], ["--dial", "127.0.0.1:9", "--dtus", "0"],
                 ["--dial", "127.0.0.1:9", "--dtus", "3", "--registration", "same"]):
        out = subprocess.run([sys.executable, "-m", "edgemodbus.cli", "simulate", *args],
                             capture_output=True, text=True, timeout=30, check=False)
        assert out.returncode == 2, args


def test_stop_while_every_dial_is_refused() -> None:
    """A cancellation that arrives as a connect fails is not lost (wait_for() before
    Python 3.12 raises the connect's OSError instead): the fleet still stops at once."""
    port = free_port()  # nobody listens: every dial is refused at once
    for _ in range(3):
        fleet = DtuFleet("127.0.0.1", port, 200, reconnect=0.001, reconnect_max=0.002).start()
        deadline = time.monotonic() + 8.0
        while fleet.stats()["dial_failures"] < 2000:  # dialling flat out
            assert time.monotonic() < deadline, "dials not refused"
            time.sleep(0.01)  # poll: until the dials fail (deadline above)
        started = time.monotonic()
        fleet.stop(timeout=5.0)
        assert time.monotonic() - started < 2.0
        assert fleet_threads() == []
