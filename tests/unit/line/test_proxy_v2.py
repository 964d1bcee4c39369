"""The PROXY v2 header reader (line/proxy_v2.py) against hand-made headers laid out as
HAProxy's doc/proxy-protocol.txt section 2.2 gives them, and properties: any header
read in any pieces gives back its addresses, and no bytes crash the reader."""

from __future__ import annotations

import ipaddress
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.line import proxy_v2
from edgemodbus.line.proxy_v2 import ProxyError, ProxyHeader, build, parse, step

SIG = b"\x0d\x0a\x0d\x0a\x00\x0d\x0a\x51\x55\x49\x54\x0a"  # the spec's bytes, spelt out


def test_a_tcp4_header_laid_out_by_hand() -> None:
    raw = SIG + bytes([0x21, 0x11]) + struct.pack("!H", 12) + bytes([203, 0, 113, 7]) + \
        bytes([10, 0, 0, 1]) + struct.pack("!HH", 40001, 9502)
    assert parse(raw + b"ID:1\r\n") == ProxyHeader(False, "203.0.113.7", 40001, 28)


def test_a_tcp6_header_with_a_tlv_is_read_and_the_tlv_skipped() -> None:
    tlv = bytes([0x04]) + struct.pack("!H", 3) + b"abc"  # PP2_TYPE_NOOP
    src = ipaddress.IPv6Address("2001:db8::7").packed
    raw = SIG + bytes([0x21, 0x21]) + struct.pack("!H", 36 + len(tlv)) + src + \
        bytes(16) + struct.pack("!HH", 5, 6) + tlv
    header = parse(raw)
    assert header == ProxyHeader(False, "2001:db8::7", 5, 16 + 36 + len(tlv))


def test_local_is_the_balancers_health_check() -> None:
    assert parse(SIG + bytes([0x20, 0x00, 0, 0])) == ProxyHeader(True, None, None, 16)


def test_unspec_keeps_the_connections_own_address() -> None:
    assert parse(SIG + bytes([0x21, 0x00, 0, 0])) == ProxyHeader(False, None, None, 16)


def test_every_prefix_of_a_header_asks_for_more() -> None:
    raw = build("198.51.100.9", 1234, "10.0.0.1", 9502)
    for n in range(1, len(raw)):
        assert parse(raw[:n]) is None, n
    assert parse(raw) is not None


@pytest.mark.parametrize(("raw", "words"), [
    (SIG[:11] + b"X" + bytes([0x21, 0x11, 0, 12]) + bytes(12), "no PROXY v2 signature"),
    (b"ID:12345\r\n", "no PROXY v2 signature"),
    (SIG + bytes([0x11, 0x11, 0, 12]) + bytes(12), "version 1"),
    (SIG + bytes([0x22, 0x11, 0, 12]) + bytes(12), "command 2"),
    (SIG + bytes([0x21, 0x12, 0, 12]) + bytes(12), "family/transport 0x12"),  # UDP
    (SIG + bytes([0x21, 0x31, 0, 216]) + bytes(216), "family/transport 0x31"),  # UNIX
    (SIG + bytes([0x21, 0x11, 0, 8]) + bytes(8), "too short"),
    (SIG + bytes([0x21, 0x21, 0, 12]) + bytes(12), "too short"),
    (SIG + bytes([0x21, 0x11]) + struct.pack("!H", proxy_v2.MAX_PAYLOAD + 1), "length 513"),
])
def test_malformed_headers_are_refused_naming_the_byte(raw: bytes, words: str) -> None:
    with pytest.raises(ProxyError, match=words):
        parse(raw)


def test_an_oversize_length_is_refused_before_its_bytes_arrive() -> None:
    with pytest.raises(ProxyError, match="at most 512"):
        parse(SIG + bytes([0x21, 0x11, 0xFF, 0xFF]))


def test_step_tells_the_listener_what_to_do() -> None:
    header = build("203.0.113.7", 4000)
    assert step(b"ID:1\r\n", proxied=False) is False  # a DTU straight in: no header
    assert step(header, proxied=False) == ("proxyNotAllowed", "a PROXY header from an "
                                           "address not in fleet.loadBalancers")
    assert step(header[:10], proxied=True) is None
    assert step(b"ID:1\r\n", proxied=True)[0] == "proxyMissing"  # type: ignore[index]
    bad = SIG + bytes([0x13, 0x11, 0, 0])
    assert step(bad, proxied=True)[0] == "proxyMalformed"  # type: ignore[index]
    found = step(header + b"ID:1\r\n", proxied=True)
    assert isinstance(found, ProxyHeader) and found.source == "203.0.113.7"


addresses = st.one_of(st.ip_addresses(v=4), st.ip_addresses(v=6)).map(str)


@given(addresses, st.integers(0, 65535), st.integers(0, 65535),
       st.binary(max_size=64), st.binary(max_size=40), st.data())
