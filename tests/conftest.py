"""Shared test configuration: markers, real-peer fixtures, and the leak check every test gets.

Fixtures
- `slave_factory(transport="rtu-over-tcp", **PymodbusSlave kwargs)` -> started slave;
  every slave it made is stopped after the test.
- `rtu_tcp_slave`, `tcp_slave`: a running PymodbusSlave for units 1, 2, 3 on 127.0.0.1;
  `serial_slave`: the same on one end of a `pty_pair`, `serial_slave.master_path` is the
  end our master opens. Other settings by indirect parametrization, e.g.
  `@pytest.mark.parametrize("rtu_tcp_slave", [{"response_delay": 0.3}], indirect=True)`.
- `pty_pair`: a running PtyPair in the test's tmp dir.
- `free_tcp_port`: a port nothing listens on (racy; for "connection refused" tests).
- `engine`: runs the test once per DTU engine ("thread", "loop"); listen-mode devices
  made through `tests.engines.with_engine` ask for it (use it as
  `@pytest.mark.usefixtures("engine")` on tests that exercise a DTU's link).
- `no_leaks` (autouse): fails the test if it leaves new threads, fds or child processes
  behind; opt out with `@pytest.mark.no_leak_check`.
"""

from __future__ import annotations

import contextlib
import gc
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, settings

from tests import engines
from tests.mosquitto import Mosquitto
from tests.peers import PtyPair, PymodbusSlave, Transport, free_port

DEFAULT_UNITS: tuple[int, ...] = (1, 2, 3)
LEAK_GRACE_SECONDS = 2.0

# Every hypothesis test runs under this profile (a test's own @settings still wins for the
# keys it names).  No per-example deadline and no too_slow health check: both measure
# time, which a loaded machine stretches (pytest-timeout bounds a hang; a test that
# measures speed does it itself).  print_blob: a failure prints the @reproduce_failure
# line.  The example database stays hypothesis's default (.hypothesis/ in the checkout,
# not in git): in a developer's checkout a failing example is replayed first, so it is
# reported again until fixed; CI's fresh clone starts without one.
# On a CI machine hypothesis loads its own "ci" profile first (derandomized, no database):
# ours is made on top of whichever is loaded, so CI keeps those.
settings.register_profile(
    "edgemodbus", parent=settings.default, deadline=None,
    suppress_health_check=[HealthCheck.too_slow], print_blob=True,
)
settings.load_profile("edgemodbus")  # pytest --hypothesis-profile=NAME picks another


def pytest_configure(config: pytest.Config) -> None:
    """Register our markers (kept here, not in pyproject)."""
    config.addinivalue_line("markers", "slow: long-running test (deselect with -m 'not slow')")
    config.addinivalue_line(
        "markers", "no_leak_check: skip the autouse thread/fd/child-process leak check"
    )


# --------------------------------------------------------------------------- peers
SlaveFactory = Callable[..., PymodbusSlave]


@pytest.fixture
def slave_factory() -> Iterator[SlaveFactory]:
    """Start PymodbusSlaves on demand; all are stopped after the test."""
    started: list[PymodbusSlave] = []

    def make(transport: Transport = "rtu-over-tcp", **kwargs: Any) -> PymodbusSlave:
        kwargs.setdefault("units", DEFAULT_UNITS)
        slave = PymodbusSlave(transport, **kwargs)
        started.append(slave)
        return slave.start()

    yield make
    for slave in reversed(started):
        slave.stop()


def _params(request: pytest.FixtureRequest) -> dict[str, Any]:
    params = getattr(request, "param", None) or {}
    return dict(params)


@pytest.fixture
def rtu_tcp_slave(request: pytest.FixtureRequest, slave_factory: SlaveFactory) -> PymodbusSlave:
    """A running slave speaking RTU framing over TCP (a DTU), units 1-3."""
    return slave_factory("rtu-over-tcp", **_params(request))


@pytest.fixture
def tcp_slave(request: pytest.FixtureRequest, slave_factory: SlaveFactory) -> PymodbusSlave:
    """A running Modbus TCP slave, units 1-3."""
    return slave_factory("tcp", **_params(request))


