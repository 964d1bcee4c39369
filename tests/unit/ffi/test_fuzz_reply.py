"""Fuzz our own frame handling in Python with hypothesis (replies are framed and checked
in C, the C codec and reply handling have their libFuzzer harnesses in csrc/fuzz/).

* ``Link._check_write_reply``: the write-echo check libmodbus 3.1.6 does not do, fed the
  reply ADU of a real write request (RTU and Modbus TCP) mutated or replaced by random
  bytes.  It must raise only :class:`ModbusError` subclasses, accept exactly the correct
  echo, and turn exactly the well-formed exception replies into their typed exception.
* The simulator's request framing (``protocol.rtu.split_frames``) and request handling
  (``Slave._handle``): random byte streams with real requests in them never raise, every
  frame cut out has a valid CRC and lies where the consumed bytes say.

The example count is bounded: EDGEMODBUS_FUZZ_EXAMPLES (default 200) per test, so
`make test` stays quick; `make fuzz` raises it.
"""

from __future__ import annotations

import os
import random
import struct

from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from edgemodbus.errors import ModbusError, ModbusExceptionResponse, ProtocolError
from edgemodbus.line.link import Link
from edgemodbus.protocol import rtu
from edgemodbus.sim import Slave

EXAMPLES = int(os.environ.get("EDGEMODBUS_FUZZ_EXAMPLES", "200"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

u16 = st.integers(0, 0xFFFF)
units = st.integers(1, 247)


@st.composite
def write_pdus(draw: st.DrawFn) -> bytes:
    """A write request PDU as link.Link builds it (FC05, 06, 15, 16, 22)."""
    fc = draw(st.sampled_from([5, 6, 15, 16, 22]))
    address = draw(u16)
    if fc == 5:
        return struct.pack(">BHH", 5, address, draw(st.sampled_from([0, 0xFF00])))
    if fc == 6:
        return struct.pack(">BHH", 6, address, draw(u16))
    if fc == 22:
        return struct.pack(">BHHH", 22, address, draw(u16), draw(u16))
    if fc == 15:
        n = draw(st.integers(1, 1968))
        packed = draw(st.binary(min_size=(n + 7) // 8, max_size=(n + 7) // 8))
        return struct.pack(">BHHB", 15, address, n, len(packed)) + packed
    values = draw(st.lists(u16, min_size=1, max_size=123))
    n = len(values)
    return struct.pack(f">BHHB{n}H", 16, address, n, 2 * n, *values)


def echo_of(pdu: bytes) -> bytes:
    """The reply PDU a correct slave sends to a write request."""
    return pdu[: 7 if pdu[0] == 22 else 5]


def wrap(mbap: bool, unit: int, reply: bytes, tid: int = 1, proto: int = 0,
         length: int | None = None, crc: bytes = b"\x00\x00") -> bytes:
    """An ADU as libmodbus hands it over: MBAP header + unit + PDU, or unit + PDU + CRC
    (libmodbus has checked the CRC already; the checker ignores it)."""
    body = bytes([unit & 0xFF]) + reply
    if mbap:
        return struct.pack(">HHH", tid, proto, len(body) if length is None else length) + body
    return body + crc


@st.composite
def replies(draw: st.DrawFn, mbap: bool, slave: int, pdu: bytes) -> bytes:
    """The correct reply, a mutation of it, an exception reply, or random bytes."""
    good = echo_of(pdu)
    kind = draw(st.sampled_from(["good", "mutated", "exception", "header", "random"]))
    if kind == "good":
        return wrap(mbap, slave, good)
    if kind == "exception":
        code = draw(st.integers(0, 255))
        # mostly well-formed, so that every exception code is seen
        well_formed = draw(st.integers(0, 3)) > 0
        fc = pdu[0] | 0x80 if well_formed else draw(st.sampled_from([pdu[0], 0x80, 0x83, 0xFF]))
        tail = b"" if well_formed else draw(st.sampled_from([b"", b"\x00", b"\x01\x02"]))
        unit = slave if well_formed else draw(st.sampled_from([slave, 0, 255]))
        return wrap(mbap, unit, bytes([fc, code]) + tail)
    if kind == "header":
        return wrap(
            mbap,
            draw(st.sampled_from([slave, slave ^ 1, 0, 255])),
            good,
            tid=draw(u16),
            proto=draw(st.sampled_from([0, 0, 1, 0xFFFF])),
            length=draw(st.sampled_from([None, None, 0, 1, len(good), len(good) + 2, 0xFFFF])),
            crc=draw(st.binary(min_size=2, max_size=2)),
        )
    if kind == "mutated":
        adu = bytearray(wrap(mbap, slave, good))
        for _ in range(draw(st.integers(1, 3))):
            op = draw(st.sampled_from(["flip", "cut", "add", "drop"]))
            if op == "flip" and adu:
                at = draw(st.integers(0, len(adu) - 1))
                adu[at] ^= 1 << draw(st.integers(0, 7))
            elif op == "cut":
                del adu[draw(st.integers(0, len(adu))):]
            elif op == "add":
                adu += draw(st.binary(min_size=1, max_size=4))
            elif adu:
                del adu[draw(st.integers(0, len(adu) - 1))]
        return bytes(adu)
    return draw(st.binary(max_size=300))


def expected_outcome(mbap: bool, slave: int, pdu: bytes, adu: bytes) -> tuple[str, int]:
    """What the checker must do, derived independently: ("ok", 0), ("exception", code)
    or ("protocol", 0)."""
    if mbap:
        if len(adu) < 9:
            return "protocol", 0
        _tid, proto, length, unit = struct.unpack_from(">HHHB", adu)
        if proto != 0 or length != len(adu) - 6:
            return "protocol", 0
        reply = adu[7:]
    else:
        if len(adu) < 3:
            return "protocol", 0
        unit, reply = adu[0], adu[1:-2]
    if unit != slave or not reply:
        return "protocol", 0
    if len(reply) == 2 and reply[0] == pdu[0] | 0x80:
        return "exception", reply[1]
    return ("ok", 0) if reply == echo_of(pdu) else ("protocol", 0)


def checker(mbap: bool) -> Link:
    """A Link with no line behind it: the reply check reads only the framing mode."""
    link = Link.__new__(Link)
    link._mbap = mbap
    return link


@FUZZ
@given(st.data(), st.booleans(), units, write_pdus())
def test_write_reply_check(data: st.DataObject, mbap: bool, slave: int, pdu: bytes) -> None:
    adu = data.draw(replies(mbap, slave, pdu), label="adu")
    want, code = expected_outcome(mbap, slave, pdu, adu)
    event(want)
    try:
        checker(mbap)._check_write_reply(slave, pdu, adu)
    except ModbusExceptionResponse as exc:
        assert (want, code) == ("exception", exc.code), adu.hex(" ")
        assert str(exc)
    except ProtocolError as exc:
        assert want == "protocol", adu.hex(" ")
        assert str(exc)
    except ModbusError as exc:  # pragma: no cover - a reply check raises nothing else
        raise AssertionError(f"unexpected {type(exc).__name__} for {adu.hex(' ')}") from exc
    else:
        assert want == "ok", adu.hex(" ")


# -- the simulator's side: request framing and handling ----------------------------------


@st.composite
def requests(draw: st.DrawFn) -> bytes:
    """A request frame with a valid CRC: reads, writes, or an unknown function code."""
    unit = draw(st.sampled_from([0, 1, 2, 7, 247]))
    kind = draw(st.sampled_from(["read", "write", "other"]))
    if kind == "read":
        pdu = struct.pack(">BHH", draw(st.integers(1, 4)), draw(u16), draw(st.integers(0, 2100)))
    elif kind == "write":
        pdu = draw(write_pdus())
        if draw(st.booleans()):  # a byte count that lies
            pdu = pdu[:5] + draw(st.binary(max_size=8))
    else:
        pdu = bytes([draw(st.integers(0, 255))]) + draw(st.binary(max_size=20))
    return rtu.frame(unit, pdu)


streams = st.lists(
    st.one_of(requests(), st.binary(min_size=1, max_size=12)), min_size=1, max_size=6
).map(b"".join)


@FUZZ
@given(streams, st.booleans())
def test_simulator_framing(stream: bytes, idle: bool) -> None:
    buf = bytearray(stream)
    frames, consumed, discarded = rtu.split_frames(buf, idle)
    assert 0 <= discarded <= consumed <= len(buf)
    if idle:
        assert consumed == len(buf)  # after t3.5 of silence nothing stays pending
    assert sum(map(len, frames)) + discarded == consumed
    at = 0
    for frame in frames:
        assert rtu.crc_ok(frame)
        at = stream.index(frame, at) + len(frame)
    assert at <= consumed


@FUZZ
@given(streams, st.integers(0, 2**32))
def test_simulator_handles_what_it_frames(stream: bytes, seed: int) -> None:
    """Every frame the splitter cuts out is served as Simulator._serve does, without an
    exception, whatever fault knobs reshape the reply."""
    slave = Slave(7, size=2000)
    rng = random.Random(seed)
    slave.set_faults(
        exception_for_other_function=bool(seed & 1),
        echo_request=bool(seed & 2),
        wrong_byte_count_every=1 if seed & 4 else 0,
        truncate_every=1 if seed & 8 else 0,
    )
    frames, _, _ = rtu.split_frames(bytearray(stream), idle=True)
    event(f"{min(len(frames), 3)} frames")
    for raw in frames:
        pdu = raw[1:-2]
        if raw[0] == 0:
            actions = slave._handle_broadcast(pdu) if pdu[0] in (5, 6, 15, 16, 22) else []
        else:
            actions = slave._handle(raw, pdu, rng, can_close=True)
        for _after, data in actions:
            assert data is None or isinstance(data, bytes)
