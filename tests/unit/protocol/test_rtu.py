"""protocol.rtu: CRC-16/MODBUS against published vectors and a bitwise reference,
frame/crc_ok, request and reply lengths, and the request splitter on streams cut at
random places."""

from __future__ import annotations

import itertools
import struct
from collections.abc import Callable

import pytest
from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.protocol import rtu

# (frame without CRC, CRC as sent: low byte first)
VECTORS = [
    ("01 03 00 00 00 0A", "C5 CD"),  # read 10 holding registers of slave 1
    ("01 03 00 00 00 01", "84 0A"),
    ("11 03 00 6B 00 03", "76 87"),  # slave 17, the request of Application Protocol 6.3
    ("01 06 00 01 00 03", "98 0B"),
    ("31 32 33 34 35 36 37 38 39", "37 4B"),  # "123456789": the catalogue check 0x4B37
    ("", "FF FF"),  # nothing: the initial value
]


def bitwise_crc16(data: bytes) -> int:
    """CRC-16/MODBUS one bit at a time, as Serial Line 6.2.2 describes it."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


@pytest.mark.parametrize(("body", "crc"), VECTORS)
def test_crc16_known_vectors(body: str, crc: str) -> None:
    data = bytes.fromhex(body)
    assert struct.pack("<H", rtu.crc16(data)) == bytes.fromhex(crc)
    assert struct.pack("<H", rtu.crc16(bytearray(data))) == bytes.fromhex(crc)
    assert struct.pack("<H", rtu.crc16(memoryview(data))) == bytes.fromhex(crc)


def test_frame_appends_the_crc_low_byte_first() -> None:
    assert rtu.frame(1, bytes.fromhex("03 00 00 00 0A")) == bytes.fromhex("01 03 00 00 00 0A C5 CD")
    assert rtu.crc_ok(bytes.fromhex("01 03 00 00 00 0A C5 CD"))
    assert not rtu.crc_ok(bytes.fromhex("01 03 00 00 00 0A CD C5"))  # bytes swapped


@pytest.mark.parametrize("slave", [-1, 256, 1000])
def test_frame_refuses_an_address_that_is_not_one_byte(slave: int) -> None:
    with pytest.raises(ValueError, match=rf"slave address {slave}: must be 0\.\.255"):
        rtu.frame(slave, b"\x03\x00\x00\x00\x01")


@pytest.mark.parametrize("short", [b"", b"\x01", b"\xff\xff", b"\x01\x7e\x80"])
def test_crc_ok_needs_address_function_and_crc(short: bytes) -> None:
    # b"\x01\x7e\x80" ends in the CRC of b"\x01" but is too short to be a frame
    assert not rtu.crc_ok(short)


@given(st.binary(max_size=300))
def test_crc16_matches_the_bitwise_definition(data: bytes) -> None:
    assert rtu.crc16(data) == bitwise_crc16(data)


@given(st.integers(0, 255), st.binary(min_size=1, max_size=253), st.data())
def test_a_frame_checks_and_any_flipped_bit_breaks_it(
    slave: int, pdu: bytes, data: st.DataObject
) -> None:
    framed = rtu.frame(slave, pdu)
    assert len(framed) == len(pdu) + 3
    assert framed[0] == slave and framed[1:-2] == pdu
    assert rtu.crc_ok(framed)
    bit = data.draw(st.integers(0, 8 * len(framed) - 1), label="bit")
    broken = bytearray(framed)
    broken[bit // 8] ^= 1 << (bit % 8)
    assert not rtu.crc_ok(broken)


# --- lengths --------------------------------------------------------------------------

u16 = st.integers(0, 0xFFFF)
slaves = st.integers(0, rtu.MAX_SLAVE_ID)


@st.composite
def request_pdus(draw: st.DrawFn) -> bytes:
    """A well-formed request PDU of every function code whose length the PDU fixes."""
    fc = draw(st.sampled_from([1, 2, 3, 4, 5, 6, 15, 16, 22]))
    if fc in (1, 2, 3, 4, 5, 6):
        return struct.pack(">BHH", fc, draw(u16), draw(u16))
    if fc == 22:
        return struct.pack(">BHHH", fc, draw(u16), draw(u16), draw(u16))
    if fc == 15:
        n = draw(st.integers(1, 1968))
        packed = draw(st.binary(min_size=(n + 7) // 8, max_size=(n + 7) // 8))
        return struct.pack(">BHHB", fc, draw(u16), n, len(packed)) + packed
    values = draw(st.lists(u16, min_size=1, max_size=123))
    n = len(values)
    return struct.pack(f">BHHB{n}H", fc, draw(u16), n, 2 * n, *values)


@st.composite
def reply_pdus(draw: st.DrawFn) -> bytes:
    """A reply PDU: a read reply with its data, a write echo, or an exception."""
    kind = draw(st.sampled_from(["read", "write", "mask", "exception"]))
    if kind == "read":
        data = draw(st.binary(max_size=250))
        return bytes([draw(st.integers(1, 4)), len(data)]) + data
    if kind == "write":
        return struct.pack(">BHH", draw(st.sampled_from([5, 6, 15, 16])), draw(u16), draw(u16))
    if kind == "mask":
        return struct.pack(">BHHH", 22, draw(u16), draw(u16), draw(u16))
    return bytes([0x80 | draw(st.integers(1, 0x7F)), draw(st.integers(1, 11))])


def header_size(length_of: Callable[[bytes], int], framed: bytes) -> int:
    """The shortest prefix of ``framed`` whose length is known."""
    return next(n for n in range(len(framed) + 1) if length_of(framed[:n]) != rtu.NEED_MORE)


@given(slaves, request_pdus(), st.binary(max_size=5), st.binary(max_size=5))
def test_request_length_is_the_frame_length(
    slave: int, pdu: bytes, before: bytes, after: bytes
) -> None:
    framed = rtu.frame(slave, pdu)
    buf = before + framed + after
    assert rtu.request_length(buf, len(before)) == len(framed)
    assert header_size(rtu.request_length, framed) in (2, 7)
    for n in range(header_size(rtu.request_length, framed), len(framed) + 1):
        assert rtu.request_length(framed[:n]) == len(framed)  # later bytes do not matter


@given(slaves, reply_pdus(), st.binary(max_size=5), st.binary(max_size=5))
def test_reply_length_is_the_frame_length(
    slave: int, pdu: bytes, before: bytes, after: bytes
) -> None:
    framed = rtu.frame(slave, pdu)
    buf = before + framed + after
    assert rtu.reply_length(buf, len(before)) == len(framed)
    assert header_size(rtu.reply_length, framed) in (2, 3)
    for n in range(header_size(rtu.reply_length, framed), len(framed) + 1):
        assert rtu.reply_length(framed[:n]) == len(framed)


@pytest.mark.parametrize("fc", [0, 7, 8, 0x11, 0x17, 0x2B, 0x7F])
def test_other_function_codes_have_no_known_length(fc: int) -> None:
    assert rtu.request_length(bytes([1, fc, 0, 0, 0, 0, 0, 0])) == rtu.UNKNOWN
    assert rtu.reply_length(bytes([1, fc, 0, 0, 0, 0, 0, 0])) == rtu.UNKNOWN
    assert rtu.reply_length(bytes([1, fc | 0x80, 2, 0, 0])) == 5


def test_pack_bits_packs_the_example_of_application_protocol_6_1() -> None:
    # coils 20..38: CD 6B 05, coil 20 in the low bit of the first byte, the rest zero-padded
    bits = [(byte >> i) & 1 for byte in bytes.fromhex("CD 6B 05") for i in range(8)][:19]
    assert rtu.pack_bits(bits) == bytes.fromhex("CD 6B 05")


@given(st.lists(st.booleans(), max_size=2000))
def test_pack_bits_round_trips_bools_ints_and_bytes(bits: list[bool]) -> None:
    packed = rtu.pack_bits(bits)
    assert len(packed) == (len(bits) + 7) // 8
    assert [(packed[i // 8] >> (i % 8)) & 1 for i in range(len(bits))] == [int(b) for b in bits]
    if len(bits) % 8:  # the padding of the last byte is zero
        assert packed[-1] >> (len(bits) % 8) == 0
    as_ints = [int(b) for b in bits]
    assert rtu.pack_bits(as_ints) == rtu.pack_bits(bytes(as_ints)) == packed
    assert rtu.pack_bits(bytearray(as_ints)) == packed


def test_function_code_sets() -> None:
    assert {1, 2, 3, 4} == rtu.READ_FUNCTIONS
    assert {5, 6, 15, 16, 22} == rtu.WRITE_FUNCTIONS


# --- the splitter ---------------------------------------------------------------------

requests = st.builds(rtu.frame, slaves, request_pdus())
garbage = st.binary(min_size=1, max_size=6).map(
    lambda b: bytes(rtu.MAX_SLAVE_ID + 1 + x % (255 - rtu.MAX_SLAVE_ID) for x in b)
)


def feed(stream: bytes, cuts: list[int]) -> tuple[list[bytes], int, bytearray]:
    """Feed ``stream`` in the pieces ``cuts`` makes, as the simulator does with what each
    recv() brings: split without idle after each piece, then once idle at the end."""
    buf = bytearray()
    out: list[bytes] = []
    discarded = 0
    bounds = [0, *sorted(set(cuts)), len(stream)]
    for lo, hi in itertools.pairwise(bounds):
        buf += stream[lo:hi]
        frames, consumed, dropped = rtu.split_frames(buf, idle=False)
        del buf[:consumed]
        out += frames
        discarded += dropped
    frames, consumed, dropped = rtu.split_frames(buf, idle=True)
    del buf[:consumed]
    return out + frames, discarded + dropped, buf


@given(st.lists(requests, min_size=1, max_size=8), st.data())
def test_split_frames_recovers_concatenated_frames_cut_anywhere(
    frames: list[bytes], data: st.DataObject
) -> None:
    stream = b"".join(frames)
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=12), label="cuts")
    out, discarded, rest = feed(stream, cuts)
    assert out == frames
    assert discarded == 0
    assert not rest


@given(st.lists(st.tuples(garbage, requests), min_size=1, max_size=6), st.data())
def test_split_frames_skips_reserved_addresses_between_frames(
    pieces: list[tuple[bytes, bytes]], data: st.DataObject
) -> None:
    """Bytes 248..255 cannot start a frame: they are dropped and every frame survives."""
    stream = b"".join(noise + framed for noise, framed in pieces)
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=12), label="cuts")
    out, discarded, rest = feed(stream, cuts)
    assert out == [framed for _, framed in pieces]
    assert discarded == sum(len(noise) for noise, _ in pieces)
    assert not rest


def test_split_frames_keeps_an_incomplete_frame_until_idle() -> None:
    framed = rtu.frame(1, bytes.fromhex("03 00 00 00 0A"))
    buf = bytearray(framed[:-1])
    assert rtu.split_frames(buf, idle=False) == ([], 0, 0)
    assert rtu.split_frames(buf, idle=True) == ([], len(buf), len(buf))  # t3.5: it is dead


def test_split_frames_takes_a_frame_of_unknown_length_when_idle() -> None:
    framed = rtu.frame(1, bytes.fromhex("2B 0E 01 00"))  # read device identification
    assert rtu.split_frames(bytearray(framed), idle=False) == ([], 0, 0)
    assert rtu.split_frames(bytearray(framed), idle=True) == ([framed], len(framed), 0)


def test_find_known_frame_looks_past_garbage() -> None:
    framed = rtu.frame(1, bytes.fromhex("03 00 00 00 0A"))
    buf = bytearray(b"\x01\x2b\x00" + framed)
    assert rtu.find_known_frame(buf, 1) == 3
    assert rtu.find_known_frame(buf[:-1], 1) == -1  # incomplete: not found
    frames, consumed, discarded = rtu.split_frames(buf, idle=False)
    assert frames == [framed] and consumed == len(buf) and discarded == 3


@pytest.mark.parametrize("reserved", range(rtu.MAX_SLAVE_ID + 1, 256))
def test_split_frames_drops_a_frame_to_a_reserved_address(reserved: int) -> None:
    bad = rtu.frame(reserved, bytes.fromhex("03 00 00 00 0A"))
    good = rtu.frame(1, bytes.fromhex("03 00 00 00 0A"))
    for idle in (False, True):
        frames, consumed, discarded = rtu.split_frames(bytearray(bad + good), idle)
        assert frames == [good]
        assert (consumed, discarded) == (len(bad + good), len(bad))