@pytest.fixture
def pty_pair(tmp_path: Path) -> Iterator[PtyPair]:
    """Two linked ptys (socat) in the test's tmp dir; closed after the test."""
    with PtyPair(tmp_path / "pty") as pair:
        yield pair


@pytest.fixture
def serial_slave(
    request: pytest.FixtureRequest, pty_pair: PtyPair, slave_factory: SlaveFactory
) -> PymodbusSlave:
    """A running serial RTU slave on `pty_pair.b`; the master opens `.master_path`."""
    params = _params(request)
    params.setdefault("device", pty_pair.b)
    params.setdefault("master_path", pty_pair.a)
    return slave_factory("serial", **params)


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Mosquitto]:
    """A mosquitto of its own on an ephemeral port of 127.0.0.1, stopped at the end."""
    with Mosquitto(tmp_path / "broker") as peer:
        yield peer


@pytest.fixture
def free_tcp_port() -> int:
    """A 127.0.0.1 port that nothing listened on a moment ago."""
    return free_port()


@pytest.fixture(params=engines.ENGINES)
def engine(request: pytest.FixtureRequest) -> Iterator[str]:
    """The engine serving the test's DTU lines (tests/engines.py)."""
    with engines.chosen(str(request.param)) as chosen:
        yield chosen


# --------------------------------------------------------------------------- leaks
@dataclass
class _Snapshot:
    threads: set[threading.Thread] = field(default_factory=set)
    fds: dict[int, str] = field(default_factory=dict)
    children: dict[int, str] = field(default_factory=dict)


def _open_fds() -> dict[int, str]:
    fds: dict[int, str] = {}
    for name in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):  # the listdir's own fd, or closed meanwhile
            fds[int(name)] = os.readlink(f"/proc/self/fd/{name}")
    return fds


def _child_processes() -> dict[int, str]:
    """pid -> command name of our direct children (live or zombie)."""
    me = os.getpid()
    children: dict[int, str] = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as stat:
                raw = stat.read()
        except OSError:
            continue
        head, _, rest = raw.rpartition(b")")
        fields = rest.split()
        if len(fields) > 1 and int(fields[1]) == me:
            children[int(name)] = head.partition(b"(")[2].decode(errors="replace")
    return children


def _snapshot() -> _Snapshot:
    return _Snapshot(
        threads={t for t in threading.enumerate() if t.is_alive()},
        fds=_open_fds(),
        children=_child_processes(),
    )


def _leaks(before: _Snapshot, after: _Snapshot) -> list[str]:
    problems: list[str] = []
    for thread in sorted(after.threads - before.threads, key=lambda t: t.name):
        target = getattr(thread, "_target", None)
        problems.append(f"thread {thread.name!r} (daemon={thread.daemon}, target={target!r})")
    for fd, target in sorted(after.fds.items()):
        old = before.fds.get(fd)
        if old is None:
            problems.append(f"fd {fd} -> {target}")
        elif old != target:
            problems.append(f"fd {fd} -> {target} (was {old})")
    for pid, comm in sorted(after.children.items()):
        if pid not in before.children:
            problems.append(f"child process {pid} ({comm})")
    return problems


@pytest.fixture(autouse=True)
def no_leaks(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail the test if it leaves threads, open fds or child processes behind.

    Threads get up to LEAK_GRACE_SECONDS to finish (checked repeatedly, with one
    gc.collect() for objects in cycles) before the test fails.
    """
    if request.node.get_closest_marker("no_leak_check"):
        yield
        return
    before = _snapshot()
    yield
    deadline = time.monotonic() + LEAK_GRACE_SECONDS
    collected = False
    while True:
        problems = _leaks(before, _snapshot())
        if not problems:
            return
        if not collected:
            gc.collect()
            collected = True
            continue
        if time.monotonic() >= deadline:
            break
        time.sleep(0.05)  # poll: the leak check's step until its grace deadline
    pytest.fail(
        "test left resources behind (use @pytest.mark.no_leak_check only if intended):\n  "
        + "\n  ".join(problems),
        pytrace=False,
    )
