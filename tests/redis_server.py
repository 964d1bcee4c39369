"""A real Redis for tests: Debian's ``redis-server`` on a free loopback port, its files
in a temporary folder (no persistence), like tests/mosquitto.py starts mosquitto.
`stop()` (SIGTERM, then SIGKILL) always reaps it.  Use it as a context manager."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from pathlib import Path

from tests.peers import free_port


class RedisError(RuntimeError):
    """redis-server could not be found or did not start."""


def redis_binary() -> str:
    """Path of redis-server; RedisError with an install hint if missing."""
    for path in ("/usr/bin/redis-server", "/usr/sbin/redis-server"):
        if os.access(path, os.X_OK):
            return path
    found = shutil.which("redis-server")
    if found:
        return found
    raise RedisError("redis-server is not installed: `apt-get install redis-server` "
                     "(make test does it)")


class RedisServer:
    """One redis-server on 127.0.0.1:`port` (chosen free at start; retried on a race)."""

    def __init__(self, tmp_dir: str | os.PathLike[str], start_timeout: float = 10.0) -> None:
        self.dir = Path(tmp_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.start_timeout = start_timeout
        self.port = 0
        self.proc: subprocess.Popen[bytes] | None = None
        self.log_path = self.dir / "redis.log"

    def __enter__(self) -> RedisServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> RedisServer:
        binary = redis_binary()
        for _attempt in range(3):
            port = free_port()
            with open(self.log_path, "ab") as log:
                self.proc = subprocess.Popen(
                    [binary, "--bind", "127.0.0.1", "--port", str(port), "--dir",
                     str(self.dir), "--save", "", "--appendonly", "no",
                     "--protected-mode", "yes", "--daemonize", "no"],
                    stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                    start_new_session=True)
            if self._wait_ready(port):
                self.port = port
                return self
            self.stop()
        raise RedisError(f"redis-server did not start; log:\n{self.log_text}")

    def _wait_ready(self, port: int) -> bool:
        deadline = time.monotonic() + self.start_timeout
        while time.monotonic() < deadline:
            if self.proc is None or self.proc.poll() is not None:
                return False
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.5) as sock:
                    sock.sendall(b"PING\r\n")
                    if sock.recv(16).startswith(b"+PONG"):
                        return True
            except OSError:
                pass
            time.sleep(0.05)  # poll: until it answers PING (deadline above)
        return False

    def stop(self, timeout: float = 5.0) -> None:
        proc, self.proc = self.proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
        proc.wait()

    @property
    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""
