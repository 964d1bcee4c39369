"""Frame-level tests of the RTU slave simulator.

The master side here is deliberately independent of edgemodbus: raw sockets (and a raw
pty), request frames and a bitwise CRC-16/MODBUS written in this file, and replies read
the way a master would (length from the header).
"""

from __future__ import annotations

import contextlib
import math
import os
import resource
import select
import signal
import socket
import struct
import subprocess
import sys
import termios
import threading
import time
import tty
from collections.abc import Iterator

import pytest

from edgemodbus.datatypes import Area
from edgemodbus.sim import (
    CounterMover,
    FloatSineMover,
    RandomWalkMover,
    Simulator,
    SineMover,
    default_bit,
    default_register,
    main,
)

QUIET = 0.12  # how long "no reply" is waited for (the simulator answers in < 5 ms)
HR, IR, COIL, DI = Area.HOLDING_REGISTER, Area.INPUT_REGISTER, Area.COIL, Area.DISCRETE_INPUT


# --- an independent little master: CRC, frames, replies -------------------------------


def crc16(data: bytes) -> int:
    """CRC-16/MODBUS, bit by bit (Modbus over Serial Line v1.02, 6.2.2)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def frame(slave: int, pdu: bytes) -> bytes:
    body = bytes([slave]) + pdu
    crc = crc16(body)
    return body + bytes([crc & 0xFF, crc >> 8])


def crc_ok(adu: bytes) -> bool:
    return len(adu) >= 4 and crc16(adu[:-2]) == adu[-2] | adu[-1] << 8


def read_req(fc: int, address: int, count: int) -> bytes:
    return struct.pack(">BHH", fc, address, count)


def test_crc_reference_vector() -> None:
    # Serial Line v1.02 appendix B example style: 01 03 00 00 00 0A -> C5 CD.
    assert frame(1, bytes.fromhex("030000000a"))[-2:] == bytes.fromhex("c5cd")


class Client:
    """A raw TCP master connection."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=2.0)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def close(self) -> None:
        self.sock.close()

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def recv_exact(self, n: int, timeout: float = 1.0) -> bytes:
        out = b""
        deadline = time.monotonic() + timeout
        while len(out) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"got {out.hex()} of {n} bytes")
            self.sock.settimeout(left)
            chunk = self.sock.recv(n - len(out))
            if not chunk:
                raise ConnectionError(f"closed after {out.hex()}")
            out += chunk
        self.sock.settimeout(2.0)
        return out

    def recv_quiet(self, quiet: float = QUIET) -> bytes:
        """Everything that arrives until ``quiet`` seconds pass without a byte."""
        out = b""
        while True:
            ready, _, _ = select.select([self.sock], [], [], quiet)
            if not ready:
                return out
            chunk = self.sock.recv(4096)
            if not chunk:
                return out
            out += chunk

    def read_reply(self, timeout: float = 1.0) -> bytes:
        """One reply ADU, its length taken from its header as a master does."""
        head = self.recv_exact(2, timeout)
        fc = head[1]
        if fc & 0x80:
            rest = self.recv_exact(3, timeout)
        elif fc in (1, 2, 3, 4):
            count = self.recv_exact(1, timeout)
            rest = count + self.recv_exact(count[0] + 2, timeout)
        elif fc in (5, 6, 15, 16):
            rest = self.recv_exact(6, timeout)
        elif fc == 0x16:
            rest = self.recv_exact(8, timeout)
        else:
            raise AssertionError(f"unexpected function {fc:#x}")
        return head + rest

    def ask(self, slave: int, pdu: bytes) -> bytes:
        """Send a request, return the reply PDU after checking address and CRC."""
        self.send(frame(slave, pdu))
        adu = self.read_reply()
        assert crc_ok(adu), adu.hex()
        assert adu[0] == slave
        return adu[1:-2]

    def expect_silence(self, wait: float = QUIET) -> None:
        assert self.recv_quiet(wait) == b""


@pytest.fixture
def sim() -> Iterator[Simulator]:
    s = Simulator(slaves=[1, 2, 3], size=10_000, seed=7)
    try:
        yield s
    finally:
        s.stop()


@pytest.fixture
def port(sim: Simulator) -> int:
    return sim.serve_tcp("127.0.0.1", 0)


