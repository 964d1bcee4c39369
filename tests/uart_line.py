"""A serial line between UARTs at their own settings, for tests on ptys.

A pty carries bytes whatever baud rate and parity its ends are set to, so on a plain pty
pair a scan would find a slave at every setting.  :class:`UartLine` relays between a pty
that the master opens (:attr:`UartLine.path`) and the slave's serial device (one end of
a socat pty pair, or a simulator's pty), the slave's UART being at ``slave`` settings;
the master's settings are read from the pty as the master set them (``tcgetattr`` on
the pty's master side sees the slave side's termios on Linux; the pty driver clears
PARENB, so parity is read from INPCK, which libmodbus sets exactly when the parity is E
or O, and PARODD).  Bytes between equal settings pass untouched; between different ones
they go through :func:`resample`: what a UART receiving at one setting makes of the
characters sent at another (sampled in the middle of each bit, a falling edge starts a
character, only the first stop bit is checked; with parity checking on (INPCK), a
character with a parity or framing error is read as 0x00, as Linux does without PARMRK
and IGNPAR; without it, as read).

:meth:`UartLine.talk` adds something else talking on the line (another master's polls
at its own settings), heard by the master side.
"""

from __future__ import annotations

import contextlib
import os
import select
import termios
import threading
import time
import tty
from dataclasses import dataclass
from fractions import Fraction
from math import ceil, floor

_SPEEDS = {
    getattr(termios, f"B{b}"): b
    for b in (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400)
    if hasattr(termios, f"B{b}")
}
_HALF = Fraction(1, 2)


@dataclass(frozen=True)
class UartSettings:
    baudrate: int
    parity: str = "N"
    stop_bits: int = 1


def character_bits(data: bytes, s: UartSettings) -> list[int]:
    """Line levels, one per bit time: start 0, 8 data bits LSB first, parity, stop 1s."""
    out: list[int] = []
    for byte in data:
        bits = [(byte >> i) & 1 for i in range(8)]
        out += [0, *bits]
        if s.parity != "N":
            ones = sum(bits)
            out.append(ones % 2 if s.parity == "E" else (ones + 1) % 2)
        out += [1] * s.stop_bits
    return out


def resample(data: bytes, tx: UartSettings, rx: UartSettings) -> bytes:
    """What a UART at ``rx`` reads of ``data`` sent back to back at ``tx``."""
    if tx == rx:
        return data
    bits = character_bits(data, tx)
    n = len(bits)

    def level(t: Fraction) -> int:
        i = floor(t * tx.baudrate)
        return bits[i] if 0 <= i < n else 1  # idle high around the frame

    bit = Fraction(1, rx.baudrate)
    out = bytearray()
    t = Fraction(0)
    while True:
        i = ceil(t * tx.baudrate)  # the next falling edge: a tx bit boundary from t on
        while i < n and not (bits[i] == 0 and (i == 0 or bits[i - 1] == 1)):
            i += 1
        if i >= n:
            return bytes(out)
        t0 = Fraction(i, tx.baudrate)
        if level(t0 + _HALF * bit) != 0:  # a glitch, not a start bit
            t = t0 + _HALF * bit
            continue
        values = [level(t0 + (k + _HALF) * bit) for k in range(1, 9)]
        k = 9
        good = True
        if rx.parity != "N":
            ones = sum(values)
            want = ones % 2 if rx.parity == "E" else (ones + 1) % 2
            good = level(t0 + (k + _HALF) * bit) == want
            k += 1
        good = good and level(t0 + (k + _HALF) * bit) == 1
        value = sum(b << j for j, b in enumerate(values))
        out.append(value if good or rx.parity == "N" else 0)
        t = t0 + (k + _HALF) * bit


def pty_settings(fd: int) -> UartSettings | None:
    """The settings a program set on a pty, read through ``fd`` (either side)."""
    iflag, _oflag, cflag, _lflag, _ispeed, ospeed, _cc = termios.tcgetattr(fd)
    baud = _SPEEDS.get(ospeed)
    if baud is None:
        return None
    parity = "N" if not iflag & termios.INPCK else ("O" if cflag & termios.PARODD else "E")
    return UartSettings(baud, parity, 2 if cflag & termios.CSTOPB else 1)


class UartLine:
    """The relay (one thread); a context manager.  ``garbled``: chunks passed through
    :func:`resample` because the settings differed, per direction."""

    def __init__(self, device: str, slave: UartSettings) -> None:
        self.slave = slave
        self.garbled = {"to_slave": 0, "to_master": 0}
        self._talk: tuple[bytes, UartSettings, float] | None = None
        self._master, self._pty = os.openpty()  # the pty side stays open: no EIO between opens
        tty.setraw(self._pty)
        self.path = os.ttyname(self._pty)
        self._dev = os.open(device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        with contextlib.suppress(termios.error):
            tty.setraw(self._dev)
        self._wake_r, self._wake_w = os.pipe()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="test-uart-line", daemon=True)

    def __enter__(self) -> UartLine:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def talk(self, frame: bytes, settings: UartSettings, every: float) -> None:
        """Someone else sends ``frame`` at ``settings`` every ``every`` seconds."""
        self._talk = (frame, settings, every)
        os.write(self._wake_w, b"x")

    def close(self) -> None:
        self._stop = True
        os.write(self._wake_w, b"x")
        if self._thread.is_alive():
            self._thread.join(5)
        for fd in (self._master, self._pty, self._dev, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)

    def _run(self) -> None:
        next_talk = 0.0
        while not self._stop:
            wait = 0.5
            if self._talk is not None:
                now = time.monotonic()
                if now >= next_talk:
                    frame, settings, every = self._talk
                    master = pty_settings(self._master)
                    if master is not None:
                        os.write(self._master, resample(frame, settings, master))
                    next_talk = now + every
                wait = max(0.0, next_talk - time.monotonic())
            ready, _, _ = select.select([self._master, self._dev, self._wake_r], [], [], wait)
            for fd in ready:
                if fd == self._wake_r:
                    os.read(fd, 64)
                    continue
                try:
                    data = os.read(fd, 4096)
                except (BlockingIOError, InterruptedError):
                    continue
                if not data:
                    continue
                master = pty_settings(self._master) or self.slave
                if fd == self._master:
                    out, target, way = resample(data, master, self.slave), self._dev, "to_slave"
                else:
                    out, target, way = resample(data, self.slave, master), self._master, "to_master"
                if master != self.slave:
                    self.garbled[way] += 1
                if out:
                    os.write(target, out)
