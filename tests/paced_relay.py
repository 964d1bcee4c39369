"""A serial line at a real baud rate, made of ptys: two socat pty pairs and a relay process
between them that delivers each byte one character time after the previous one.

A pty passes bytes as fast as they are written, so a master reading a pty never waits
for the wire the way it does on a UART.  :class:`PacedLine` puts the wire back::

    master: line.master ~socat~ relay A <-relay-> relay B ~socat~ line.slave: slave

The relay (this module run as a script, in its own process so that its CPU is never
counted as the master's) reads whatever either side writes and puts it on ONE shared
wire timeline, as on a half-duplex RS-485 pair: a byte is delivered one character time
(start + data + parity + stop bits at the baud rate) after the previous byte on the wire
in either direction, or after it was written if the wire was idle.  Bytes are written in
the batches that are due, so a late wake-up of the relay delays but never reorders them.

Used by tests/integration/test_paced_line.py and by bench/test_bench_serial.py.
``PacedLine(tmp_dir, baudrate=9600)`` is a context manager; ``.master`` is the path the
master opens, ``.slave`` the one a serial slave opens.  With ``log_gaps=True`` the relay
also logs every turnaround on the wire, and :meth:`PacedLine.gaps` returns them: the
silence before each frame, from the last byte delivered to a side to the first byte that
side sends back (the master's inter-frame gap, the slave's response latency).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
import tty
from pathlib import Path
from typing import IO

if __package__ in (None, ""):  # run as a script: tests/ is not a package on sys.path
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tests.peers import PeerError, PtyPair, _die_with_parent

__all__ = ["PacedLine", "char_time"]

RELAY_SCRIPT = Path(__file__).resolve()


def char_time(baudrate: int, parity: str = "N", data_bits: int = 8, stop_bits: int = 1) -> float:
    """Seconds per character on the wire: start + data + parity + stop bits."""
    return (1 + data_bits + (0 if parity == "N" else 1) + stop_bits) / baudrate


class PacedLine:
    """Two socat pty pairs and the pacing relay between them (see the module doc)."""

    def __init__(self, directory: str | os.PathLike[str], baudrate: int = 9600, *,
                 parity: str = "N", data_bits: int = 8, stop_bits: int = 1,
                 timeout: float = 5.0, log_gaps: bool = False) -> None:
        self.directory = Path(directory)
        self._gap_log = self.directory / "relay-gaps.log" if log_gaps else None
        self.baudrate = baudrate
        self.char_time = char_time(baudrate, parity, data_bits, stop_bits)
        self.timeout = timeout
        self._master_pair = PtyPair(self.directory, "master", "relay-a", timeout)
        self._slave_pair = PtyPair(self.directory, "relay-b", "slave", timeout)
        self._proc: subprocess.Popen[bytes] | None = None
        self._log: IO[bytes] | None = None

    @property
    def master(self) -> str:
        """The path the master opens."""
        return self._master_pair.a

    @property
    def slave(self) -> str:
        """The path a serial slave opens."""
        return self._slave_pair.b

    def gaps(self, side: str) -> list[float]:
        """The turnarounds logged so far (``log_gaps=True``), oldest first, in seconds:
        for ``side`` "master" the silence the master kept between the last reply byte it
        got and its next request; for "slave", between a request and its reply.  As the
        relay sees them: its own wake-up latency (tens of us) is in the figures."""
        if self._gap_log is None:
            raise ValueError("PacedLine: gaps are logged only with log_gaps=True")
        if not self._gap_log.exists():
            return []
        gaps = []
        for line in self._gap_log.read_text().splitlines():
            who, _, seconds = line.partition(" ")
            if who == side and seconds:
                gaps.append(float(seconds))
        return gaps

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def __enter__(self) -> PacedLine:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> PacedLine:
        """Start both pty pairs and the relay; returns once the relay has opened its ends."""
        try:
            self._master_pair.start()
            self._slave_pair.start()
            self._log = tempfile.TemporaryFile(prefix="paced-relay-", suffix=".log")  # noqa: SIM115 - close()
            log = [] if self._gap_log is None else ["--gap-log", str(self._gap_log)]
            self._proc = subprocess.Popen(
                [sys.executable, str(RELAY_SCRIPT), "--char-time", repr(self.char_time),
                 *log, self._master_pair.b, self._slave_pair.a],
                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=self._log,
                start_new_session=True, preexec_fn=_die_with_parent,
            )
            assert self._proc.stdout is not None
            ready, _, _ = select.select([self._proc.stdout], [], [], self.timeout)
            line = self._proc.stdout.readline() if ready else b""
            if line.strip() != b"READY":
                raise PeerError(f"paced relay did not start: {line!r} {self._stderr()}")
        except BaseException:
            self.close()
            raise
        return self

    def _stderr(self) -> str:
        if self._log is None:
            return ""
        self._log.seek(0)
        return self._log.read().decode(errors="replace")

    def close(self) -> None:
        """Stop the relay and both pty pairs (idempotent)."""
        proc = self._proc
        if proc is not None:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(3.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            if proc.stdout is not None:
                proc.stdout.close()
            self._proc = None
        if self._log is not None:
            self._log.close()
            self._log = None
        self._slave_pair.close()
        self._master_pair.close()


# -- the relay process ------------------------------------------------------------------


def _open_raw(path: str) -> int:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    return fd


def relay(a: int, b: int, char: float, gap_log: IO[str] | None = None) -> None:
    """Move bytes between ``a`` and ``b`` on one wire timeline: each byte is written one
    character time after the previous byte on the wire (either direction) or after it
    arrived, whichever is later.  ``gap_log``: a line "master SECONDS" or "slave SECONDS"
    for every turnaround (bytes from a side that the last bytes on the idle wire went
    to), the time from their delivery to the new bytes' arrival."""
    other = {a: b, b: a}
    side = {a: "master", b: "slave"}
    wire: collections.deque[tuple[float, int, int]] = collections.deque()  # (due, fd, byte)
    wire_free = 0.0  # when the last byte queued is off the wire
    last_to, last_write = -1, 0.0  # where and when the last bytes were delivered
    while True:
        timeout = max(0.0, wire[0][0] - time.monotonic()) if wire else None
        readable, _, _ = select.select([a, b], [], [], timeout)
        now = time.monotonic()
        for fd in readable:
            try:
                data = os.read(fd, 4096)
            except BlockingIOError:
                continue
            except OSError:  # the other end of the pair went away (EIO): keep serving
                time.sleep(0.01)  # pacing: the pair's other end away: retry
                continue
            if gap_log is not None and data and not wire and last_to == fd:
                gap_log.write(f"{side[fd]} {now - last_write:.9f}\n")
            for byte in data:
                wire_free = max(now, wire_free) + char
                wire.append((wire_free, other[fd], byte))
        due: dict[int, bytearray] = {}
        now = time.monotonic()
        while wire and wire[0][0] <= now:
            _, fd, byte = wire.popleft()
            due.setdefault(fd, bytearray()).append(byte)
        for fd, chunk in due.items():
            with contextlib.suppress(BlockingIOError, OSError):
                os.write(fd, chunk)
            last_to, last_write = fd, time.monotonic()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="baud-paced relay between two ptys")
    parser.add_argument("--char-time", type=float, required=True, help="seconds per char")
    parser.add_argument("--gap-log", help="file that gets a line per turnaround on the wire")
    parser.add_argument("a")
    parser.add_argument("b")
    args = parser.parse_args(argv)

    def on_term(_sig: int, _frame: object) -> None:
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, on_term)
    a, b = _open_raw(args.a), _open_raw(args.b)
    gap_log = open(args.gap_log, "a", buffering=1) if args.gap_log else None  # noqa: SIM115
    try:
        sys.stdout.write("READY\n")
        sys.stdout.flush()
        relay(a, b, args.char_time, gap_log)
    finally:
        os.close(a)
        os.close(b)
        if gap_log is not None:
            gap_log.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