@pytest.fixture
def conn(port: int) -> Iterator[Client]:
    c = Client(port)
    try:
        yield c
    finally:
        c.close()


def regs_of(pdu: bytes) -> list[int]:
    assert pdu[1] == len(pdu) - 2
    return list(struct.unpack(f">{pdu[1] // 2}H", pdu[2:]))


def bits_of(pdu: bytes, count: int) -> list[bool]:
    assert pdu[1] == (count + 7) // 8
    return [bool(pdu[2 + i // 8] >> (i % 8) & 1) for i in range(count)]


# --- defaults and function codes ------------------------------------------------------


def test_default_values_derive_from_address() -> None:
    assert default_register(2, 10) == 2010
    assert default_register(70, 5) == (70_005 & 0xFFFF)
    assert default_bit(1, 1) is True
    assert default_bit(1, 0) is False
    assert default_bit(2, 0) is True


def test_fc03_fc04_read_registers(conn: Client) -> None:
    assert regs_of(conn.ask(2, read_req(3, 100, 3))) == [2100, 2101, 2102]
    assert regs_of(conn.ask(3, read_req(4, 7, 2))) == [3007, 3008]
    full = conn.ask(1, read_req(3, 9875, 125))  # the largest legal read, to the last address
    assert regs_of(full) == [default_register(1, a) for a in range(9875, 10_000)]


def test_fc01_fc02_read_bits(conn: Client) -> None:
    pdu = conn.ask(1, read_req(1, 3, 10))
    assert pdu[0] == 1
    assert bits_of(pdu, 10) == [default_bit(1, a) for a in range(3, 13)]
    # Padding bits of the last byte are zero (Application Protocol 6.1).
    assert pdu[3] >> 2 == 0
    pdu = conn.ask(2, read_req(2, 0, 2000))
    assert bits_of(pdu, 2000) == [default_bit(2, a) for a in range(2000)]


def test_fc05_write_coil(sim: Simulator, conn: Client) -> None:
    req = struct.pack(">BHH", 5, 1, 0xFF00)  # coil 1 of slave 2 starts False
    assert conn.ask(2, req) == req  # echo
    assert sim.slave(2).get_bits(COIL, 1) == [True]
    off = struct.pack(">BHH", 5, 1, 0x0000)
    assert conn.ask(2, off) == off
    assert sim.slave(2).get_bits(COIL, 0, 3) == [True, False, True]
    assert conn.ask(2, struct.pack(">BHH", 5, 1, 0x1234)) == bytes([0x85, 0x03])


def test_fc06_write_register(sim: Simulator, conn: Client) -> None:
    req = struct.pack(">BHH", 6, 42, 0xBEEF)
    assert conn.ask(1, req) == req
    assert sim.slave(1).get_registers(HR, 41, 3) == [1041, 0xBEEF, 1043]
    assert sim.slave(2).get_registers(HR, 42) == [2042]  # other slaves untouched


def test_fc15_write_coils(sim: Simulator, conn: Client) -> None:
    values = [True, True, False, True, False, False, True, False, True, True]
    packed = bytes([0b01001011, 0b11])
    req = struct.pack(">BHHB", 15, 20, len(values), 2) + packed
    assert conn.ask(3, req) == struct.pack(">BHH", 15, 20, 10)
    assert sim.slave(3).get_bits(COIL, 20, 10) == values
    assert bits_of(conn.ask(3, read_req(1, 20, 10)), 10) == values


def test_fc16_write_registers(sim: Simulator, conn: Client) -> None:
    req = struct.pack(">BHHB3H", 16, 500, 3, 6, 1, 0x8000, 0xFFFF)
    assert conn.ask(1, req) == struct.pack(">BHH", 16, 500, 3)
    assert sim.slave(1).get_registers(HR, 500, 3) == [1, 0x8000, 0xFFFF]
    assert regs_of(conn.ask(1, read_req(3, 499, 5))) == [1499, 1, 0x8000, 0xFFFF, 1503]


def test_fc22_mask_write(sim: Simulator, conn: Client) -> None:
    # The example of Application Protocol 6.16: current 0x12, AND 0xF2, OR 0x25 -> 0x17.
    sim.slave(1).set_registers(HR, 4, [0x12])
    req = struct.pack(">BHHH", 0x16, 4, 0x00F2, 0x0025)
    assert conn.ask(1, req) == req
    assert sim.slave(1).get_registers(HR, 4) == [0x17]


def test_unsupported_function_is_exception_01(conn: Client) -> None:
    # FC07 (read exception status) has no length we know: the frame ends by silence.
    assert conn.ask(1, bytes([0x07])) == bytes([0x87, 0x01])
    assert conn.ask(2, bytes([0x2B, 0x0E, 0x01, 0x00])) == bytes([0xAB, 0x01])


@pytest.mark.parametrize(
    ("pdu", "code"),
    [
        (read_req(3, 9999, 2), 2),  # runs past the last register
        (read_req(4, 10_000, 1), 2),
        (read_req(1, 9990, 11), 2),
        (struct.pack(">BHH", 6, 10_000, 1), 2),
        (struct.pack(">BHHH", 0x16, 12_000, 0, 0), 2),
        (read_req(3, 0, 0), 3),  # quantity 0
        (read_req(3, 0, 126), 3),  # > 125 registers
        (read_req(4, 0, 126), 3),
        (read_req(1, 0, 2001), 3),  # > 2000 bits
        (read_req(2, 0, 0), 3),
        (struct.pack(">BHHB2H", 16, 0, 3, 4, 1, 2), 3),  # byte count != 2 * quantity
        (struct.pack(">BHHBB", 15, 0, 9, 1, 0xFF), 3),  # 9 coils need 2 bytes
        (struct.pack(">BHHB", 16, 0, 0, 0), 3),  # quantity 0
    ],
)
def test_exceptions_02_03(conn: Client, pdu: bytes, code: int) -> None:
    assert conn.ask(1, pdu) == bytes([pdu[0] | 0x80, code])


def test_size_is_configurable() -> None:
    with Simulator(slaves=[5], size=100) as sim:
        c = Client(sim.serve_tcp())
        try:
            assert regs_of(c.ask(5, read_req(3, 98, 2))) == [5098, 5099]
            assert c.ask(5, read_req(3, 99, 2)) == bytes([0x83, 0x02])
        finally:
            c.close()
        with pytest.raises(IndexError):
            sim.slave(5).get_registers(HR, 100)


def test_unknown_slave_is_silent_and_line_recovers(sim: Simulator, conn: Client) -> None:
    conn.send(frame(9, read_req(3, 0, 1)))
    conn.expect_silence()
    assert regs_of(conn.ask(3, read_req(3, 0, 1))) == [3000]
    assert sim.stats()["line"]["unknown_slave"] == 1


def test_broadcast_write_executed_by_all_never_answered(sim: Simulator, conn: Client) -> None:
    conn.send(frame(0, struct.pack(">BHH", 6, 7, 777)))
    conn.expect_silence()
    for s in (1, 2, 3):
        assert sim.slave(s).get_registers(HR, 7) == [777]
    conn.send(frame(0, struct.pack(">BHHB2H", 16, 8, 2, 4, 5, 6)))
    conn.expect_silence()
    assert sim.slave(2).get_registers(HR, 8, 2) == [5, 6]
    conn.send(frame(0, read_req(3, 0, 1)))  # broadcast reads are ignored
    conn.expect_silence()
    stats = sim.stats()
    assert stats["line"]["broadcasts"] == 3
    assert stats["slaves"][1]["broadcasts"] == 2
    assert stats["slaves"][1]["replies"] == 0


# --- framing: garbage, bad CRC, split and back-to-back requests -----------------------


def test_bad_crc_request_is_ignored(sim: Simulator, conn: Client) -> None:
    bad = bytearray(frame(1, read_req(3, 0, 1)))
    bad[-1] ^= 0xFF
    conn.send(bytes(bad))
    conn.expect_silence()
    assert regs_of(conn.ask(1, read_req(3, 1, 1))) == [1001]
    assert sim.stats()["line"]["discarded_bytes"] >= 8


@pytest.mark.parametrize(
    "garbage", [b"\xff\xfe", b"\x01\x03\x00", b"\x01\x10\x00\x00\x00\x01\xff", b"\x05\x55"]
)
def test_garbage_before_request_is_skipped(conn: Client, garbage: bytes) -> None:
    conn.send(garbage + frame(2, read_req(3, 5, 1)))
    assert regs_of(_reply_pdu(conn, 2)) == [2005]


def _reply_pdu(conn: Client, slave: int) -> bytes:
    adu = conn.read_reply()
    assert crc_ok(adu)
    assert adu[0] == slave
    return adu[1:-2]


def test_request_in_pieces_and_back_to_back(sim: Simulator) -> None:
    # A generous idle time, so that a loaded machine cannot turn the pause into silence.
    conn = Client(sim.serve_tcp(silence=0.5))
    try:
        req = frame(1, read_req(3, 10, 1))
        conn.send(req[:3])
        time.sleep(0.02)  # pacing: the request in two pieces
        conn.send(req[3:])
        assert regs_of(_reply_pdu(conn, 1)) == [1010]
        conn.send(frame(1, read_req(3, 11, 1)) + frame(2, read_req(3, 12, 1)))
        assert regs_of(_reply_pdu(conn, 1)) == [1011]
        assert regs_of(_reply_pdu(conn, 2)) == [2012]
    finally:
        conn.close()


def test_several_clients_at_once(port: int) -> None:
    clients = [Client(port) for _ in range(3)]
    try:
        for i, c in enumerate(clients):
            c.send(frame(i + 1, read_req(3, i, 1)))
        for i, c in enumerate(clients):
            assert regs_of(_reply_pdu(c, i + 1)) == [default_register(i + 1, i)]
    finally:
        for c in clients:
            c.close()


# --- data access and movers -----------------------------------------------------------


def test_set_get_from_the_test_side(sim: Simulator, conn: Client) -> None:
    s1 = sim.slave(1)
    s1.set_registers(HR, 100, [1, 2, -1])
    s1.set_registers(IR, 100, [9])
    s1.set_bits(DI, 5, [True, True, False])
    s1.set_float32(HR, 200, 1.5)
    assert regs_of(conn.ask(1, read_req(3, 100, 3))) == [1, 2, 0xFFFF]
    assert regs_of(conn.ask(1, read_req(4, 100, 1))) == [9]
    assert bits_of(conn.ask(1, read_req(2, 5, 3)), 3) == [True, True, False]
    assert regs_of(conn.ask(1, read_req(3, 200, 2))) == [0x3FC0, 0x0000]
    with pytest.raises(ValueError):
        s1.set_registers(HR, 0, [0x10000])
    with pytest.raises(ValueError):
        s1.set_bits(HR, 0, [True])
    with pytest.raises(IndexError):
        s1.set_registers(HR, 9999, [1, 2])


def test_mover_values_from_elapsed_time() -> None:
    counter = CounterMover(area=HR, address=0, registers=2, interval_ms=100, step=3, start=10)
    assert counter.values(0.0) == [10, 11]
    assert counter.values(0.25) == [16, 17]
    sine = SineMover(area=IR, address=0, period_s=4.0, amplitude=1000)
    assert sine.values(0.0) == [0]
    assert sine.values(1.0) == [1000]
    assert sine.values(3.0) == [(-1000) & 0xFFFF]
    fsine = FloatSineMover(area=HR, address=0, period_s=4.0, amplitude=2.5, offset=10.0)
    hi, lo = fsine.values(1.0)
    assert struct.unpack(">f", struct.pack(">HH", hi, lo))[0] == 12.5
    walk_a = RandomWalkMover(address=0, registers=2, step=5, low=-20, high=20, seed=3)
    walk_b = RandomWalkMover(address=0, registers=2, step=5, low=-20, high=20, seed=3)
    seq_a = [walk_a.values(t * 0.5) for t in range(40)]
    assert seq_a == [walk_b.values(t * 0.5) for t in range(40)]
    signed = {v - 0x10000 if v & 0x8000 else v for pair in seq_a for v in pair}
    assert signed <= set(range(-20, 21, 5)) and len(signed) > 1
    with pytest.raises(ValueError):
        CounterMover(area=COIL)


def test_movers_on_the_wire(sim: Simulator, conn: Client) -> None:
    s2 = sim.slave(2)
    s2.add_mover(CounterMover(area=HR, address=10, interval_ms=40))
    s2.add_mover(FloatSineMover(area=IR, address=20, period_s=1.0, amplitude=5.0, offset=50.0))
    first = regs_of(conn.ask(2, read_req(3, 9, 3)))
    assert first[0] == 2009 and first[2] == 2011  # neighbours keep their defaults
    time.sleep(0.13)  # pacing: the 40 ms mover steps at least twice
    second = regs_of(conn.ask(2, read_req(3, 10, 1)))
    assert second[0] - first[1] >= 2
    hi_lo = regs_of(conn.ask(2, read_req(4, 20, 2)))
    value = struct.unpack(">f", struct.pack(">2H", *hi_lo))[0]
    assert 45.0 <= value <= 55.0 and not math.isnan(value)
    s2.clear_movers()
    frozen = s2.get_registers(HR, 10)
    time.sleep(0.05)  # pacing: a window in which nothing may move
    assert s2.get_registers(HR, 10) == frozen


# --- fault knobs ----------------------------------------------------------------------


def test_fault_silent(sim: Simulator, conn: Client) -> None:
    sim.slave(2).faults.silent = True
    conn.send(frame(2, struct.pack(">BHH", 6, 0, 5)))
    conn.expect_silence()
    assert sim.slave(2).get_registers(HR, 0) == [2000]  # not executed either
    assert regs_of(conn.ask(1, read_req(3, 0, 1))) == [1000]
    assert sim.stats()["slaves"][2]["faults"] == {"silent": 1}


def test_fault_drop_every(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.drop_every = 2
    answered = []
    for i in range(4):
        conn.send(frame(1, struct.pack(">BHH", 6, i, 100 + i)))
        answered.append(conn.recv_quiet() != b"")
    assert answered == [True, False, True, False]
    # Dropped replies were still executed.
    assert sim.slave(1).get_registers(HR, 0, 4) == [100, 101, 102, 103]
    st = sim.stats()["slaves"][1]
    assert st["faults"]["drop_every"] == 2 and st["replies"] == 2 and st["requests"] == 4


def test_fault_delay_does_not_block_other_connections(sim: Simulator, port: int) -> None:
    sim.slave(1).faults.delay = 0.5
    slow, fast = Client(port), Client(port)
    try:
        t0 = time.monotonic()
        slow.send(frame(1, read_req(3, 0, 1)))
        assert regs_of(fast.ask(2, read_req(3, 0, 1))) == [2000]
        assert time.monotonic() - t0 < 0.4
        assert slow.recv_quiet(0.0) == b""  # not yet
        assert regs_of(_reply_pdu(slow, 1)) == [1000]
        assert time.monotonic() - t0 >= 0.49
    finally:
        slow.close()
        fast.close()


def test_fault_corrupt_crc(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.corrupt_crc_every = 1
    conn.send(frame(1, read_req(3, 0, 2)))
    adu = conn.read_reply()
    assert not crc_ok(adu)
    assert adu[:-2] == bytes([1, 3, 4]) + struct.pack(">2H", 1000, 1001)


def test_fault_corrupt_data_keeps_original_crc(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.corrupt_data_every = 2
    assert regs_of(conn.ask(1, read_req(3, 0, 2))) == [1000, 1001]  # 1st: fine
    conn.send(frame(1, read_req(3, 0, 2)))
    adu = bytearray(conn.read_reply())
    assert not crc_ok(bytes(adu))
    assert adu[:-2] != bytes([1, 3, 4]) + struct.pack(">2H", 1000, 1001)
    adu[-3] ^= 0x01  # undo the one flipped bit: the CRC was the original one
    assert crc_ok(bytes(adu))


def test_fault_wrong_byte_count_with_valid_crc(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.wrong_byte_count_every = 1
    pdu = conn.ask(1, read_req(3, 0, 3))  # CRC checked by ask()
    assert pdu[1] == 4 and regs_of(pdu) == [1000, 1001]
    pdu = conn.ask(1, read_req(3, 0, 1))
    assert pdu[1] == 4  # one register asked, two returned
    pdu = conn.ask(1, read_req(1, 0, 8))
    assert pdu[1] == 2
    write = struct.pack(">BHH", 6, 0, 1)
    assert conn.ask(1, write) == write  # not applicable to write echoes


def test_fault_answer_as(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.answer_as = 9
    conn.send(frame(1, read_req(3, 0, 1)))
    adu = conn.read_reply()
    assert crc_ok(adu)
    assert adu[0] == 9 and regs_of(adu[1:-2]) == [1000]


def test_fault_exception_ranges(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.exception_ranges = [(HR, 100, 110, 4), (COIL, 0, 1, 2)]
    assert regs_of(conn.ask(1, read_req(3, 95, 5))) == list(range(1095, 1100))
    assert conn.ask(1, read_req(3, 99, 2)) == bytes([0x83, 4])
    assert conn.ask(1, read_req(3, 109, 1)) == bytes([0x83, 4])
    assert conn.ask(1, struct.pack(">BHH", 6, 105, 1)) == bytes([0x86, 4])
    assert regs_of(conn.ask(1, read_req(3, 110, 1))) == [1110]
    assert regs_of(conn.ask(1, read_req(4, 100, 1))) == [1100]  # other area
    assert conn.ask(1, struct.pack(">BHH", 5, 0, 0xFF00)) == bytes([0x85, 2])
    assert sim.stats()["slaves"][1]["exceptions"] == 3 + 1


def test_fault_close_every(sim: Simulator, port: int) -> None:
    sim.slave(1).faults.close_every = 2
    first = Client(port)
    try:
        assert regs_of(first.ask(1, read_req(3, 0, 1))) == [1000]
        first.send(frame(1, read_req(3, 0, 1)))
        first.sock.settimeout(1.0)
        assert first.sock.recv(16) == b""  # closed by the simulator, no reply
    finally:
        first.close()
    second = Client(port)
    try:
        assert regs_of(second.ask(1, read_req(3, 1, 1))) == [1001]
    finally:
        second.close()
    assert sim.stats()["slaves"][1]["faults"]["close_every"] == 1


def test_fault_trailing_garbage_and_noise_before(sim: Simulator, conn: Client) -> None:
    good = frame(1, struct.pack(">BHH", 6, 3, 3))
    sim.slave(1).faults.trailing_garbage = b"\xde\xad"
    conn.send(good)
    assert conn.recv_quiet() == good + b"\xde\xad"
    sim.slave(1).set_faults(trailing_garbage=b"", noise_before=b"\x00\xff\x00")
    conn.send(good)
    assert conn.recv_quiet() == b"\x00\xff\x00" + good


def test_fault_split_reply(sim: Simulator, conn: Client) -> None:
    sim.slave(1).set_faults(split_reply=3, split_pause=0.06)
    good = frame(1, struct.pack(">BHH", 6, 3, 3))
    t0 = time.monotonic()
    conn.send(good)
    first = conn.sock.recv(64)
    assert 0 < len(first) < len(good)
    rest = conn.recv_exact(len(good) - len(first))
    assert first + rest == good
    assert time.monotonic() - t0 >= 0.11


def test_fault_byte_delay(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.byte_delay = 0.015
    good = frame(1, struct.pack(">BHH", 6, 3, 3))
    t0 = time.monotonic()
    conn.send(good)
    assert len(conn.sock.recv(64)) == 1
    assert conn.recv_exact(7) == good[1:]
    assert time.monotonic() - t0 >= 7 * 0.015 - 0.005


def test_fault_truncate_every(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.truncate_every = 1
    good = frame(1, struct.pack(">BHH", 6, 3, 3))
    conn.send(good)
    assert conn.recv_quiet() == good[:4]


def test_fault_echo_request(sim: Simulator, conn: Client) -> None:
    sim.slave(2).faults.echo_request = True
    req = frame(2, read_req(3, 0, 1))
    conn.send(req)
    assert conn.recv_exact(len(req)) == req
    assert regs_of(_reply_pdu(conn, 2)) == [2000]


def test_fault_random_reply_count(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.random_reply_count = 2
    req = frame(1, read_req(3, 0, 1))
    good = frame(1, bytes([3, 2]) + struct.pack(">H", 1000))
    for _ in range(2):
        conn.send(req)
        junk = conn.recv_quiet()
        assert junk and junk != good and not (junk[:1] == b"\x01" and crc_ok(junk))
    assert sim.slave(1).faults.random_reply_count == 0
    assert regs_of(conn.ask(1, read_req(3, 0, 1))) == [1000]


def test_fault_exception_for_other_function(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.exception_for_other_function = True
    pdu = conn.ask(1, read_req(3, 0, 1))
    assert pdu[0] & 0x80 and pdu[0] != 0x83 and len(pdu) == 2
    pdu = conn.ask(1, read_req(4, 0, 1))
    assert pdu[0] & 0x80 and pdu[0] != 0x84


def test_fault_answer_broadcast(sim: Simulator, conn: Client) -> None:
    sim.slave(2).faults.answer_broadcast = True
    req = struct.pack(">BHH", 6, 1, 11)
    conn.send(frame(0, req))
    assert conn.read_reply() == frame(2, req)
    conn.expect_silence()  # only slave 2 misbehaves
    assert sim.slave(3).get_registers(HR, 1) == [11]


def test_fault_refused_functions(sim: Simulator, conn: Client) -> None:
    sim.slave(1).faults.refused_functions = frozenset({16, 0x16})
    req = struct.pack(">BHHB2H", 16, 0, 2, 4, 5, 6)
    assert conn.ask(1, req) == bytes([0x90, 0x01])
    assert conn.ask(1, struct.pack(">BHHH", 0x16, 0, 0, 0)) == bytes([0x96, 0x01])
    assert sim.slave(1).get_registers(HR, 0, 2) == [1000, 1001]  # not executed
    write = struct.pack(">BHH", 6, 0, 5)
    assert conn.ask(1, write) == write  # other functions still work
    assert conn.ask(2, req) == struct.pack(">BHH", 16, 0, 2)  # other slaves unaffected
    assert sim.stats()["slaves"][1]["faults"]["refused_functions"] == 2


def test_faults_clear_and_unknown_knob(sim: Simulator, conn: Client) -> None:
    s1 = sim.slave(1)
    s1.set_faults(silent=True, delay=5.0, exception_ranges=[(HR, 0, 1, 4)])
    s1.faults.clear()
    assert regs_of(conn.ask(1, read_req(3, 0, 1))) == [1000]
    with pytest.raises(AttributeError):
        s1.set_faults(no_such_knob=1)
    with pytest.raises(AttributeError):
        s1.faults.no_such_knob = 1  # type: ignore[attr-defined]


def test_stats(sim: Simulator, conn: Client) -> None:
    conn.ask(1, read_req(3, 0, 1))
    conn.ask(1, read_req(3, 0, 0))
    conn.send(frame(0, struct.pack(">BHH", 6, 1, 1)))
    conn.expect_silence(0.05)
    stats = sim.stats()
    assert stats["line"] == {
        "frames": 3,
        "discarded_bytes": 0,
        "unknown_slave": 0,
        "broadcasts": 1,
        "connections": 1,
    }
    assert stats["slaves"][1] == {
        "requests": 2,
        "replies": 2,
        "exceptions": 1,
        "broadcasts": 1,
        "faults": {},
    }


def test_on_request_sees_every_frame_when_it_arrived(sim: Simulator, conn: Client) -> None:
    seen: list[tuple[float, bytes]] = []
    sim.on_request = lambda at, raw: seen.append((at, raw))
    sim.slave(1).faults.delay = 0.1
    write = frame(1, struct.pack(">BHH", 6, 7, 77))
    t0 = time.monotonic()
    conn.send(write)
    assert conn.read_reply()[1] == 6
    t1 = time.monotonic()
    conn.send(frame(9, read_req(3, 0, 1)))  # nobody has address 9: still reported
    conn.expect_silence(0.05)
    assert [raw for _, raw in seen] == [write, frame(9, read_req(3, 0, 1))]
    # the arrival, not the (delayed) reply: well before the reply came back
    assert t0 <= seen[0][0] <= t1 - 0.09
    assert t1 <= seen[1][0]
    sim.on_request = None
    conn.ask(1, read_req(3, 0, 1))
    assert len(seen) == 2


def test_add_and_remove_slave_while_serving(sim: Simulator, conn: Client) -> None:
    sim.add_slave(40)
    assert regs_of(conn.ask(40, read_req(3, 1, 1))) == [40_001]
    sim.remove_slave(40)
    conn.send(frame(40, read_req(3, 1, 1)))
    conn.expect_silence()
    with pytest.raises(ValueError):
        sim.add_slave(1)
    with pytest.raises(ValueError):
        sim.add_slave(248)


# --- pty ------------------------------------------------------------------------------


def _pty_read(fd: int, n: int, timeout: float = 1.0) -> bytes:
    out = b""
    deadline = time.monotonic() + timeout
    while len(out) < n:
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            break
        chunk = os.read(fd, n - len(out))
        if not chunk:  # hangup: the simulator's side is gone
            raise ConnectionError("pty hung up")
        out += chunk
    return out


def test_pty_serves_raw_rtu(sim: Simulator) -> None:
    path = sim.serve_pty()
    assert path.startswith("/dev/pts/") and sim.pty_paths == [path]
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        lflag = termios.tcgetattr(fd)[3]
        assert not lflag & (termios.ICANON | termios.ECHO | termios.ISIG)  # raw already
        tty.setraw(fd)
        # Bytes a line discipline would eat or translate (0x0D, 0x11, 0x13, 0x7F).
        sim.slave(3).set_registers(HR, 0, [0x0D11, 0x137F])
        os.write(fd, frame(3, read_req(3, 0, 2)))
        adu = _pty_read(fd, 9)
        assert crc_ok(adu) and adu[:5] == bytes([3, 3, 4, 0x0D, 0x11])
        sim.slave(3).faults.close_every = 1  # cannot close a pty: the request is dropped
        os.write(fd, frame(3, read_req(3, 0, 1)))
        assert _pty_read(fd, 1, QUIET) == b""
        sim.slave(3).faults.clear()
        os.write(fd, b"\xf0\x0f" + frame(3, bytes([0x07])))  # garbage + unknown FC
        assert _pty_read(fd, 5) == frame(3, bytes([0x87, 0x01]))
    finally:
        os.close(fd)
    # The line survives its client going away; a new one is served.
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        tty.setraw(fd)
        os.write(fd, frame(1, read_req(4, 2, 1)))
        assert _pty_read(fd, 7) == frame(1, bytes([4, 2]) + struct.pack(">H", 1002))
    finally:
        os.close(fd)


# --- lifecycle ------------------------------------------------------------------------


def _fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


def _sim_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "edgemodbus-simulator"]


def test_stop_leaves_no_thread_or_fd() -> None:
    before = _fds()
    sim = Simulator(slaves=[1])
    port = sim.serve_tcp()
    sim.serve_pty()
    sim.slave(1).faults.delay = 5.0  # a reply still pending at stop()
    c = Client(port)
    try:
        c.send(frame(1, read_req(3, 0, 1)))
        time.sleep(0.05)  # pacing: the request sent before stop()
        assert len(_sim_threads()) == 1
        sim.stop()
        c.sock.settimeout(1.0)
        assert c.sock.recv(16) == b""  # the simulator's end is closed
    finally:
        c.close()
    assert _sim_threads() == []
    assert _fds() == before
    sim.stop()  # idempotent
    with pytest.raises(RuntimeError):
        sim.serve_tcp()
    with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.5):
        pytest.fail("listener still open")


def test_context_manager_and_never_started() -> None:
    before = _fds()
    with Simulator(slaves=[1, 2]) as sim:
        c = Client(sim.serve_tcp())
        try:
            assert regs_of(c.ask(2, read_req(3, 0, 1))) == [2000]
            assert sim.disconnect_clients() == 1
            c.sock.settimeout(1.0)
            assert c.sock.recv(16) == b""
        finally:
            c.close()
    Simulator().stop()  # never started: nothing to do
    assert _sim_threads() == []
    assert _fds() == before


def test_idle_simulator_uses_no_cpu(sim: Simulator, conn: Client) -> None:
    assert regs_of(conn.ask(1, read_req(3, 0, 1))) == [1000]
    sim.serve_pty()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    time.sleep(0.5)  # pacing: the window measured
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    used = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    assert used < 0.05


# --- command line ---------------------------------------------------------------------


def test_main_serves_until_sigterm() -> None:
    code = "import sys; from edgemodbus.sim import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "--port", "0", "--slaves", "1,4-5", "--movers"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().split()
        assert line[0] == "tcp" and line[1].startswith("127.0.0.1:")
        c = Client(int(line[1].rsplit(":", 1)[1]))
        try:
            assert regs_of(c.ask(5, read_req(3, 10, 1))) == [5010]
            c.send(frame(2, read_req(3, 10, 1)))  # not in 1,4-5
            c.expect_silence()
        finally:
            c.close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


def test_main_reports_a_busy_port(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        assert main(["--port", str(port)]) == 2  # docs/command-line.md, "Exit codes"
    assert capsys.readouterr().err == (f"edgemodbus simulate: --host 127.0.0.1 --port {port}: "
                                       f"cannot listen on 127.0.0.1:{port}: Address already "
                                       "in use\n")
