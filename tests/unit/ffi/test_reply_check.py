"""The one reply check (csrc/emb_check.c, ``emb_check_reply``).

* Property test against an independent model written here from Modbus Application
  Protocol v1.1b3 (ch. 6 and 7) and Modbus Messaging on TCP/IP (3.1.3): random requests of
  every function the master sends (reads, writes, 0x11, 0x16, 0x17, unknown codes, short
  ones) and replies that are right, mutated, exceptions or random; the C verdict (which
  error, which exception code) must be the model's, for PDUs and for RTU and MBAP ADUs.
* The same check inside a transaction, on a socketpair with a peer that answers: a
  write's wrong echo, a 0x16 reply with another mask, a read's or 0x17's wrong byte count
  now fail in C (before, ``emb_transact`` took them and only some callers checked in
  Python).
"""

from __future__ import annotations

import os
import socket
import struct
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from edgemodbus import _ffi
from edgemodbus._ffi import check
from edgemodbus.errors import IllegalDataValue, ProtocolError
from edgemodbus.protocol import rtu

EXAMPLES = int(os.environ.get("EDGEMODBUS_FUZZ_EXAMPLES", "200"))
PROPS = settings(max_examples=max(EXAMPLES, 300), deadline=None,
                 suppress_health_check=[HealthCheck.too_slow])
u16 = st.integers(0, 0xFFFF)

# -- the model ------------------------------------------------------------------------------

OK = (0, -1)