def test_any_header_in_any_pieces_gives_back_its_address(
        source: str, sport: int, dport: int, tlv: bytes, payload: bytes,
        data: st.DataObject) -> None:
    dest = "10.0.0.1" if ":" not in source else "fd00::1"
    raw = build(source, sport, dest, dport, tlv=tlv)
    cut = data.draw(st.integers(0, len(raw) - 1))
    assert parse(raw[:cut]) is None if cut else True
    header = parse(raw + payload)
    assert header is not None
    assert (header.source, header.source_port, header.size) == \
        (str(ipaddress.ip_address(source)), sport, len(raw))
    assert (raw + payload)[header.size:] == payload


@given(st.binary(max_size=80))
def test_no_bytes_after_the_signature_crash_the_reader(tail: bytes) -> None:
    try:
        header = parse(SIG + tail)
    except ProxyError:
        return
    assert header is None or header.size <= len(SIG) + len(tail)


# An encoder written from the spec's layout (HAProxy's doc/proxy-protocol.txt, 2.2), not
# from proxy_v2.build: each field drawn on its own, lengths that may lie, and an oracle of
# what a receiver must conclude from those fields.
_ADDRESS_BYTES = {0x1: 12, 0x2: 36, 0x3: 216}  # the address block of INET, INET6, UNIX


@st.composite
def spec_headers(draw: st.DrawFn) -> tuple[bytes, str, tuple[bool, str | None, int | None,
                                                              int] | None]:
    """(bytes, what they are, the header expected or None for an error): version,
    command, family, transport drawn from valid and invalid nibbles; the address block
    of the family, TLVs (type, 2-byte length, value), and a length field that is
    honest, short by some bytes, or any 16-bit number."""
    version = draw(st.sampled_from([2, 2, 2, 1, 3, 0xF]))
    command = draw(st.sampled_from([0, 1, 1, 1, 2, 0xF]))
    family = draw(st.sampled_from([0x0, 0x1, 0x1, 0x2, 0x3, 0x4]))
    transport = draw(st.sampled_from([0x1, 0x1, 0x0, 0x2]))
    if family == 0x1:
        src = draw(st.ip_addresses(v=4))
        addresses = src.packed + draw(st.binary(min_size=4, max_size=4))
    elif family == 0x2:
        src = draw(st.ip_addresses(v=6))
        addresses = src.packed + draw(st.binary(min_size=16, max_size=16))
    else:
        src = None
        addresses = draw(st.binary(min_size=_ADDRESS_BYTES.get(family, 0),
                                   max_size=_ADDRESS_BYTES.get(family, 0)))
    sport = draw(st.integers(0, 65535))
    if family in (0x1, 0x2):
        addresses += struct.pack("!HH", sport, draw(st.integers(0, 65535)))
    tlvs = b"".join(bytes([t]) + struct.pack("!H", len(v)) + v for t, v in draw(
        st.lists(st.tuples(st.integers(0, 255), st.binary(max_size=40)), max_size=4)))
    body = addresses + tlvs
    honest = len(body)
    length = draw(st.sampled_from(["honest", "short", "any"]))
    declared = {"honest": honest, "short": max(0, honest - draw(st.integers(1, 40))),
                "any": draw(st.integers(0, 65535))}[length]
    raw = SIG + bytes([version << 4 | command, family << 4 | transport]) + \
        struct.pack("!H", declared) + body
    what = f"v{version} cmd{command} fam{family:x}{transport:x} len {declared}/{honest}"
    expected: tuple[bool, str | None, int | None, int] | None
    size = 16 + declared
    if version != 2 or command not in (0, 1) or declared > proxy_v2.MAX_PAYLOAD:
        expected = None
    elif command == 0:
        expected = (True, None, None, size)
    elif family == 0 and transport == 0:
        expected = (False, None, None, size)
    elif (family, transport) not in ((0x1, 0x1), (0x2, 0x1)) or \
            declared < _ADDRESS_BYTES[family]:
        expected = None
    else:
        assert src is not None
        expected = (False, str(src), sport, size)
    return raw, what, expected


@given(spec_headers())
def test_the_reader_agrees_with_an_encoder_from_the_spec(
        case: tuple[bytes, str, tuple[bool, str | None, int | None, int] | None]) -> None:
    raw, what, expected = case
    declared = struct.unpack_from("!H", raw, 14)[0]
    if expected is not None and len(raw) < 16 + declared:  # a length beyond the bytes:
        assert parse(raw) is None, what  # it waits (the deadline ends it: the listener)
        return
    if expected is None:
        with pytest.raises(ProxyError):
            header = parse(raw + bytes(70_000))  # enough bytes for any length
            raise AssertionError(f"{what}: read as {header}")
        return
    header = parse(raw)
    assert header is not None, what
    assert (header.local, header.source, header.source_port, header.size) == expected, what


def test_unfinished_says_how_far_the_header_got() -> None:
    raw = build("203.0.113.7", 1)
    assert proxy_v2.unfinished(raw[:20]) == (
        "proxyMalformed", "a PROXY v2 header not complete within registrationTimeout "
        "(20 bytes of 28)")
    assert proxy_v2.unfinished(raw[:5])[1].endswith("(5 bytes of at least 16)")
