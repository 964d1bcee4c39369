"""The one reply check (csrc/emb_check.c, ``emb_check_reply``) for callers that hold the
bytes of a request and its reply: the same check every transaction of csrc/emb_io.c
makes in C.  Returns a :class:`Verdict`; the caller words the error."""

from __future__ import annotations

from dataclasses import dataclass

from .native import MAX_ADU_LENGTH, ffi, lib

# what the check found (the errnos of csrc/emb_check.h)
E_SLAVE: int = lib.EMB_ESLAVE  # another unit id
E_FUNCTION: int = lib.EMB_EFUNCTION  # another function code
E_OTHER_EXCEPTION: int = lib.EMB_EOTHEREXC  # an exception response to another function
E_COUNT: int = lib.EMB_ECOUNT  # a read's byte count, or too short to hold one
E_LENGTH: int = lib.EMB_ELENGTH  # not the length the request calls for
E_WRITE_ECHO: int = lib.EMB_EWECHO  # a write's reply does not repeat the request
E_PROTOCOL_ID: int = lib.EMB_EPROTOID  # MBAP protocol id is not 0
E_MBAP_LENGTH: int = lib.EMB_EMBAPLEN  # MBAP length disagrees with the frame


@dataclass(frozen=True, slots=True)
class Verdict:
    """``error``: 0 when the reply answers the request, else one of the ``E_*`` codes;
    ``exception``: the code of an exception response to the request's function, or -1."""

    error: int
    exception: int = -1

    @property
    def ok(self) -> bool:
        return self.error == 0


def check_reply_pdu(request: bytes, reply: bytes) -> Verdict:
    """Whether ``reply`` (a PDU: function code first) answers ``request`` (a PDU): the
    function or an exception response to it, a read's byte count, the length, a write's
    echo (Modbus Application Protocol v1.1b3, 6 and 7)."""
    if not request or len(request) >= MAX_ADU_LENGTH or len(reply) >= MAX_ADU_LENGTH:
        raise ValueError(f"reply check: a request of {len(request)} bytes: must be "
                         f"1..{MAX_ADU_LENGTH - 1}; a reply of {len(reply)} bytes: must be "
                         f"0..{MAX_ADU_LENGTH - 1}")
    exc = ffi.new("int *")
    err = lib.emb_check_reply(b"\0" + request, len(request) + 1, b"\0" + reply,
                              len(reply) + 1, exc)
    return Verdict(int(err), int(exc[0]))


def check_reply_adu(mbap: bool, slave: int, pdu: bytes, adu: bytes) -> Verdict:
    """Whether the reply ADU ``adu`` answers ``pdu`` sent to ``slave``: on Modbus TCP
    (``mbap``) its MBAP protocol id and length first (not its transaction id), else an RTU
    frame whose CRC was checked on receipt (its last two bytes are not looked at)."""
    if not 1 <= len(pdu) < MAX_ADU_LENGTH or not 0 <= slave <= 255:
        raise ValueError(f"reply check: a request of {len(pdu)} bytes to slave {slave}; "
                         f"must be 1..{MAX_ADU_LENGTH - 1} bytes to 0..255")
    exc = ffi.new("int *")
    err = lib.emb_check_adu(1 if mbap else 0, -1, slave, pdu, len(pdu), adu, len(adu), exc)
    return Verdict(int(err), int(exc[0]))


def crc16(frame: bytes) -> int:
    """CRC-16/MODBUS of ``frame`` as csrc/emb_util.c computes it for every RTU frame
    sent and received (Modbus over Serial Line v1.02, 6.2.2); sent low byte first."""
    if len(frame) > MAX_ADU_LENGTH:
        raise ValueError(f"crc16: a frame of {len(frame)} bytes; at most {MAX_ADU_LENGTH}")
    return int(lib.emb_crc16(frame, len(frame)))
