"""The non-blocking framer of plain RTU DTU streams (csrc/emb_stream.c emb_stream_fill +
emb_stream_try, which the blocking receive and the loop engine share), fed a reply in
arbitrary pieces through a socketpair, against a model written here with
protocol/rtu.py's independent framing: heartbeats before the frame skipped and counted,
nothing taken until the frame is whole, then the frame, another slave's frame (0), a bad
CRC, or bytes that begin no reply (left for the drain)."""

from __future__ import annotations

import socket

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus._ffi.context import Context
from edgemodbus._ffi.native import ffi, lib
from edgemodbus.protocol import rtu

MORE = int(lib.EMB_STREAM_MORE)
ENOBASE = int(lib.MODBUS_ENOBASE)
EMBBADCRC = ENOBASE + 12  # modbus.h
EMBBADDATA = ENOBASE + 13
SLAVE = 7


def _model(stream: bytes, hb: bytes) -> tuple[int, int, bytes]:
    """(result, heartbeats, frame) for the bytes received so far."""
    i, beats = 0, 0
    while hb and stream.startswith(hb, i):
        i, beats = i + len(hb), beats + 1
    rest = stream[i:]
    if not rest or (hb and len(rest) < len(hb) and hb.startswith(rest)):
        return MORE, beats, b""
    if len(rest) < 3:  # every reply has its address, function and one more byte
        return MORE, beats, b""
    fc = rest[1]
    if fc & 0x80:
        need = 5  # an exception response (Modbus Application Protocol v1.1b3, 7)
    elif fc in (1, 2, 3, 4):
        need = 5 + rest[2]  # address, function, byte count, data, CRC (6.1-6.4)
    elif fc in (5, 6, 15, 16):
        need = 8
    else:
        need = 5  # a function of unknown length: framed as libmodbus frames it
    known = rtu.reply_length(rest)
    assert known == rtu.UNKNOWN or known == need  # the Python framer agrees
    if need > 256:  # longer than an RTU ADU (Modbus over Serial Line 2.5.1)
        return -EMBBADDATA, beats, rest[:256]
    if len(rest) < need:
        return MORE, beats, b""
    frame = rest[:need]
    if frame[0] not in (SLAVE, 0):
        return 0, beats, frame
    if not rtu.crc_ok(frame):
        return -EMBBADCRC, beats, frame
    return need, beats, frame


@st.composite
def _streams(draw: st.DrawFn) -> tuple[bytes, bytes, list[int]]:
    hb = draw(st.one_of(st.just(b""), st.binary(min_size=1, max_size=8)))
    if hb and hb[0] in (SLAVE, 0, 3):  # a heartbeat is not taken for a frame's start here
        hb = bytes([0xAA]) + hb[1:]
    slave = draw(st.sampled_from([SLAVE, SLAVE, 0, 9]))
    kind = draw(st.sampled_from(["read", "exception", "write", "unknown", "overlong"]))
    if kind == "read":
        data = draw(st.binary(max_size=250))
        pdu = bytes([draw(st.sampled_from([1, 2, 3, 4])), len(data)]) + data
    elif kind == "exception":
        pdu = bytes([0x83, draw(st.integers(1, 11))])
    elif kind == "write":
        pdu = bytes([6]) + draw(st.binary(min_size=4, max_size=4))
    elif kind == "unknown":
        pdu = bytes([0x41]) + draw(st.binary(min_size=1, max_size=6))
    else:
        pdu = bytes([3, draw(st.integers(252, 255))]) + draw(st.binary(max_size=6))
    frame = bytearray(rtu.frame(slave, pdu))
    if draw(st.booleans()) and draw(st.booleans()):
        frame[-1] ^= 0x5A  # a bad CRC
    stream = hb * draw(st.integers(0, 3)) + bytes(frame)
    cuts = sorted(set(draw(st.lists(st.integers(1, len(stream) - 1), max_size=6))))
    return hb, stream, cuts


