"""A fleet of DTUs shared out over several processes: :class:`FleetProcesses` runs
``processes`` child processes (``python -c``, not forked: a gateway's threads stay out
of them), each a :class:`~edgemodbus.sim.fleet.DtuFleet` of its
own range of the DTUs' numbers, on its own event loop.

One asyncio loop serves a few thousand DTUs (each request is Python work on it), and one
process opens at most its hard ``RLIMIT_NOFILE`` sockets; a fleet of tens of thousands
needs both shared out.  The children take the fleet's options as given (``sources``
included: DTU ``n`` dials from ``sources[n % len(sources)]`` whichever child runs it)
and answer the parent over their stdin and stdout, a line each: their counters, their
CPU time, a reset of every connection (:meth:`FleetProcesses.reset_all`), stop.
"""

from __future__ import annotations

import contextlib
import json
import logging
import select
import subprocess
import sys
import time
from typing import IO, Any

from .dialling import check_sources
from .fleet import DtuFleet

log = logging.getLogger("edgemodbus.simulator")

_START_S = 120.0  # a child's import, fleet and first dial (a loaded machine)
_ANSWER_S = 60.0  # a child's answer to one command
_CHILD = "from edgemodbus.sim.fleet_procs import child_main; child_main()"


def _encode(options: dict[str, Any]) -> str:
    """The fleet's options as one JSON line (bytes as {"hex": ...})."""
    return json.dumps({k: {"hex": v.hex()} if isinstance(v, bytes) else v
                       for k, v in options.items()})


def _decode(line: str) -> dict[str, Any]:
    return {k: bytes.fromhex(v["hex"]) if isinstance(v, dict) else v
            for k, v in json.loads(line).items()}


def child_main() -> None:
    """A child (``python -c`` of :data:`_CHILD`): reads its fleet's settings, one JSON
    line, from stdin; runs the fleet on its thread; answers one line per command
    (``stats``: a JSON line of its counters and CPU seconds, ``reset``) until ``stop`` or
    the end of stdin."""
    logging.getLogger("edgemodbus").setLevel(logging.ERROR)
    settings = _decode(sys.stdin.readline())
    host, port, count = settings.pop("host"), settings.pop("port"), settings.pop("count")
    with DtuFleet(host, port, count, **settings) as fleet:
        print("dialling", flush=True)
        for line in sys.stdin:
            command = line.strip()
            if command == "stop":
                return
            if command == "reset":
                fleet.reset_all()
                print("reset", flush=True)
            else:  # "stats"
                print(json.dumps({"stats": fleet.stats(), "cpu": time.process_time()}),
                      flush=True)


def _read_line(proc: subprocess.Popen[str], timeout: float, what: str) -> str:
    out = proc.stdout
    assert out is not None
    poller = select.poll()  # not select(): a gateway's fds are past 1024
    poller.register(out, select.POLLIN)
    line = out.readline() if poller.poll(timeout * 1000) else ""
    if not line:
        raise RuntimeError(f"DTU fleet process {proc.pid} did not {what} (exit code "
                           f"{proc.poll()})")
    return line


class FleetProcesses:
    """``count`` DTUs numbered from ``first`` that dial ``host:port``, in ``processes``
    child processes (contiguous ranges of numbers; the first children take one more when
    the count does not divide).  ``options``: :class:`DtuFleet`'s keyword arguments
    (``registration`` as a template, not a function: the children are other programs).

    >>> with FleetProcesses("127.0.0.1", 9502, 20000, processes=4,      # doctest: +SKIP
    ...                     sources=loopback_sources(20000)) as fleet:
    ...     fleet.stats()["connected"]
    """

    def __init__(self, host: str, port: int, count: int, *, processes: int, first: int = 0,
                 **options: Any) -> None:
        if not isinstance(processes, int) or not 1 <= processes <= 256:
            raise ValueError(f"processes {processes!r}: must be an integer 1..256")
        if count < processes:
            raise ValueError(f"a fleet of {count} DTUs in {processes} processes: must be at "
                             "least one DTU per process")
        if callable(options.get("registration")):
            raise ValueError("registration: a template string (a function does not reach "
                             "the child processes)")
        check_sources(options.get("sources", ()), host)
        DtuFleet(host, port, 1, first=first, **options)  # the options checked here, once
        self.host, self.port, self.count = host, port, count
        share, extra = divmod(count, processes)
        self.shares: list[tuple[int, int]] = []  # (first number, count) per child
        at = first
        for k in range(processes):
            n = share + (k < extra)
            self.shares.append((at, n))
            at += n
        self._options = options
        self._children: list[subprocess.Popen[str]] = []

    def start(self) -> FleetProcesses:
        """Start the children and wait until each dials (RuntimeError when one does
        not start: every child is stopped)."""
        if self._children:
            return self
        try:
            for first, n in self.shares:
                proc = subprocess.Popen([sys.executable, "-c", _CHILD], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, text=True)
                self._children.append(proc)
                self._send(proc, _encode({**self._options, "host": self.host,
                                          "port": self.port, "count": n, "first": first}))
            for proc in self._children:
                _read_line(proc, _START_S, "start")
        except BaseException:
            self.stop()
            raise
        return self

    @staticmethod
    def _send(proc: subprocess.Popen[str], line: str) -> None:
        stdin: IO[str] | None = proc.stdin
        assert stdin is not None
        stdin.write(line + "\n")
        stdin.flush()

    def _ask(self, command: str) -> list[str]:
        for proc in self._children:
            self._send(proc, command)
        return [_read_line(proc, _ANSWER_S, f"answer {command!r}") for proc in self._children]

    def stats(self) -> dict[str, int]:
        """:meth:`DtuFleet.stats` summed over the children."""
        total: dict[str, int] = {}
        for line in self._ask("stats"):
            for key, value in json.loads(line)["stats"].items():
                total[key] = total.get(key, 0) + value
        return total

    def cpu_seconds(self) -> float:
        """The children's CPU time (user + system, all their threads) so far."""
        return float(sum(json.loads(line)["cpu"] for line in self._ask("stats")))

    def reset_all(self) -> None:
        """Every DTU's connection reset at once (:meth:`DtuFleet.reset_all`), in every
        child; returns when all are done."""
        self._ask("reset")

    def stop(self, timeout: float = 30.0) -> None:
        """Stop every child (each closes its connections) and reap it. Idempotent."""
        children, self._children = self._children, []
        for proc in children:
            with contextlib.suppress(OSError, ValueError):
                self._send(proc, "stop")
        deadline = time.monotonic() + timeout
        for proc in children:
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("DTU fleet process %d did not stop: killed", proc.pid)
                proc.kill()
                proc.wait(5.0)
            for pipe in (proc.stdin, proc.stdout):
                if pipe is not None:
                    with contextlib.suppress(OSError):
                        pipe.close()

    def __enter__(self) -> FleetProcesses:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


__all__ = ["FleetProcesses", "child_main"]
