"""A real TCP load balancer for tests: Debian's ``haproxy`` in the foreground (``-db``)
with a config taken from docs/deploy.md (the block the page documents), its addresses
and ports replaced by 127.0.0.1 ones.  ``stop()`` (SIGTERM, then SIGKILL) always reaps
it; use it as a context manager."""

from __future__ import annotations

import re
import resource
import shutil
import socket
import subprocess
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "docs" / "deploy.md"


def documented_config() -> str:
    """The ```haproxy block of docs/deploy.md."""
    found = re.search(r"```haproxy\n(.*?)```", DEPLOY.read_text(), re.S)
    assert found, "docs/deploy.md has no ```haproxy block"
    return found.group(1)


def local_config(frontend: int, servers: list[int]) -> str:
    """The documented config with the frontend on 127.0.0.1:``frontend`` and the k-th
    ``server`` line at 127.0.0.1:``servers[k]`` (as many servers as the page has), and
    ``maxconn`` within this machine's open-files limit (two descriptors a connection)."""
    text = re.sub(r"(?m)^(\s*bind )\S+", rf"\g<1>127.0.0.1:{frontend}", documented_config())
    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    if hard != resource.RLIM_INFINITY:
        text = re.sub(r"(?m)^(\s*maxconn )(\d+)",
                      lambda m: f"{m.group(1)}{min(int(m.group(2)), (hard - 200) // 2)}", text)
    lines = re.findall(r"(?m)^\s*server \S+ \S+", text)
    assert len(lines) == len(servers), f"docs/deploy.md has {len(lines)} servers"
    for line, port in zip(lines, servers, strict=True):
        name = line.split()[1]
        text = text.replace(line, f"    server {name} 127.0.0.1:{port}", 1)
    return text


class HAProxy:
    """haproxy -db -f CONFIG as a child process, ready when its frontend accepts."""

    def __init__(self, config: str, path: Path, frontend: int) -> None:
        binary = shutil.which("haproxy") or "/usr/sbin/haproxy"
        if not Path(binary).exists():
            raise RuntimeError("haproxy not installed: apt-get install haproxy (make does)")
        path.write_text(config)
        self.frontend = frontend
        self.log_path = path.with_suffix(".log")
        check = subprocess.run([binary, "-c", "-f", str(path)], capture_output=True,
                               text=True, check=False)
        assert check.returncode == 0, f"haproxy -c: {check.stdout}{check.stderr}"
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen([binary, "-db", "-f", str(path)],
                                         stdin=subprocess.DEVNULL, stdout=log, stderr=log)

    def __enter__(self) -> HAProxy:
        deadline = time.monotonic() + 15
        while True:
            assert self.proc.poll() is None, f"haproxy exited: {self.log}"
            try:
                socket.create_connection(("127.0.0.1", self.frontend), timeout=1).close()
                return self
            except OSError:
                if time.monotonic() > deadline:
                    self.stop()
                    raise AssertionError(f"haproxy did not listen: {self.log}") from None
                time.sleep(0.05)  # poll: until haproxy listens (deadline above)

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self.proc.wait()
