"""CRC-16/MODBUS of csrc/emb_util.c (``emb_crc16``, table-driven) against two independent
implementations: the bit-by-bit algorithm of Modbus over Serial Line v1.02, 6.2.2, written
here, and pymodbus's RTU framer's CRC; on random frames of every length an RTU ADU may
have, and on the published check values."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.framer.rtu import FramerRTU

from edgemodbus._ffi import check
from edgemodbus._ffi.native import MAX_ADU_LENGTH


def crc_bitwise(frame: bytes) -> int:
    """6.2.2: load 0xFFFF, xor each byte into the low half, then eight times: shift right,
    xor 0xA001 when the bit shifted out was 1."""
    crc = 0xFFFF
    for byte in frame:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


@pytest.mark.parametrize(("frame", "crc"), [
    (b"", 0xFFFF),
    (b"123456789", 0x4B37),  # the catalogue check value of CRC-16/MODBUS
    (bytes.fromhex("01 03 00 00 00 0A"), 0xCDC5),  # on the wire: C5 CD
    (bytes.fromhex("11 03 00 6B 00 03"), 0x8776),  # slave 17 reads 3 at 0x6B: 76 87
])
def test_known_values(frame: bytes, crc: int) -> None:
    assert check.crc16(frame) == crc
    assert crc_bitwise(frame) == crc


@settings(max_examples=400, deadline=None)
@given(st.binary(min_size=0, max_size=MAX_ADU_LENGTH))
def test_table_matches_bitwise_and_pymodbus(frame: bytes) -> None:
    got = check.crc16(frame)
    assert got == crc_bitwise(frame)
    # pymodbus sends the CRC high byte first in its int: swap to compare registers
    theirs = FramerRTU.compute_CRC(frame)
    assert got == ((theirs & 0xFF) << 8 | theirs >> 8)


def test_a_frame_with_its_crc_checks_to_zero() -> None:
    """Appending the CRC low byte first leaves a register of 0 (how a receiver checks)."""
    frame = bytes(range(40))
    crc = check.crc16(frame)
    assert check.crc16(frame + bytes([crc & 0xFF, crc >> 8])) == 0


def test_too_long_is_refused_by_name() -> None:
    too_long = rf"crc16: a frame of {MAX_ADU_LENGTH + 1} bytes; at most {MAX_ADU_LENGTH}"
    with pytest.raises(ValueError, match=too_long):
        check.crc16(bytes(MAX_ADU_LENGTH + 1))
