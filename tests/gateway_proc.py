"""The gateway service through its public CLI (``python -m edgemodbus.gateway``) in a
child process, with an optional open-files limit, and what it costs as /proc sees it:
CPU (whole process, or the threads of one name), RSS, fds, threads; its log lines.

Used by tests/integration/test_fd_limit.py and tools/soak_gateway.py (issue #25).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import resource
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
_TICK = os.sysconf("SC_CLK_TCK")


def device_file(port: int, unit: int, code: str, tags: int = 3,
                read_cycle: int = 100) -> dict[str, Any]:
    """A device file polling ``tags`` holding registers of ``unit`` behind an
    RTU-over-TCP peer on 127.0.0.1:``port``."""
    return {
        "organization": {"deviceCode": code},
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
            "slaveId": unit, "readCycle": read_cycle, "readTimeout": 1000,
            "byteTimeout": 50, "retries": 0},
        "addressList": [{"name": f"t{i}", "address": f"hr:{i}", "deviceDataType": "UInt16"}
                        for i in range(tags)],
    }


def write_json(path: Path, data: Any) -> None:
    """Write atomically (as a config tool should), so a reload never sees half a file."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(data if isinstance(data, str) else json.dumps(data))
    tmp.replace(path)


def served(port: int, unit: int = 1, count: int = 3) -> bool:
    """A master (pymodbus) reads holding registers 0..count of ``unit`` from the
    gateway's Modbus TCP server on ``port`` and gets the peer's values (``unit``'s
    device file polls them from tests/peers.py's default registers)."""
    from pymodbus.client import ModbusTcpClient

    from tests.peers import default_register

    client = ModbusTcpClient("127.0.0.1", port=port, timeout=1, retries=0)
    try:
        if not client.connect():
            return False
        reply = client.read_holding_registers(0, count=count, device_id=unit)
        want = [default_register(unit, "hr", a) for a in range(count)]
        return not reply.isError() and list(reply.registers) == want
    except Exception:
        return False
    finally:
        client.close()


def scrape(port: int, timeout: float = 10.0) -> str:
    """The gateway's /metrics text."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=timeout) as resp:
        return str(resp.read().decode())


def nested_json(depth: int = 100_000) -> str:
    """A JSON document nested ``depth`` deep (a list in a list ...)."""
    return "[" * depth + "]" * depth


@dataclass(frozen=True)
class Usage:
    """One look at the child: CPU seconds (user + system) so far, of the process and of
    each thread (by its id: Python 3.11 does not give threads OS names, so a spinning
    thread is found as the busiest one); RSS in KiB; fds; threads."""

    at: float
    cpu: float
    thread_cpu: dict[int, float]
    rss_kib: int
    fds: int
    threads: int


class GatewayProcess:
    """``python -m edgemodbus.gateway --config-dir DIR`` in a child process, its output
    in ``log_path``; ``nofile`` > 0 sets its soft RLIMIT_NOFILE.  Always reaped."""

    def __init__(self, config_dir: Path, log_path: Path, *, nofile: int = 0,
                 extra: tuple[str, ...] = ()) -> None:
        self.config_dir = config_dir
        self.log_path = log_path
        self.nofile = nofile
        self.extra = extra
        self.proc: subprocess.Popen[bytes] | None = None

    def __enter__(self) -> GatewayProcess:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop("JOURNAL_STREAM", None)
        nofile = self.nofile

        def limit() -> None:  # in the child, before exec
            if nofile > 0:
                hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, hard))

        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "edgemodbus.gateway", "--config-dir",
                 str(self.config_dir), *self.extra],
                stdin=subprocess.DEVNULL, stdout=log, stderr=log, cwd=REPO, env=env,
                preexec_fn=limit)
        return self

    def __exit__(self, *exc: object) -> None:
        proc = self.proc
        if proc is not None and proc.poll() is None:
            proc.kill()
        if proc is not None:
            proc.wait()

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    @property
    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def lines(self, pattern: str) -> list[str]:
        return [ln for ln in self.log.splitlines() if re.search(pattern, ln)]

    def wait_log(self, pattern: str, timeout: float = 20.0, count: int = 1) -> str:
        """The ``count``-th line matching ``pattern``, waited for (the child must live)."""
        deadline = time.monotonic() + timeout
        while True:
            found = self.lines(pattern)
            if len(found) >= count:
                return found[count - 1]
            assert self.proc is not None
            if self.proc.poll() is not None:
                raise AssertionError(f"gateway exited ({self.proc.returncode}):\n{self.log}")
            if time.monotonic() > deadline:
                raise AssertionError(f"no log line /{pattern}/ x{count}; log:\n{self.log}")
            time.sleep(0.05)  # poll: the step of the log wait (deadline above)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal(self, signum: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(signum)

    def wait(self, timeout: float = 20.0) -> int:
        """The exit status, once the child ended."""
        assert self.proc is not None
        return self.proc.wait(timeout)

    def stop(self, timeout: float = 20.0) -> int:
        """SIGTERM, then the exit status."""
        self.signal(signal.SIGTERM)
        return self.wait(timeout)

    def usage(self) -> Usage:
        """CPU (of the process and per thread), RSS, fds and threads now."""
        base = f"/proc/{self.pid}"
        cpu = _cpu(f"{base}/stat")
        thread_cpu: dict[int, float] = {}
        tids = os.listdir(f"{base}/task")
        for tid in tids:
            with contextlib.suppress(OSError):  # (a thread that just ended)
                thread_cpu[int(tid)] = _cpu(f"{base}/task/{tid}/stat")
        rss = 0
        with open(f"{base}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    rss = int(line.split()[1])
        return Usage(time.monotonic(), cpu, thread_cpu, rss, len(os.listdir(f"{base}/fd")),
                     len(tids))


def _cpu(stat_path: str) -> float:
    with open(stat_path) as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICK  # utime, stime (man 5 proc)


def cpu_share(first: Usage, last: Usage) -> tuple[float, float]:
    """CPU seconds per second between two looks: (the process, its busiest thread)."""
    span = max(last.at - first.at, 1e-6)
    busiest = max((cpu - first.thread_cpu.get(tid, 0.0) for tid, cpu in
                   last.thread_cpu.items()), default=0.0)
    return (last.cpu - first.cpu) / span, busiest / span


@contextlib.contextmanager
def idle_connections(port: int, n: int, send: bytes = b"",
                     patience: float = 10.0) -> Iterator[list[socket.socket]]:
    """``n`` connections to 127.0.0.1:``port`` that send ``send`` (if anything) and then
    nothing, made without blocking (a full backlog must not stall the caller); those
    still connecting after ``patience`` seconds are kept as they are.  All closed after."""
    socks: list[socket.socket] = []
    try:
        for _ in range(n):
            sock = socket.socket()
            sock.setblocking(False)
            rc = sock.connect_ex(("127.0.0.1", port))
            if rc not in (0, errno.EINPROGRESS):
                sock.close()
                continue
            socks.append(sock)
        deadline = time.monotonic() + patience
        pending = list(socks)
        while pending and time.monotonic() < deadline:
            still = []
            for sock in pending:
                err = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
                try:
                    sock.getpeername()
                except OSError:
                    if err == 0:
                        still.append(sock)
                    continue
                if send:
                    with contextlib.suppress(OSError):
                        sock.send(send)
            pending = still
            if pending:
                time.sleep(0.02)  # poll: connecting until each is accepted or refused
        yield socks
    finally:
        for sock in socks:
            sock.close()
