"""The Redis lease (gateway/lease.py) under the faults of its socket
(docs/fault-checklist.md "The Redis lease"): Redis down, answering garbage, a bulk
length of 1 GB, silent past the lease, a huge value under the lease key.  A fake server
in front of a real redis-server plays each fault and then relays again: the lease is
never held while the engine fails, is lost before its known end, costs one log line per
kind of error and interval and almost no CPU, and is taken again once Redis answers."""

from __future__ import annotations

import contextlib
import logging
import resource
import selectors
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.peers import free_port
from tests.redis_server import RedisServer, redis_binary
from tests.waiting import wait_for

try:
    redis_binary()
    import redis  # noqa: F401
except Exception as exc:  # pragma: no cover - the Makefile installs both
    pytest.skip(f"no redis-server or redis client: {exc}", allow_module_level=True)

from edgemodbus.gateway.lease import Lease, LeaseKeeper, RedisEngine

LEASE_MS, RENEW_MS = 1000, 300
UNREACHABLE = "lease: cannot reach the lease engine"


class FakeRedis:
    """A TCP server on 127.0.0.1 whose connections each play :attr:`mode` as it was when
    they were accepted: ``relay`` (to the real Redis at ``upstream``), ``garbage`` (a
    reply that is not RESP), ``huge`` (a bulk string announced as 1 GB, 1 KB sent),
    ``silent`` (reads, never answers)."""

    def __init__(self, upstream: int) -> None:
        self.upstream = upstream
        self.mode = "relay"
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.conns: list[socket.socket] = []
        self._accepter = threading.Thread(target=self._accept, name="fake-redis")

    def __enter__(self) -> FakeRedis:
        self._accepter.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._accepter.join()
        for thread in self._threads:
            thread.join()
        for conn in self.conns:
            conn.close()
        self.sock.close()

    def _accept(self) -> None:
        self.sock.settimeout(0.05)
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            self.conns.append(conn)
            thread = threading.Thread(target=self._serve, args=(conn, self.mode))
            self._threads.append(thread)
            thread.start()

    def _serve(self, conn: socket.socket, mode: str) -> None:
        up = socket.create_connection(("127.0.0.1", self.upstream)) if mode == "relay" \
            else None
        sel = selectors.DefaultSelector()
        sel.register(conn, selectors.EVENT_READ, up)
        if up is not None:
            sel.register(up, selectors.EVENT_READ, conn)
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(0.05):
                    src: socket.socket = key.fileobj  # type: ignore[assignment]
                    try:
                        data = src.recv(65536)
                    except OSError:
                        data = b""
                    if not data:
                        return
                    if key.data is not None:
                        key.data.sendall(data)
                    elif mode == "garbage":
                        conn.sendall(b"?this is no RESP " + b"x" * 4000 + b"\r\n")
                    elif mode == "huge":
                        conn.sendall(b"$1073741824\r\n" + b"x" * 1024)
        except OSError:
            return
        finally:
            sel.close()
            if up is not None:
                up.close()


class Lines(logging.Handler):
    """The lease's log lines."""

    def __init__(self) -> None:
        super().__init__()
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())

    def count(self, words: str) -> int:
        return sum(words in line for line in list(self.lines))


@contextlib.contextmanager
def lease_on(port: int) -> Iterator[tuple[Lease, Lines, list[tuple[float, float]]]]:
    """A lease kept on its thread against 127.0.0.1:port; the losses as (when, the
    lease's known end then)."""
    lines = Lines()
    logger = logging.getLogger("edgemodbus.lease")
    logger.addHandler(lines)
    logger.setLevel(logging.INFO)
    engine = RedisEngine(f"redis://127.0.0.1:{port}/0", "faults:", timeout=RENEW_MS / 1000)
    losses: list[tuple[float, float]] = []
    lease = Lease(engine, LEASE_MS, RENEW_MS,
                  on_loss=lambda reason: losses.append((time.monotonic(), lease.expires)))
    keeper = LeaseKeeper(lease).start()
    try:
        yield lease, lines, losses
    finally:
        keeper.stop()
        engine.close()
        logger.removeHandler(lines)


