"""The binding layer without I/O: errno mapping, buffers, source fingerprint."""

from __future__ import annotations

import errno
import socket

import pytest

from edgemodbus import _ffi
from edgemodbus.errors import (
    CrcError,
    GatewayTargetFailedToRespond,
    IllegalDataAddress,
    IllegalFunction,
    ModbusConnectionError,
    ModbusError,
    ModbusExceptionResponse,
    ModbusTimeoutError,
    ProtocolError,
    SlaveDeviceBusy,
    exception_for_code,
)

ENOBASE = 112345678  # MODBUS_ENOBASE in modbus.h


def test_timeout_maps_to_timeout_error() -> None:
    exc = _ffi.error_from_errno(errno.ETIMEDOUT, "slave 3 FC03 @0+2")
    assert isinstance(exc, ModbusTimeoutError) and isinstance(exc, TimeoutError)
    assert "slave 3 FC03" in str(exc)


@pytest.mark.parametrize(
    ("code", "cls"),
    [(1, IllegalFunction), (2, IllegalDataAddress), (6, SlaveDeviceBusy),
     (11, GatewayTargetFailedToRespond)],
)
def test_exception_codes_map_to_subclasses(code: int, cls: type) -> None:
    exc = _ffi.error_from_errno(ENOBASE + code, "x")
    assert type(exc) is cls
    assert isinstance(exc, ModbusExceptionResponse) and exc.code == code


def test_undefined_exception_code_keeps_its_number() -> None:
    exc = _ffi.error_from_errno(ENOBASE + 9, "x")
    assert type(exc) is ModbusExceptionResponse and exc.code == 9
    assert "0x09" in str(exc)
    assert exception_for_code(0x42).code == 0x42


def test_protocol_and_crc_errors() -> None:
    assert isinstance(_ffi.error_from_errno(ENOBASE + 12, "x"), CrcError)
    for offset in (13, 14, 15, 16, 17):
        exc = _ffi.error_from_errno(ENOBASE + offset, "x")
        assert isinstance(exc, ProtocolError) and not isinstance(exc, CrcError)
    assert "wrong slave" in str(_ffi.error_from_errno(ENOBASE + 17, "x"))


@pytest.mark.parametrize("err", [errno.ECONNRESET, errno.EPIPE, errno.EIO, errno.EBADF])
def test_link_errors_are_connection_errors(err: int) -> None:
    exc = _ffi.error_from_errno(err, "x")
    assert isinstance(exc, ModbusConnectionError) and isinstance(exc, ConnectionError)
    assert isinstance(exc, ModbusError)


def test_block_buffers_are_reused() -> None:
    a, b = socket.socketpair()
    try:
        ctx = _ffi.Context.on_socket(a.fileno(), "pair", mbap=False)
        try:
            assert ctx.registers is ctx.registers and ctx.registers.bits is False
            assert ctx.bits.bits is True
            assert ctx.fd == a.fileno()
        finally:
            ctx.close()
        # closing the context must not close a socket it does not own
        a.send(b"x")
        assert b.recv(1) == b"x"
    finally:
        a.close()
        b.close()


def test_discard_input_drains_and_reports_eof() -> None:
    a, b = socket.socketpair()
    try:
        b.send(b"\x01\x02\x03")
        assert _ffi.discard_input(a.fileno(), 0.0, 0.01) == 3
        assert _ffi.discard_input(a.fileno(), 0.05, 0.01) == 0
        b.close()
        with pytest.raises(ModbusConnectionError):
            _ffi.discard_input(a.fileno(), 0.05, 0.01)
    finally:
        a.close()


def test_stale_build_is_refused(tmp_path) -> None:
    """An extension built from other sources fails loudly at import."""
    from pathlib import Path

    from edgemodbus._ffi import source_hash

    (tmp_path / "csrc").mkdir()
    (tmp_path / "csrc" / "x.c").write_text("int x;\n")
    (tmp_path / "build_ffi.py").write_text("# build\n")
    built = source_hash(tmp_path)
    _ffi.check_fingerprint(built, tmp_path)  # same sources: fine
    (tmp_path / "csrc" / "x.c").write_text("int y;\n")
    with pytest.raises(ImportError, match="make build"):
        _ffi.check_fingerprint(built, tmp_path)
    _ffi.check_fingerprint("anything", tmp_path / "wheel")  # no csrc/: not checked
    # and the module in use was built from this checkout's sources
    here = Path(_ffi.__file__).resolve().parents[3]
    assert _ffi.ffi.string(_ffi.lib.emb_source_hash()).decode() == source_hash(here)