@settings(max_examples=400, deadline=None)
@given(_streams())
def test_pieces_frame_as_the_model_says(case: tuple[bytes, bytes, list[int]]) -> None:
    hb, stream, cuts = case
    link = ffi.new("emb_link *")
    buf = ffi.new("emb_stream_buf *")
    link.sb = buf
    ffi.memmove(link.hb, hb, len(hb))
    link.hb_len = len(hb)
    rsp = ffi.new("uint8_t[]", int(lib.EMB_MAX_ADU))
    got = ffi.new("int *")
    a, b = socket.socketpair()
    try:
        a.setblocking(False)
        sent = 0
        for end in [*cuts, len(stream)]:
            b.sendall(stream[sent:end])
            n = 0
            while n < end - sent:
                r = lib.emb_stream_fill(link, a.fileno())
                assert r > 0, (r, ffi.errno)
                n += r
            sent = end
            rc = lib.emb_stream_try(link, SLAVE, rsp, got)
            if rc == -1:
                rc = -ffi.errno
            want, beats, frame = _model(stream[:sent], hb)
            assert rc == want, (stream[:sent].hex(), rc, want)
            assert link.heartbeats == beats
            if rc == MORE:
                assert got[0] == 0
                continue
            assert bytes(ffi.buffer(rsp, got[0])) == frame
            return
        raise AssertionError("a whole stream must frame")
    finally:
        a.close()
        b.close()


MS = 1_000_000


@settings(max_examples=500, deadline=None)
@given(start=st.integers(1, 10**12), gap=st.one_of(st.none(), st.integers(0, 5000 * MS)),
       total=st.integers(0, 2000), quiet=st.integers(0, 500), limit=st.integers(0, 5000))
def test_the_settle_deadline_follows_its_rules(start: int, gap: int | None, total: int,
                                               quiet: int, limit: int) -> None:
    """emb_settle_until (the settling link's deadline in the loop engine, the wait of the
    blocking discard): total_ms; once bytes came, quiet_ms after the last if later; never
    past limit_ms, which is at least total_ms."""
    last = 0 if gap is None else start + gap
    got = lib.emb_settle_until(start, last, total, quiet, limit)
    cap = start + max(limit, total) * MS
    want = start + total * MS
    if last:
        want = max(want, last + quiet * MS)
    assert got == min(want, cap)
    assert start + min(total, max(limit, total)) * MS <= got <= cap


def test_bytes_with_nothing_asked_are_dropped_and_heartbeats_counted() -> None:
    link = ffi.new("emb_link *")
    buf = ffi.new("emb_stream_buf *")
    assert lib.emb_stream_take_idle(link) == -1  # no stream buffers
    link.sb = buf
    ffi.memmove(link.hb, b"HB", 2)
    link.hb_len = 2
    a, b = socket.socketpair()
    try:
        a.setblocking(False)
        b.sendall(b"HB\x07\x03\x02HB\x01")
        assert lib.emb_stream_fill(link, a.fileno()) == 8
        assert lib.emb_stream_take_idle(link) == 4  # 07 03 02, 01
        assert link.heartbeats == 2
        rsp = ffi.new("uint8_t[]", int(lib.EMB_MAX_ADU))
        got = ffi.new("int *")
        assert lib.emb_stream_try(link, SLAVE, rsp, got) == MORE  # nothing left
    finally:
        a.close()
        b.close()


def test_a_wrapped_link_needs_its_report_ring_and_a_plain_one_goes_without() -> None:
    """The report ring (4 kB) is apart from the receive buffer: a plain DTU stream
    allocates only the 512 B buffer (docs/scale.md "Memory per DTU"); a wrapped link
    without its ring is refused (EINVAL) rather than written through a NULL pointer."""
    assert ffi.sizeof("emb_stream_buf") <= 512
    link = ffi.new("emb_link *")
    buf = ffi.new("emb_stream_buf *")
    link.sb = buf
    link.wrapped = 1
    assert lib.emb_stream_take_idle(link) == -1  # no ring
    ring = ffi.new("uint8_t[]", int(lib.EMB_RING_SIZE))
    link.ring = ring
    assert lib.emb_stream_take_idle(link) == 0


def test_a_context_allocates_the_ring_for_wrapped_streams_only() -> None:
    a, b = socket.socketpair()
    plain = Context.on_socket(a.fileno(), "plain", mbap=False)
    wrapped = Context.on_socket(b.fileno(), "wrapped", mbap=False)
    try:
        plain.set_stream(b"HB", False)
        plain.ensure_stream_buffers()
        wrapped.set_stream(b"", True)
        assert plain.is_stream and wrapped.is_stream
        assert plain._link.ring == ffi.NULL
        assert wrapped._link.ring != ffi.NULL
    finally:
        plain.close()
        wrapped.close()
        a.close()
        b.close()