def normal_reply(request: bytes) -> tuple[str, int, int] | None:
    """What the normal reply to ``request`` must be (ch. 6): ("count", byte count, PDU
    length) for reads, ("echo", PDU length, 0) for writes, None when the request does not
    tell (unknown function, too short)."""
    fc = request[0]
    if fc in (0x01, 0x02, 0x03, 0x04, 0x17) and len(request) >= 5:
        qty = int.from_bytes(request[3:5], "big")  # 6.17: the read quantity comes first
        count = -(-qty // 8) if fc in (0x01, 0x02) else qty * 2
        return "count", count, count + 2
    if fc in (0x05, 0x06, 0x0F, 0x10) and len(request) >= 5:
        return "echo", 5, 0  # 6.5, 6.6: address and value; 6.11, 6.12: address, quantity
    if fc == 0x16 and len(request) >= 7:
        return "echo", 7, 0  # 6.16: the whole request
    return None


def model(unit: int, request: bytes, reply_unit: int, reply: bytes) -> tuple[int, int]:
    """(error, exception code) that the check must give for a reply PDU from
    ``reply_unit`` to ``request`` sent to ``unit``."""
    if not request or len(reply) < 2:
        return check.E_COUNT, -1
    if reply_unit != unit:
        return check.E_SLAVE, -1
    fc = request[0]
    if reply[0] == fc | 0x80:  # ch. 7: function | 0x80 and one code
        return (0, reply[1]) if len(reply) == 2 else (check.E_LENGTH, -1)
    if reply[0] & 0x80:
        return check.E_OTHER_EXCEPTION, -1
    if reply[0] != fc:
        return check.E_FUNCTION, -1
    if fc == 0x11:  # 6.13: byte count, then at least the run indicator
        return OK if len(reply) >= 3 and reply[1] == len(reply) - 2 else (check.E_LENGTH, -1)
    want = normal_reply(request)
    if want is None:
        return OK
    if want[0] == "count":
        if reply[1] != want[1]:
            return check.E_COUNT, -1
        return OK if len(reply) == want[2] else (check.E_LENGTH, -1)
    if len(reply) != want[1]:
        return check.E_LENGTH, -1
    return OK if reply == request[:want[1]] else (check.E_WRITE_ECHO, -1)


# -- requests and replies -------------------------------------------------------------------


@st.composite
def requests(draw: st.DrawFn) -> bytes:
    """A request PDU: any function the master sends, well-formed or not."""
    kind = draw(st.sampled_from(["read", "write", "multiple", "mask", "rw", "id", "other",
                                 "short"]))
    address = draw(u16)
    if kind == "read":
        return struct.pack(">BHH", draw(st.integers(1, 4)), address,
                           draw(st.one_of(st.integers(1, 125), st.integers(0, 2100))))
    if kind == "write":
        return struct.pack(">BHH", draw(st.sampled_from([5, 6])), address, draw(u16))
    if kind == "multiple":
        fc = draw(st.sampled_from([0x0F, 0x10]))
        data = draw(st.binary(min_size=1, max_size=20))
        return struct.pack(">BHHB", fc, address, draw(st.integers(1, 123)), len(data)) + data
    if kind == "mask":
        return struct.pack(">BHHH", 0x16, address, draw(u16), draw(u16))
    if kind == "rw":
        data = draw(st.binary(min_size=2, max_size=8))
        return struct.pack(">BHHHHB", 0x17, address, draw(st.integers(1, 125)), draw(u16),
                           len(data) // 2, len(data)) + data
    if kind == "id":
        return b"\x11"
    if kind == "other":
        return bytes([draw(st.sampled_from([0x07, 0x08, 0x2B, 0x41, 0x7F]))]) + draw(
            st.binary(max_size=6))
    return bytes([draw(st.sampled_from([1, 3, 5, 0x0F, 0x16, 0x17]))]) + draw(
        st.binary(max_size=4))


def good_reply(draw: st.DrawFn, request: bytes) -> bytes:
    want = normal_reply(request)
    fc = request[0]
    if fc == 0x11:
        ident = draw(st.binary(min_size=1, max_size=20))
        return bytes([fc, len(ident)]) + ident
    if want is None:
        return bytes([fc]) + draw(st.binary(min_size=1, max_size=8))
    if want[0] == "count":
        count = min(want[1], 252)
        return bytes([fc, count & 0xFF]) + draw(st.binary(min_size=count, max_size=count))
    return request[:want[1]]


@st.composite
def replies(draw: st.DrawFn, request: bytes) -> bytes:
    """The right reply, a mutation of it, an exception reply, or random bytes."""
    kind = draw(st.sampled_from(["good", "mutated", "mutated", "exception", "random"]))
    event(kind)
    if kind == "good":
        return good_reply(draw, request)
    if kind == "exception":
        fc = draw(st.sampled_from([request[0] | 0x80, request[0] | 0x80, 0x83, 0x90, 0xFF]))
        tail = draw(st.sampled_from([b"", b"", b"", b"\x00"]))
        return bytes([fc, draw(st.integers(0, 255))]) + tail
    if kind == "mutated":
        reply = bytearray(good_reply(draw, request))
        for _ in range(draw(st.integers(1, 3))):
            op = draw(st.sampled_from(["flip", "cut", "add", "drop"]))
            if op == "flip" and reply:
                at = draw(st.integers(0, len(reply) - 1))
                reply[at] ^= 1 << draw(st.integers(0, 7))
            elif op == "cut":
                del reply[draw(st.integers(0, len(reply))):]
            elif op == "add":
                reply += draw(st.binary(min_size=1, max_size=3))
            elif reply:
                del reply[draw(st.integers(0, len(reply) - 1))]
        return bytes(reply)
    return draw(st.binary(max_size=40))


@PROPS
@given(requests(), st.data())
def test_the_pdu_verdict_is_the_models(request: bytes, data: st.DataObject) -> None:
    reply = data.draw(replies(request), label="reply")
    got = check.check_reply_pdu(request, reply)
    assert (got.error, got.exception) == model(0, request, 0, reply), (request.hex(" "),
                                                                      reply.hex(" "))


@PROPS
@given(requests(), st.data(), st.booleans(), st.integers(1, 247))
def test_the_adu_verdict_is_the_models(request: bytes, data: st.DataObject, mbap: bool,
                                       unit: int) -> None:
    reply = data.draw(replies(request), label="reply")
    reply_unit = data.draw(st.sampled_from([unit, unit, unit, unit ^ 1, 0]), label="unit")
    body = bytes([reply_unit]) + reply
    if mbap:
        proto = data.draw(st.sampled_from([0, 0, 0, 1, 0x100]), label="proto")
        length = data.draw(st.sampled_from([len(body)] * 3 + [len(body) + 1, 0]),
                           label="length")
        adu = struct.pack(">HHH", data.draw(u16, label="tid"), proto, length) + body
        want = (model(unit, request, reply_unit, reply) if len(adu) >= 9 else
                (check.E_COUNT, -1))
        if len(adu) >= 9 and proto != 0:
            want = check.E_PROTOCOL_ID, -1
        elif len(adu) >= 9 and length != len(body):
            want = check.E_MBAP_LENGTH, -1
    else:
        adu = body + b"\xde\xad"  # the CRC was checked on receipt: not looked at
        want = model(unit, request, reply_unit, reply) if len(adu) >= 5 else (check.E_COUNT, -1)
    got = check.check_reply_adu(mbap, unit, request, adu)
    assert (got.error, got.exception) == want, (request.hex(" "), adu.hex(" "))


def test_bad_arguments_are_refused_with_what_is_allowed() -> None:
    with pytest.raises(ValueError, match=r"a request of 0 bytes: must be 1\.\.259"):
        check.check_reply_pdu(b"", b"\x03\x00")
    with pytest.raises(ValueError, match="slave 256"):
        check.check_reply_adu(False, 256, b"\x03\x00\x00\x00\x01", b"")


# -- inside a transaction -------------------------------------------------------------------


@contextmanager
def answering(mbap: bool, answer: bytes) -> Iterator[_ffi.Context]:
    """A context on a socketpair whose peer reads one request and sends ``answer``
    (an RTU frame gets its CRC; on Modbus TCP the MBAP header of the request's
    transaction id is put before it)."""
    ours, peer = socket.socketpair()
    ctx = _ffi.Context.on_socket(ours.fileno(), "pair", mbap=mbap)
    ctx.set_timeouts(2.0, 0.5)

    def run() -> None:
        request = peer.recv(512)
        if not request:
            return
        if mbap:
            peer.sendall(request[:4] + struct.pack(">H", len(answer)) + answer)
        else:
            peer.sendall(rtu.frame(answer[0], answer[1:]))

    thread = threading.Thread(target=run, name="reply-check-peer")
    thread.start()
    try:
        yield ctx
    finally:
        thread.join(10)
        ctx.close()
        ours.close()
        peer.close()


WRONG = [
    # (request PDU, reply PDU, message): each reply has the right function and length
    (struct.pack(">BHH", 6, 100, 5), struct.pack(">BHH", 6, 100, 6), "echo 00 64 00 06"),
    (struct.pack(">BHH", 5, 7, 0xFF00), struct.pack(">BHH", 5, 8, 0xFF00), "echo"),
    (struct.pack(">BHHBHH", 0x10, 1, 2, 4, 10, 11), struct.pack(">BHH", 0x10, 1, 3), "echo"),
    (struct.pack(">BHHBB", 0x0F, 1, 3, 1, 5), struct.pack(">BHH", 0x0F, 2, 3), "echo"),
    (struct.pack(">BHHH", 0x16, 4, 0xFF00, 0x0012), struct.pack(">BHHH", 0x16, 4, 0xFF00, 0),
     "echo 00 04 ff 00 00 00 does not match the request 00 04 ff 00 00 12"),
    (struct.pack(">BHH", 3, 0, 2), bytes([3, 2, 0, 1]), "byte count does not match the "
     "request \\(2, expected 4\\)"),
    (struct.pack(">BHHHHBH", 0x17, 0, 2, 9, 1, 2, 7), bytes([0x17, 2, 0, 1]),
     "byte count does not match the request \\(2, expected 4\\)"),
]


@pytest.mark.parametrize("mbap", [False, True], ids=["rtu", "mbap"])
@pytest.mark.parametrize(("pdu", "reply", "message"), WRONG,
                         ids=["fc06", "fc05", "fc10", "fc0f", "fc16", "fc03", "fc17"])
def test_a_transaction_refuses_what_does_not_answer_its_request(
        mbap: bool, pdu: bytes, reply: bytes, message: str) -> None:
    with answering(mbap, bytes([9]) + reply) as ctx, pytest.raises(ProtocolError,
                                                                    match=message):
        ctx.transact(9, pdu)


@pytest.mark.parametrize("mbap", [False, True], ids=["rtu", "mbap"])
def test_a_transaction_takes_the_right_reply_and_an_exception(mbap: bool) -> None:
    pdu = struct.pack(">BHHH", 0x16, 4, 0xFF00, 0x0012)
    with answering(mbap, bytes([9]) + pdu) as ctx:
        adu = ctx.transact(9, pdu)
        assert (adu[7:] if mbap else adu[1:-2]) == pdu
    with answering(mbap, bytes([9, 0x96, 3])) as ctx, pytest.raises(IllegalDataValue):
        ctx.transact(9, pdu)
