"""Serial lines at their baud rate (tests/paced_relay.py: ptys with a relay that delivers
each byte one character time after the previous): correct values through the line
worker, the reader sleeping while a frame is on the wire (csrc/emb_io.c, emb_pace), and
the byte timeout still finding a frame that stops short or tolerating one that pauses."""

from __future__ import annotations

import os
import struct
import threading
import time
import tty
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from edgemodbus import _ffi
from edgemodbus.datatypes import Area
from edgemodbus.errors import ModbusTimeoutError
from edgemodbus.line.endpoint import LineTiming, SerialPort
from edgemodbus.line.worker import LineWorker
from edgemodbus.protocol import rtu
from tests.paced_relay import PacedLine
from tests.peers import PymodbusSlave, default_bit, default_register


@pytest.mark.parametrize("baudrate", [9600, 115200])
def test_reads_and_writes_through_a_paced_line(tmp_path: Path, baudrate: int) -> None:
    with PacedLine(tmp_path, baudrate) as line, PymodbusSlave(
        "serial", device=line.slave, baudrate=baudrate, units=(1, 2)
    ):
        worker = LineWorker(SerialPort(line.master, baudrate),
                            LineTiming(response_timeout=1.0, byte_timeout=0.3))
        worker.start()
        try:
            for unit in (1, 2):
                assert worker.read(unit, Area.HOLDING_REGISTER, 0, 125).result(5) == [
                    default_register(unit, "hr", a) for a in range(125)]
                assert worker.read(unit, Area.COIL, 5, 2000).result(5) == [
                    int(default_bit(unit, "co", a)) for a in range(5, 2005)]
            worker.write_registers(2, 40, [1, 2, 3]).result(5)
            assert worker.read(2, Area.HOLDING_REGISTER, 39, 5).result(5) == [
                default_register(2, "hr", 39), 1, 2, 3, default_register(2, "hr", 43)]
            assert worker.stats.timeouts == 0 and worker.stats.crc_errors == 0
        finally:
            worker.stop()


def _cpu_per_read(ctx: _ffi.Context, reads: int) -> float:
    start = time.process_time()
    for _ in range(reads):
        ctx.read(1, 3, 0, 125)
    return (time.process_time() - start) / reads


def test_pacing_saves_the_wake_up_per_byte(tmp_path: Path) -> None:
    """At 9600 baud a 255-byte reply takes 265 ms: read byte by byte it costs a poll()
    and a read() each; paced, a few.  The same line, the same reads, with and without
    the character time set: this process's CPU (the slave and relay are other
    processes)."""
    port = SerialPort(str(tmp_path / "master"), 9600)
    with PacedLine(tmp_path, 9600) as line, PymodbusSlave(
        "serial", device=line.slave, baudrate=9600, units=(1,)
    ):
        ctx = _ffi.Context.rtu(line.master, 9600, "N", 8, 1)
        try:
            ctx.connect()
            ctx.set_timeouts(1.0, 0.3)
            assert ctx.read(1, 3, 0, 125).to_list() == [default_register(1, "hr", a)
                                                         for a in range(125)]
            unpaced = paced = float("inf")
            for _ in range(3):  # alternated, the best of each: the machine is shared
                ctx.set_char_time(0.0)
                unpaced = min(unpaced, _cpu_per_read(ctx, 2))
                ctx.set_char_time(port.char_time)
                paced = min(paced, _cpu_per_read(ctx, 2))
            assert ctx.read(1, 3, 0, 125).to_list() == [default_register(1, "hr", a)
                                                         for a in range(125)]
        finally:
            ctx.close()
    assert paced < unpaced / 2, (paced, unpaced)


class FakeSlave:
    """The far end of a paced line played by hand: answers one request with ``chunks``
    of bytes, pausing ``pause`` seconds between them (a thread, joined by ``join``)."""

    def __init__(self, path: str, chunks: list[bytes], pause: float = 0.0) -> None:
        self._fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self._fd)
        self._chunks, self._pause = chunks, pause
        self.request = b""
        self._thread = threading.Thread(target=self._run, name="fake-serial-slave")
        self._thread.start()

    def _run(self) -> None:
        while len(self.request) < 8:  # an FC03 request
            self.request += os.read(self._fd, 8 - len(self.request))
        for i, chunk in enumerate(self._chunks):
            if i:
                time.sleep(self._pause)  # pacing: the chunks apart
            os.write(self._fd, chunk)

    def join(self) -> None:
        self._thread.join(5)
        os.close(self._fd)


REPLY_125 = rtu.frame(1, struct.pack(">BB125H", 3, 250, *range(125)))


@contextmanager
def paced_context(tmp_path: Path, baudrate: int,
                  byte_timeout: float) -> Iterator[tuple[PacedLine, _ffi.Context]]:
    with PacedLine(tmp_path, baudrate) as line:
        ctx = _ffi.Context.rtu(line.master, baudrate, "N", 8, 1)
        try:
            ctx.connect()
            ctx.set_timeouts(1.0, byte_timeout)
            ctx.set_char_time(line.char_time)
            yield line, ctx
        finally:
            ctx.close()


def test_a_reply_that_stops_short_is_found_one_byte_timeout_after_it_was_due(
    tmp_path: Path,
) -> None:
    """At 4800 baud the reply should take 530 ms on the wire; 20 of its 255 bytes come.
    The reader sleeps for the frame, finds it short, and gives up one byte timeout
    (50 ms) after the frame was due: not after sleeping again for the 235 missing bytes
    (490 ms more), and never before the frame could have been complete."""
    with paced_context(tmp_path, 4800, 0.05) as (line, ctx):
        frame_time = (8 + len(REPLY_125)) * line.char_time  # request and whole reply
        slave = FakeSlave(line.slave, [REPLY_125[:20]])
        started = time.monotonic()
        try:
            with pytest.raises(ModbusTimeoutError, match="incomplete reply"):
                ctx.read(1, 3, 0, 125)
            elapsed = time.monotonic() - started
        finally:
            slave.join()
    assert slave.request == rtu.frame(1, bytes.fromhex("030000007d"))  # FC03 @0+125
    assert frame_time + 0.04 < elapsed < frame_time + 0.05 + 0.3, (elapsed, frame_time)


@pytest.mark.parametrize("baudrate", [9600, 115200])
def test_a_reply_that_pauses_within_the_byte_timeout_is_read_whole(
    tmp_path: Path, baudrate: int
) -> None:
    """A slave that sends its reply in pieces with 50 ms pauses (under the 250 ms byte
    timeout): the reader, woken early by each pause, falls back to waiting a byte
    timeout for the next piece and gets the whole frame."""
    with paced_context(tmp_path, baudrate, 0.25) as (line, ctx):
        pieces = [REPLY_125[:3], REPLY_125[3:100], REPLY_125[100:101], REPLY_125[101:]]
        slave = FakeSlave(line.slave, pieces, pause=0.05)
        try:
            assert ctx.read(1, 3, 0, 125).to_list() == list(range(125))
        finally:
            slave.join()
