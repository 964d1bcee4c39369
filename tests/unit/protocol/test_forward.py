"""Request checks and reply checks of forward mode (edgemodbus.protocol.forward).

Valid requests are built by an independent encoder (pymodbus 3.16.1's request PDUs), for
every supported function and every quantity the spec allows; junk is random bytes,
classified here by a plain reading of the Modbus Application Protocol v1.1b3, ch. 6.
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.pdu import ModbusPDU
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadCoilsResponse,
    ReadDiscreteInputsRequest,
    ReadDiscreteInputsResponse,
    WriteMultipleCoilsRequest,
    WriteSingleCoilRequest,
)
from pymodbus.pdu.other_message import ReportDeviceIdRequest, ReportDeviceIdResponse
from pymodbus.pdu.register_message import (
    MaskWriteRegisterRequest,
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    ReadInputRegistersRequest,
    ReadInputRegistersResponse,
    ReadWriteMultipleRegistersRequest,
    WriteMultipleRegistersRequest,
    WriteSingleRegisterRequest,
)

from edgemodbus.errors import (
    CrcError,
    IllegalDataAddress,
    LineBusyError,
    ModbusConnectionError,
    ModbusTimeoutError,
    ProtocolError,
    TargetBackoffError,
)
from edgemodbus.protocol.forward import (
    FORWARD_FUNCTIONS,
    ForwardRequestError,
    InvalidRequestError,
    UnsupportedFunctionError,
    check_reply,
    check_request,
    exception_code_for,
    expected_reply_length,
    read_reply,
    read_span,
)

u16 = st.integers(0, 0xFFFF)


def pdu_of(request: ModbusPDU) -> bytes:
    return bytes([request.function_code]) + request.encode()


@st.composite
def valid_requests(draw: st.DrawFn) -> bytes:
    """A valid request of a supported function, encoded by pymodbus."""
    fc = draw(st.sampled_from(sorted(FORWARD_FUNCTIONS)))
    address = draw(u16)
    request: ModbusPDU
    if fc in (1, 2):
        cls = ReadCoilsRequest if fc == 1 else ReadDiscreteInputsRequest
        request = cls(address=address, count=draw(st.integers(1, 2000)))
    elif fc in (3, 4):
        cls3 = ReadHoldingRegistersRequest if fc == 3 else ReadInputRegistersRequest
        request = cls3(address=address, count=draw(st.integers(1, 125)))
    elif fc == 5:
        request = WriteSingleCoilRequest(address=address, bits=[draw(st.booleans())])
    elif fc == 6:
        request = WriteSingleRegisterRequest(address=address, registers=[draw(u16)])
    elif fc == 15:
        bits = draw(st.lists(st.booleans(), min_size=1, max_size=1968))
        request = WriteMultipleCoilsRequest(address=address, bits=bits)
    elif fc == 16:
        regs = draw(st.lists(u16, min_size=1, max_size=123))
        request = WriteMultipleRegistersRequest(address=address, registers=regs)
    elif fc == 0x11:
        request = ReportDeviceIdRequest()
    elif fc == 22:
        request = MaskWriteRegisterRequest(address=address, and_mask=draw(u16),
                                           or_mask=draw(u16))
    else:
        request = ReadWriteMultipleRegistersRequest(
            read_address=address, read_count=draw(st.integers(1, 125)),
            write_address=draw(u16),
            write_registers=draw(st.lists(u16, min_size=1, max_size=121)))
    return pdu_of(request)


@given(valid_requests())
@settings(max_examples=400)
def test_every_valid_request_is_accepted(pdu: bytes) -> None:
    check_request(pdu)


def plain_reading(pdu: bytes) -> int | None:
    """The exception code a gateway owes for ``pdu``: None (forward it), 1 or 3."""
    if not pdu:
        return 3
    fc, n = pdu[0], len(pdu)
    if fc not in (1, 2, 3, 4, 5, 6, 15, 16, 17, 22, 23):
        return 1
    if fc == 17:  # Report Server ID: the function code alone (6.13)
        return None if n == 1 else 3
    if fc in (1, 2, 3, 4, 5, 6):
        if n != 5:
            return 3
        value = int.from_bytes(pdu[3:5], "big")
        limit = {1: 2000, 2: 2000, 3: 125, 4: 125}.get(fc)
        if limit is not None:
            return None if 1 <= value <= limit else 3
        if fc == 5:
            return None if value in (0, 0xFF00) else 3
        return None
    if fc == 22:
        return None if n == 7 else 3
    if fc in (15, 16):
        if n < 6:
            return 3
        qty, count = int.from_bytes(pdu[3:5], "big"), pdu[5]
        limit, need = (1968, (qty + 7) // 8) if fc == 15 else (123, 2 * qty)
        return None if 1 <= qty <= limit and count == need == n - 6 else 3
    if n < 10:
        return 3
    rq, wq, count = int.from_bytes(pdu[3:5], "big"), int.from_bytes(pdu[7:9], "big"), pdu[9]
    return None if 1 <= rq <= 125 and 1 <= wq <= 121 and count == 2 * wq == n - 10 else 3


def verdict(pdu: bytes) -> int | None:
    try:
        check_request(pdu)
    except ForwardRequestError as exc:
        assert isinstance(exc, ValueError)
        assert exception_code_for(exc) == exc.exception_code
        return exc.exception_code
    return None


@given(st.binary(max_size=260))
@settings(max_examples=1000)
def test_random_bytes_get_the_right_code(pdu: bytes) -> None:
    assert verdict(pdu) == plain_reading(pdu)


@given(st.sampled_from(sorted(FORWARD_FUNCTIONS)), st.binary(max_size=40))
@settings(max_examples=1000)
def test_random_bodies_of_supported_functions_get_the_right_code(fc: int, body: bytes) -> None:
    assert verdict(bytes([fc]) + body) == plain_reading(bytes([fc]) + body)


@given(valid_requests(), st.data())
@settings(max_examples=300)
def test_a_valid_request_cut_or_grown_is_refused_with_03(pdu: bytes, data: st.DataObject) -> None:
    if len(pdu) > 1:  # (Report Server ID is the function code alone)
        cut = pdu[:data.draw(st.integers(1, len(pdu) - 1))]
        assert verdict(cut) == 3
    grown = pdu + data.draw(st.binary(min_size=1, max_size=4))
    assert verdict(grown) == 3


@pytest.mark.parametrize("fc", [0x07, 0x08, 0x0B, 0x0C, 0x14, 0x15, 0x18, 0x2B, 0x81])
def test_functions_we_cannot_frame_are_illegal_function(fc: int) -> None:
    with pytest.raises(UnsupportedFunctionError, match=f"{fc:#04x}") as info:
        check_request(bytes([fc, 0, 0, 0, 1]))
    assert info.value.exception_code == exception_code_for(info.value) == 0x01


@pytest.mark.parametrize(("pdu", "message"), [
    (b"", "empty"),
    (bytes.fromhex("0300000000"), "quantity 0: must be 1..125"),
    (bytes.fromhex("030000007e"), "quantity 126: must be 1..125"),
    (bytes.fromhex("01000007d1"), "quantity 2001: must be 1..2000"),
    (bytes.fromhex("0500001234"), "coil value 0x1234"),
    (bytes.fromhex("03000001"), "of 4 bytes: must be 5"),
    (bytes.fromhex("100000000204000100"), "but 3 data bytes follow"),
    (bytes.fromhex("10000000020300010002"), "byte count 3: the quantity needs 4"),
    (bytes.fromhex("0f0000000a01ff"), "byte count 1: the quantity needs 2"),
    (bytes.fromhex("17000000010000007a00"), "quantity to write 122: must be 1..121"),
])
def test_bad_requests_name_what_is_wrong(pdu: bytes, message: str) -> None:
    with pytest.raises(InvalidRequestError, match=message) as info:
        check_request(pdu)
    assert exception_code_for(info.value) == 0x03


# -- replies ----------------------------------------------------------------------------
@given(valid_requests(), st.data())
@settings(max_examples=300)
def test_a_well_formed_reply_passes_and_a_changed_one_does_not(pdu: bytes,
                                                                data: st.DataObject) -> None:
    fc = pdu[0]
    n = expected_reply_length(pdu)
    if fc in (1, 2, 3, 4, 0x11, 23):
        reply = bytes([fc, n - 2]) + data.draw(st.binary(min_size=n - 2, max_size=n - 2))
    else:
        reply = pdu[:n]  # a write's reply echoes the start of its request
    check_reply(pdu, reply)
    check_reply(pdu, bytes([fc | 0x80, data.draw(st.integers(0, 255))]))
    i = data.draw(st.integers(0, n - 1))
    if fc in (1, 2, 3, 4, 0x11, 23) and i >= 2:
        return  # register values and bits are the slave's: any are fine
    changed = bytearray(reply)
    changed[i] ^= data.draw(st.integers(1, 255))
    with pytest.raises(ProtocolError):
        check_reply(pdu, bytes(changed))
    with pytest.raises(ProtocolError):
        check_reply(pdu, reply[:-1])
    with pytest.raises(ProtocolError):
        check_reply(pdu, reply + b"\x00")


@given(st.binary(max_size=240), st.booleans())
def test_report_server_id_replies_as_pymodbus_encodes_them_pass(ident: bytes, on: bool) -> None:
    """FC 0x11 (6.13): byte count, then what the slave chooses to say."""
    reply = bytes([0x11]) + ReportDeviceIdResponse(identifier=ident, status=on).encode()
    check_reply(b"\x11", reply)
    with pytest.raises(ProtocolError):
        check_reply(b"\x11", reply + b"\x00")
    with pytest.raises(ProtocolError):
        check_reply(b"\x11", reply[:-1])


def test_reply_lengths_follow_the_spec() -> None:
    assert expected_reply_length(bytes.fromhex("0100000013")) == 2 + 3  # 19 coils: 3 bytes
    assert expected_reply_length(bytes.fromhex("030000007d")) == 2 + 250
    assert expected_reply_length(bytes.fromhex("1700000003000000010200ff")) == 2 + 6
    assert expected_reply_length(struct.pack(">BHH", 6, 1, 2)) == 5
    assert expected_reply_length(struct.pack(">BHHH", 22, 1, 2, 3)) == 7


def test_failures_map_to_gateway_codes() -> None:
    assert exception_code_for(ModbusTimeoutError("no answer")) == 0x0B
    assert exception_code_for(CrcError("bad crc")) == 0x0B
    assert exception_code_for(ProtocolError("bad echo")) == 0x0B
    assert exception_code_for(ModbusConnectionError("line down")) == 0x0A
    assert exception_code_for(IllegalDataAddress()) == 0x02
    assert exception_code_for(RuntimeError("bug")) == 0x04
    assert exception_code_for(InvalidRequestError("x")) == 0x03
    assert exception_code_for(UnsupportedFunctionError("x")) == 0x01
    assert exception_code_for(LineBusyError("too many waiting")) == 0x06
    assert exception_code_for(TargetBackoffError("backing off")) == 0x0B


# -- read coalescing: the span of a read request, and a reply built from values ---------------
@given(st.sampled_from([1, 2, 3, 4]), u16, st.data())
def test_read_replies_equal_pymodbus_encoding(fc: int, address: int, data: st.DataObject) -> None:
    """The reply PDU built from values is the one pymodbus (an independent encoder) makes,
    and it passes our own reply check for the request with that span."""
    bits = fc in (1, 2)
    count = data.draw(st.integers(1, 2000 if bits else 125))
    request = struct.pack(">BHH", fc, address, count)
    assert read_span(request) == (fc, address, count)
    if bits:
        values = data.draw(st.lists(st.integers(0, 1), min_size=count, max_size=count))
        cls = ReadCoilsResponse if fc == 1 else ReadDiscreteInputsResponse
        # pymodbus pads bits to whole bytes itself
        theirs = cls(bits=[bool(v) for v in values] + [False] * (-count % 8))
    else:
        values = data.draw(st.lists(u16, min_size=count, max_size=count))
        cls2 = ReadHoldingRegistersResponse if fc == 3 else ReadInputRegistersResponse
        theirs = cls2(registers=values)
    ours = read_reply(fc, values)
    assert ours == pdu_of(theirs)
    check_reply(request, ours)


@given(valid_requests())
def test_only_reads_have_a_span(pdu: bytes) -> None:
    assert (read_span(pdu) is None) == (pdu[0] not in (1, 2, 3, 4))
