"""The write encoder of csrc/emb_io.c (``emb_write_pdu``, what ``emb_write`` sends) against
pymodbus's request classes, an independent encoder: random FC05, FC06, FC15, FC16 and FC22
requests (Modbus Application Protocol v1.1b3, 6.5, 6.6, 6.11, 6.12, 6.16) must give the
same PDU; what the protocol does not allow is refused (EINVAL), never sent."""

from __future__ import annotations

import errno
import socket
from collections.abc import Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.pdu import ModbusPDU
from pymodbus.pdu.bit_message import WriteMultipleCoilsRequest, WriteSingleCoilRequest
from pymodbus.pdu.register_message import (
    MaskWriteRegisterRequest,
    WriteMultipleRegistersRequest,
    WriteSingleRegisterRequest,
)

from edgemodbus._ffi import Context
from edgemodbus._ffi.native import MAX_ADU_LENGTH, ffi, lib

MAX_BITS = 1968  # 6.11: 0x7B0
MAX_REGISTERS = 123  # 6.12: 0x7B
ADDRESS = st.integers(0, 0xFFFF)
REGISTER = st.integers(0, 0xFFFF)


def ours(function: int, address: int, values: Sequence[int]) -> bytes | None:
    pdu = ffi.new("uint8_t[]", MAX_ADU_LENGTH)
    n = lib.emb_write_pdu(function, address, len(values), list(values), pdu)
    return None if n == -1 else bytes(ffi.buffer(pdu, n))


def theirs(request: ModbusPDU) -> bytes:
    return bytes([request.function_code]) + request.encode()


@settings(max_examples=300, deadline=None)
@given(function=st.sampled_from([5, 6, 15, 16, 22]), address=ADDRESS, data=st.data())
def test_the_pdu_is_pymodbus(function: int, address: int, data: st.DataObject) -> None:
    request: ModbusPDU
    values: list[int]
    if function == 5:
        values = [int(data.draw(st.booleans()))]
        request = WriteSingleCoilRequest(address=address, bits=[bool(values[0])])
    elif function == 15:
        bits = data.draw(st.lists(st.booleans(), min_size=1, max_size=MAX_BITS))
        values = [int(b) for b in bits]
        request = WriteMultipleCoilsRequest(address=address, bits=bits)
    elif function == 6:
        values = [data.draw(REGISTER)]
        request = WriteSingleRegisterRequest(address=address, registers=values)
    elif function == 16:
        values = data.draw(st.lists(REGISTER, min_size=1, max_size=MAX_REGISTERS))
        request = WriteMultipleRegistersRequest(address=address, registers=values)
    else:
        values = [data.draw(REGISTER), data.draw(REGISTER)]
        request = MaskWriteRegisterRequest(address=address, and_mask=values[0],
                                           or_mask=values[1])
    assert ours(function, address, values) == theirs(request)


def test_any_non_zero_value_is_a_coil_on() -> None:
    assert ours(5, 1, [7]) == bytes.fromhex("05 0001 FF00")
    assert ours(15, 1, [2, 0, 9]) == bytes.fromhex("0F 0001 0003 01 05")


@pytest.mark.parametrize(("function", "address", "count"), [
    (3, 0, 1),  # a read: not a write
    (23, 0, 2),  # FC23 is sent whole by emb_request, not encoded here
    (6, 0x10000, 1), (6, -1, 1),  # addresses are 0..65535 (4.4)
    (5, 0, 2), (6, 0, 0), (22, 0, 1),  # FC05/06 write one, FC22 takes two masks
    (15, 0, 0), (15, 0, MAX_BITS + 1),  # 6.11: 1..0x7B0
    (16, 0, 0), (16, 0, MAX_REGISTERS + 1),  # 6.12: 1..0x7B
])
def test_what_the_protocol_does_not_allow_is_refused(function: int, address: int,
                                                     count: int) -> None:
    assert ours(function, address, [1] * count) is None
    assert ffi.errno == errno.EINVAL


def test_a_write_the_encoder_refuses_names_what_is_allowed() -> None:
    """Context.write: refused before anything is sent, the error says why."""
    ours_end, peer = socket.socketpair()
    ctx = Context.on_socket(ours_end.fileno(), "pair", mbap=False)
    try:
        with pytest.raises(ValueError, match=r"pair: FC06 @3: a value of \[70000\] is not a "
                           r"register \(0\.\.65535\)"):
            ctx.write(1, 6, 3, [70000])
        with pytest.raises(ValueError, match=r"pair: FC03 @0 of 1 values: the function must "
                           r"be 5, 6, 15, 16 or 22"):
            ctx.write(1, 3, 0, [1])
        peer.setblocking(False)
        with pytest.raises(BlockingIOError):
            peer.recv(1)  # nothing went out
    finally:
        ctx.close()
        ours_end.close()
        peer.close()