def thread_cpu(thread: threading.Thread) -> float:
    """CPU seconds of one thread of this process (/proc)."""
    with open(f"/proc/self/task/{thread.native_id}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / 100.0


def errors_for(lease: Lease, seconds: float) -> int:
    """engineErrors added over ``seconds`` (at least three attempts' worth)."""
    before = lease.counts["engineErrors"]
    wait_for(lambda: lease.counts["engineErrors"] >= before + 3, timeout=seconds + 20,
             what="three failed attempts")
    return lease.counts["engineErrors"] - before


def test_redis_down_at_start_costs_one_line_and_no_spin() -> None:
    port = free_port()  # nothing listens there
    with lease_on(port) as (lease, lines, _):
        thread = next(t for t in threading.enumerate() if t.name == "lease")
        cpu0, wall0 = thread_cpu(thread), time.monotonic()
        errors = errors_for(lease, 2.0)
        cpu = (thread_cpu(thread) - cpu0) / (time.monotonic() - wall0)
        assert not lease.check() and lease.deadline() == 0.0
        assert errors >= 3
        assert lines.count(UNREACHABLE) == 1, lines.lines  # one per kind and 10 s
        assert cpu < 0.05, cpu


def test_garbage_a_1gb_bulk_and_silence_lose_the_lease_safely_and_it_comes_back(
        tmp_path: Path) -> None:
    with RedisServer(tmp_path / "redis") as rds, FakeRedis(rds.port) as fake, \
            lease_on(fake.port) as (lease, lines, losses):
        wait_for(lease.check, timeout=20, what="the lease through the relay")
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        for mode in ("garbage", "huge", "silent"):
            fake.mode = mode
            for conn in list(fake.conns):  # the pool's connection is closed: a new one
                with contextlib.suppress(OSError):
                    conn.shutdown(socket.SHUT_RDWR)
            wait_for(lambda: not lease.check(), timeout=20, what=f"the lease lost ({mode})")
            lost_at, known_end = losses[-1]
            assert lost_at < known_end, (mode, lost_at, known_end)  # before its end
            assert lease.deadline() == 0.0
            errors_for(lease, 2.0)
            assert not lease.check()
            fake.mode = "relay"
            wait_for(lease.check, timeout=20, what=f"the lease again after {mode}")
        grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024
        assert grown_mb < 64, grown_mb  # the 1 GB bulk was never buffered
        assert lease.counts["gained"] == 4 and lease.counts["lost"] == 3
        assert lines.count(UNREACHABLE) <= 3, lines.lines  # one per kind of error
        assert lines.count("answers again") == 3
        assert all(len(line) < 400 for line in lines.lines)  # the garbage not quoted whole


def attempts(client: object) -> int:
    """Scripts Redis ran (the lease's attempts: EVALSHA, or EVAL the first time)."""
    stats = client.info("commandstats")  # type: ignore[attr-defined]
    return sum(int(stats.get(f"cmdstat_{name}", {}).get("calls", 0))
               for name in ("evalsha", "eval"))


def test_a_huge_value_under_the_lease_key_keeps_the_lease_away_without_cost(
        tmp_path: Path) -> None:
    with RedisServer(tmp_path / "redis") as rds:
        import redis as client

        other = client.Redis.from_url(rds.url)
        try:
            other.set("faults:leader", b"x" * (64 * 1024 * 1024))
            with lease_on(rds.port) as (lease, lines, _):
                rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
                calls0 = attempts(other)
                wait_for(lambda: attempts(other) >= calls0 + 3, timeout=20,
                         what="three attempts against the held key")
                assert not lease.check()
                assert lease.counts["engineErrors"] == 0 and lines.count(UNREACHABLE) == 0
                grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024
                assert grown_mb < 32, grown_mb  # the scripts compare in Redis
                other.delete("faults:leader")
                wait_for(lease.check, timeout=20, what="the lease once the key is gone")
        finally:
            other.close()
