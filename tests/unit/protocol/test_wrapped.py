"""Wrapped report frames: the seed's examples, segmentation, and bad frames."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.protocol.wrapped import ReportParser, wrap

SINGLE = bytes.fromhex("FFAA0001010302030578B70D")
# the seed's batch report: 80 holding registers of slave 1 from address 1, as it prints them
BATCH_VALUES = [0] * 25 + [16384, 0, 0, 0, 3327, 924, 32, 0, -1, -1, 0, 110] + [0] * 29 + [
    250, 0, 0, 0, 0, -55, 16, 25, 30, 16, 25, 25, 87, 7]


def batch_frame() -> bytes:
    data = struct.pack(">80h", *BATCH_VALUES)
    return wrap(1, 1, bytes([3, len(data)]) + data)


def signed(regs: list[int]) -> list[int]:
    return [r - 0x10000 if r & 0x8000 else r for r in regs]


def test_seed_single_report() -> None:
    parser = ReportParser()
    (report,) = parser.feed(SINGLE)
    assert (report.address, report.slave, report.function) == (1, 1, 3)
    assert report.registers == [773]
    assert parser.frames == 1 and parser.dropped == 0


def test_seed_batch_report() -> None:
    assert len(BATCH_VALUES) == 80
    (report,) = ReportParser().feed(batch_frame())
    assert (report.address, report.slave, report.function) == (1, 1, 3)
    assert signed(report.registers) == BATCH_VALUES


def test_wrap_builds_the_seed_frame() -> None:
    assert wrap(1, 1, bytes.fromhex("03020305")) == SINGLE


def test_split_over_segments_and_packed_together() -> None:
    parser = ReportParser()
    stream = SINGLE + batch_frame() + SINGLE
    got = []
    for i in range(len(stream)):
        got += parser.feed(stream[i:i + 1])
    assert [r.registers[0] for r in got] == [773, 0, 773]
    assert len(ReportParser().feed(stream)) == 3


@pytest.mark.parametrize(
    "bad",
    [
        bytes.fromhex("FFAB0001010302030578B70D"),  # bad header
        bytes.fromhex("FFAA0001010302030578B70E"),  # bad tail
        bytes.fromhex("FFAA0001010302030578B80D"),  # bad CRC
        bytes.fromhex("FFAA000101030303050078B70D"),  # odd byte count: length does not add up
        bytes.fromhex("FFAA0001014102030578B70D"),  # unknown function code
    ],
)
def test_bad_frames_are_dropped_and_parsing_resumes(bad: bytes, caplog) -> None:
    parser = ReportParser()
    reports = parser.feed(bad + SINGLE)
    assert [r.registers for r in reports] == [[773]]
    assert parser.dropped == 1  # one bad frame, one drop (its rest is not noise)
    assert any("FF" in rec.getMessage() for rec in caplog.records)


NOISE = [bytes.fromhex("FFAB0001010302030578B70D"), bytes.fromhex("0013")]  # no FF AA
BAD_CRC = bytes.fromhex("FFAA0001010302030578B80D")  # its end is known: length and tail agree
END_UNKNOWN = [
    bytes.fromhex("FFAA0001010302030578B70E"),  # bad tail
    bytes.fromhex("FFAA000101030303050078B70D"),  # odd byte count
    bytes.fromhex("FFAA0001014102030578B70D"),  # unknown function code
]


def expected_drops(pieces: list[bytes]) -> int:
    """One drop per bad frame, and per run of noise that is not the rest of a bad frame
    whose end was unknown (those bytes up to the next header belong to it)."""
    drops, absorbing = 0, False
    for piece in pieces:
        if piece == SINGLE:
            absorbing = False
        elif piece == BAD_CRC:
            drops, absorbing = drops + 1, False
        elif piece in END_UNKNOWN or not absorbing:  # a bad frame, or noise starting a run
            drops, absorbing = drops + 1, True
    return drops


@settings(max_examples=300, deadline=None)
@given(pieces=st.lists(st.sampled_from([SINGLE, BAD_CRC, *END_UNKNOWN, *NOISE]),
                       min_size=1, max_size=6),
       cuts=st.lists(st.integers(min_value=0, max_value=80), max_size=8))
def test_each_bad_frame_or_noise_run_is_one_drop_however_split(
        pieces: list[bytes], cuts: list[int]) -> None:
    """Good frames, bad frames and noise in any order and TCP segmentation: every good
    frame comes through, and each bad frame or run of noise is counted exactly once."""
    stream = b"".join(pieces)
    parser = ReportParser()
    got = []
    start = 0
    for cut in [*sorted({min(c, len(stream)) for c in cuts}), len(stream)]:
        got += parser.feed(stream[start:cut])
        start = cut
    assert [r.raw for r in got] == [p for p in pieces if p == SINGLE]
    assert parser.dropped == expected_drops(pieces)


def test_heartbeats_are_discarded_and_counted() -> None:
    parser = ReportParser(heartbeat=b"HB")
    reports = parser.feed(b"HB" + SINGLE + b"H")
    reports += parser.feed(b"B" + SINGLE)
    assert len(reports) == 2
    assert parser.heartbeats == 2 and parser.dropped == 0


def test_write_echo_and_exception() -> None:
    echo = wrap(7, 1, bytes.fromhex("0600070102"))
    exc = wrap(7, 1, bytes.fromhex("8602"))
    reports = ReportParser().feed(echo + exc)
    assert reports[0].function == 6 and reports[0].data == bytes.fromhex("00070102")
    assert reports[1].exception_code == 2
