"""The PROXY protocol version 2 header a TCP load balancer (HAProxy ``send-proxy-v2``)
puts before a proxied connection's first byte, so that the DTU listener sees the DTU's
own address, not the balancer's (the format: HAProxy's ``doc/proxy-protocol.txt``,
section 2.2).  Pure bytes, no I/O: :func:`parse` reads what has arrived so far.

Layout: the 12-byte signature; one byte of version (high nibble, 2) and command (low
nibble: 0 LOCAL, 1 PROXY); one byte of address family (high nibble: 0 UNSPEC, 1 INET,
2 INET6, 3 UNIX) and transport (low nibble: 1 STREAM); a big-endian 2-byte length of
what follows; then source address, destination address, source port, destination port
(4+4+2+2 bytes for TCP over IPv4, 16+16+2+2 for IPv6) and optional TLVs, skipped here.
"""

from __future__ import annotations

import ipaddress
import struct
from dataclasses import dataclass

SIGNATURE = b"\r\n\r\n\x00\r\nQUIT\n"
HEADER_FIXED = 16  # signature, version/command, family/transport, length
MAX_PAYLOAD = 512
"""Longest address block plus TLVs accepted (HAProxy sends 12 or 36 bytes of addresses
and a few TLVs at most; the spec asks receivers to take at least 216 bytes)."""
MAX_HEADER = HEADER_FIXED + MAX_PAYLOAD
"""The most bytes a balancer's connection is read for before its header is complete."""

_TCP4, _TCP6, _UNSPEC = 0x11, 0x21, 0x00


class ProxyError(ValueError):
    """A header that is not a valid PROXY v2 header for a TCP listener (the message says
    which byte and what was allowed)."""


@dataclass(frozen=True)
class ProxyHeader:
    """A complete header: ``source`` is the client's address (None for a LOCAL command,
    the balancer's own health check, or an UNSPEC family: the connection's own endpoints
    stand), ``size`` the header's length in bytes (the payload starts after it)."""

    local: bool
    source: str | None
    source_port: int | None
    size: int


def maybe_header(buf: bytes) -> bool:
    """Whether ``buf`` starts like a PROXY v2 header (or is a prefix of its signature)."""
    n = min(len(buf), len(SIGNATURE))
    return n > 0 and buf[:n] == SIGNATURE[:n]


def parse(buf: bytes) -> ProxyHeader | None:
    """The header at the start of ``buf``; None while more bytes are needed.  ProxyError
    when the bytes cannot be a header (wrong signature, version, command, family, or a
    length beyond :data:`MAX_PAYLOAD` or too short for its addresses)."""
    if not maybe_header(buf):
        raise ProxyError(f"no PROXY v2 signature: starts with {buf[:12].hex()}")
    if len(buf) < HEADER_FIXED:
        return None
    ver_cmd, family, length = buf[12], buf[13], struct.unpack_from("!H", buf, 14)[0]
    if ver_cmd >> 4 != 2:
        raise ProxyError(f"version {ver_cmd >> 4} (byte 12 = 0x{ver_cmd:02x}); only 2")
    command = ver_cmd & 0x0F
    if command not in (0, 1):
        raise ProxyError(f"command {command} (byte 12 = 0x{ver_cmd:02x}); allowed 0 LOCAL "
                         "or 1 PROXY")
    if length > MAX_PAYLOAD:
        raise ProxyError(f"length {length} (bytes 14-15); at most {MAX_PAYLOAD}")
    if len(buf) < HEADER_FIXED + length:
        return None
    size = HEADER_FIXED + length
    if command == 0:
        return ProxyHeader(True, None, None, size)  # LOCAL: the balancer's health check
    if family == _UNSPEC:
        return ProxyHeader(False, None, None, size)
    if family == _TCP4:
        need, alen = 12, 4
    elif family == _TCP6:
        need, alen = 36, 16
    else:
        raise ProxyError(f"family/transport 0x{family:02x} (byte 13); allowed 0x11 TCP "
                         "over IPv4, 0x21 TCP over IPv6 or 0x00 UNSPEC")
    if length < need:
        raise ProxyError(f"length {length} (bytes 14-15) is too short for the addresses "
                         f"of family 0x{family:02x} ({need} bytes)")
    raw = buf[HEADER_FIXED:HEADER_FIXED + alen]
    address = ipaddress.IPv4Address(raw) if alen == 4 else ipaddress.IPv6Address(raw)
    port = struct.unpack_from("!H", buf, HEADER_FIXED + 2 * alen)[0]
    return ProxyHeader(False, str(address), port, size)


def step(buf: bytes, proxied: bool) -> tuple[str, str] | ProxyHeader | bool | None:
    """What the DTU listener does with a newcomer's first bytes ``buf``.  ``proxied``:
    it comes from a configured load balancer and must start with a header.  Returns
    (counter, reason) to refuse it; a complete header; None while the header is not
    complete; False when there is no header to read (not proxied, no signature)."""
    if not proxied:
        if buf[:len(SIGNATURE)] != SIGNATURE:
            return False
        return ("proxyNotAllowed", "a PROXY header from an address not in "
                "fleet.loadBalancers")
    try:
        return parse(buf)
    except ProxyError as exc:
        if maybe_header(buf):
            return ("proxyMalformed", f"a malformed PROXY v2 header: {exc}")
        return ("proxyMissing", "no PROXY v2 header from a load balancer "
                "(fleet.loadBalancers)")


def unfinished(buf: bytes) -> tuple[str, str]:
    """(counter, reason) for a balancer's connection whose header was not complete at
    its registration timeout (a header sent a byte at a time, or cut short): refused as
    malformed, saying how far it got (it was counted as a silent peer before, which does
    not point at the balancer)."""
    need = f"{HEADER_FIXED + struct.unpack_from('!H', buf, 14)[0]}" \
        if len(buf) >= HEADER_FIXED else f"at least {HEADER_FIXED}"
    return ("proxyMalformed", f"a PROXY v2 header not complete within "
            f"registrationTimeout ({len(buf)} bytes of {need})")


def build(source: str | None, source_port: int = 0, dest: str | None = None,
          dest_port: int = 0, *, local: bool = False, tlv: bytes = b"") -> bytes:
    """A PROXY v2 header as a balancer sends it (tests and the simulator use it)."""
    if local or source is None:
        return SIGNATURE + bytes([0x20 if local else 0x21, _UNSPEC]) + \
            struct.pack("!H", len(tlv)) + tlv
    src = ipaddress.ip_address(source)
    dst = ipaddress.ip_address(dest or ("0.0.0.0" if src.version == 4 else "::"))
    family = _TCP4 if src.version == 4 else _TCP6
    body = src.packed + dst.packed + struct.pack("!HH", source_port, dest_port) + tlv
    return SIGNATURE + bytes([0x21, family]) + struct.pack("!H", len(body)) + body


__all__ = ["HEADER_FIXED", "MAX_HEADER", "MAX_PAYLOAD", "SIGNATURE", "ProxyError",
           "ProxyHeader", "build", "maybe_header", "parse", "step", "unfinished"]
