"""Connect-mode lines on the loop engine under the faults of their connect
(docs/fault-checklist.md "The loop engine's sockets"): a host name whose DNS answer
never comes, and no fd for the connect's socket (EMFILE).  The other lines on the loop
are polled meanwhile, the faulty one says why and retries at its reconnect interval."""

from __future__ import annotations

import errno
import os
import socket
import threading
import time
import types
from collections.abc import Iterator
from typing import Any

import pytest

from edgemodbus.datatypes import ItemStatus
from edgemodbus.line import loop_connect
from tests.integration.test_loop_connect import all_ok, device, exact, running
from tests.integration.test_loop_dtu_faults import loop_thread, thread_cpu
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

SLOW = "slow.invalid"  # a name whose lookup blocks until the test lets it go


@pytest.fixture
def slow_dns(monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, Any]]:
    """_resolve blocks for SLOW (as getaddrinfo does while a DNS server never answers)
    until the test ends; other names resolve as ever.  ``calls``: lookups of SLOW."""
    real = loop_connect._resolve
    release = threading.Event()
    state: dict[str, Any] = {"calls": 0, "blocked": threading.Event()}

    def resolve(host: str, port: int) -> list[loop_connect.Address]:
        if host == SLOW:
            state["calls"] += 1
            state["blocked"].set()
            release.wait(60)
            raise socket.gaierror(socket.EAI_AGAIN, "Temporary failure in name resolution")
        return real(host, port)

    monkeypatch.setattr(loop_connect, "_resolve", resolve)
    try:
        yield state
    finally:
        release.set()
        wait_for(lambda: all(t.name != "edgemodbus-resolve" for t in threading.enumerate()),
                 what="the resolver threads ended")


def test_a_name_that_never_resolves_holds_up_no_other_line(slow_dns: dict[str, Any]) -> None:
    """One thread resolved names in turn: the good line's "localhost" waited behind the
    slow name (and behind each of its retries) and its connect timed out resolving."""
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        slow = device(slave.port, code="slow", tcpHost=SLOW, connectTimeout=300,
                      reconnectInterval=100)
        good = device(slave.port, code="good", tcpHost="localhost")
        with running(slow) as (d_slow,):
            wait_for(slow_dns["blocked"].is_set, what="the slow lookup under way")
            with running(good):
                wait_for(lambda: all_ok(good), what="the good line polled")
                assert exact(good, 1)
                failures = d_slow.stats()["line"]["connectFailures"]
                wait_for(lambda: d_slow.stats()["line"]["connectFailures"] >= failures + 3,
                         what="three more failed connects of the slow line")
                reason = slow.address_list[0].error_reason or ""
                assert "resolving 'slow.invalid'" in reason, reason
                assert slow.address_list[0].status is not ItemStatus.OK
                assert slow_dns["calls"] == 1  # its retries share the one lookup
                resolvers = [t for t in threading.enumerate()
                             if t.name == "edgemodbus-resolve"]
                assert len(resolvers) <= loop_connect.MAX_RESOLVERS


def test_no_fd_for_the_connect_is_told_and_retried_without_a_spin(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """socket() failing with EMFILE for one endpoint: its items say so, it retries at
    its reconnect interval (no spin), the other line on the loop is polled."""
    with PymodbusSlave("rtu-over-tcp", units=(1, 2)) as slave:
        starved = device(slave.port, slave=2, code="starved", tcpHost="::1",
                         reconnectInterval=200, maxBackoff=400)
        good = device(slave.port, code="good")
        class NoFdForV6(socket.socket):
            """A socket, but none of AF_INET6: as socket() fails when no fd is left."""

            def __init__(self, family: int = -1, *args: Any, **kwargs: Any) -> None:
                if family == socket.AF_INET6:
                    tries["n"] += 1
                    raise OSError(errno.EMFILE, os.strerror(errno.EMFILE))
                super().__init__(family, *args, **kwargs)

        tries = {"n": 0}
        # the dialer's own view of the socket module, not the process's
        monkeypatch.setattr(loop_connect, "socket",
                            types.SimpleNamespace(**{**vars(socket), "socket": NoFdForV6}))
        with running(good, starved) as (_d_good, d_starved):
            wait_for(lambda: all_ok(good), what="the good line polled")
            wait_for(lambda: "Too many open files" in
                     (starved.address_list[0].error_reason or ""), what="the reason")
            first, loop = tries["n"], loop_thread()
            cpu0, wall0 = thread_cpu(loop), time.monotonic()
            wait_for(lambda: d_starved.stats()["line"]["connectFailures"] >= 6,
                     what="six failed connects")
            cpu = (thread_cpu(loop) - cpu0) / (time.monotonic() - wall0)
            assert tries["n"] - first <= 10  # one try per reconnect interval, not a spin
            assert cpu < 0.05, cpu  # the loop thread while the fault holds
            assert exact(good, 1)
