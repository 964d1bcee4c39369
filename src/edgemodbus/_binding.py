"""The only module that touches the cffi extension ``edgemodbus._native``.

It declares nothing itself (the cdefs are in csrc/cdefs/), wraps each C call the rest
of the package needs, reads errno right after a failed call and maps it to the
exception hierarchy of :mod:`edgemodbus.errors`.  ``modbus_strerror`` is never called:
it is not thread-safe in libmodbus 3.1.6 and our workers run concurrently.

Objects here hold cdata; the public modules hold these objects, never raw cdata.
"""

from __future__ import annotations

import errno as _errno
import os
from pathlib import Path
from typing import Any

from .errors import (
    CrcError,
    ModbusConnectionError,
    ModbusError,
    ModbusTimeoutError,
    ProtocolError,
    exception_for_code,
)

try:
    from ._native import ffi, lib
except ImportError as exc:  # pragma: no cover - depends on the build
    raise ImportError(
        "edgemodbus._native is not built or cannot load libmodbus "
        f"({exc}); build it with `make build` (pip install -e .) after "
        "`apt-get install libmodbus-dev pkg-config`"
    ) from exc


def check_fingerprint(built: str, root: Path) -> None:
    """Refuse an extension compiled from other C sources than ``root`` (a source
    checkout) holds; an installed wheel has no csrc/ next to it and is not checked."""
    if not ((root / "csrc").is_dir() and (root / "build_ffi.py").is_file()):
        return
    from ._sourcehash import source_hash

    current = source_hash(root)
    if built != current:
        raise ImportError(
            f"edgemodbus._native was built from other sources (fingerprint {built}) than "
            f"{root / 'csrc'} now holds ({current}); rebuild it: `make build` "
            "(or pip install -e .)"
        )


def _check_build() -> None:
    built = ffi.string(lib.emb_source_hash()).decode()
    check_fingerprint(built, Path(__file__).resolve().parents[2])


_check_build()

MAX_READ_REGISTERS: int = lib.MODBUS_MAX_READ_REGISTERS
MAX_READ_BITS: int = lib.MODBUS_MAX_READ_BITS
MAX_WRITE_REGISTERS: int = lib.MODBUS_MAX_WRITE_REGISTERS
MAX_WRITE_BITS: int = lib.MODBUS_MAX_WRITE_BITS
MAX_ADU_LENGTH: int = lib.MODBUS_TCP_MAX_ADU_LENGTH
FD_SETSIZE = 1024  # libmodbus 3.1.6 FD_SETs the context's fd: a larger fd aborts the process

_ENOBASE: int = lib.MODBUS_ENOBASE
_EMBXGTAR = _ENOBASE + 11
_PROTOCOL_ERRNOS = {
    _EMBXGTAR + 2: "bad data (wrong byte count, quantity or response length)",
    _EMBXGTAR + 3: "exception response does not match the request",
    _EMBXGTAR + 4: "unknown exception code",
    _EMBXGTAR + 5: "too many data",
    _EMBXGTAR + 6: "response from the wrong slave id",
}
_CONNECTION_ERRNOS = {
    _errno.ECONNRESET,
    _errno.ECONNREFUSED,
    _errno.ECONNABORTED,
    _errno.EPIPE,
    _errno.EIO,
    _errno.EBADF,
    _errno.ENOTCONN,
    _errno.ENETUNREACH,
    _errno.EHOSTUNREACH,
    _errno.ENXIO,
    _errno.ENODEV,
}


def error_from_errno(err: int, what: str) -> ModbusError:
    """Map an errno left by libmodbus (or by our csrc helpers) to a typed error."""
    if err == _errno.ETIMEDOUT:
        return ModbusTimeoutError(f"{what}: no response (timeout)")
    if _ENOBASE < err <= _EMBXGTAR:
        return exception_for_code(err - _ENOBASE, what)
    if err == _EMBXGTAR + 1:
        return CrcError(f"{what}: CRC error")
    if err in _PROTOCOL_ERRNOS:
        return ProtocolError(f"{what}: {_PROTOCOL_ERRNOS[err]}")
    if err in _CONNECTION_ERRNOS:
        return ModbusConnectionError(f"{what}: link error: {os.strerror(err)}")
    if err == 0:
        return ModbusConnectionError(f"{what}: failed without an error code")
    return ModbusConnectionError(f"{what}: {os.strerror(err)} (errno {err})")


class Block:
    """The data of the last read on a :class:`Context`: registers or bits (one per byte).

    It is a view of the context's own buffer, valid until the next read on it; the bus
    decodes it before issuing another request, so no read allocates.
    """

    __slots__ = ("_ptr", "bits", "count")

    def __init__(self, ptr: Any, bits: bool) -> None:
        self._ptr = ptr
        self.bits = bits
        self.count = 0

    def to_list(self) -> list[int]:
        """Copy out the values (registers as ints, bits as 0/1)."""
        return list(ffi.unpack(self._ptr, self.count))


class Context:
    """One libmodbus context (``modbus_t``), used by exactly one thread.

    ``Context.rtu`` opens a serial port itself; ``Context.on_socket`` drives a socket
    that the caller connected and keeps owning (RTU framing without MBAP, or Modbus
    TCP): libmodbus never closes it, so the socket's lifetime stays explicit.
    """

    def __init__(self, ptr: Any, label: str, owns_fd: bool) -> None:
        if ptr == ffi.NULL:
            raise ModbusConnectionError(
                f"{label}: libmodbus could not create a context ({os.strerror(ffi.errno)})"
            )
        self._ptr = ptr
        self.label = label
        self._owns_fd = owns_fd
        self.registers = Block(ffi.new("uint16_t[]", MAX_READ_REGISTERS), bits=False)
        self.bits = Block(ffi.new("uint8_t[]", MAX_READ_BITS), bits=True)
        self._rsp = ffi.new("uint8_t[]", MAX_ADU_LENGTH)
        self._req = ffi.new("uint8_t[]", MAX_ADU_LENGTH)

    # -- construction ----------------------------------------------------------------
    @classmethod
    def rtu(cls, port: str, baud: int, parity: str, data_bits: int, stop_bits: int) -> Context:
        ptr = lib.modbus_new_rtu(port.encode(), baud, parity.encode(), data_bits, stop_bits)
        return cls(ptr, port, owns_fd=True)

    @classmethod
    def on_socket(cls, fd: int, label: str, mbap: bool) -> Context:
        """A context on a connected socket: MBAP framing if ``mbap``, else raw RTU frames."""
        if fd >= FD_SETSIZE:
            raise ModbusConnectionError(
                f"{label}: socket fd {fd} >= {FD_SETSIZE}; libmodbus 3.1.6 cannot select() "
                "on it (it would abort the process); close unused files or raise nothing here"
            )
        if mbap:
            ptr = lib.modbus_new_tcp(b"127.0.0.1", 502)  # address unused: we own the socket
        else:
            ptr = lib.modbus_new_rtu(b"/dev/null", 9600, b"N", 8, 1)  # settings unused
        ctx = cls(ptr, label, owns_fd=False)
        lib.modbus_set_socket(ctx._ptr, fd)
        return ctx

    def connect(self, rs485: str = "none", rts_delay_us: int | None = None) -> None:
        """Open the serial port of an ``rtu`` context and set its RS-485 mode."""
        if lib.modbus_connect(self._ptr) == -1:
            err = ffi.errno
            if err == _errno.ENOENT:
                msg = "does not exist (check the device path; is the adapter plugged in?)"
            elif err == _errno.EACCES:
                msg = (
                    "permission denied: add the user to the 'dialout' group "
                    "(usermod -aG dialout USER, then log in again) or run with access to it"
                )
            else:
                msg = os.strerror(err)
            raise ModbusConnectionError(f"serial port {self.label}: {msg}")
        fd = self.fd
        if fd >= FD_SETSIZE:
            lib.modbus_close(self._ptr)
            raise ModbusConnectionError(
                f"serial port {self.label}: fd {fd} >= {FD_SETSIZE}; libmodbus 3.1.6 would "
                "abort the process in select(); too many files are open"
            )
        if rs485 == "kernel" and lib.modbus_rtu_set_serial_mode(self._ptr, 1) == -1:
            err = ffi.errno
            lib.modbus_close(self._ptr)
            raise ModbusConnectionError(
                f"serial port {self.label}: the driver refused RS-485 mode "
                f"(TIOCSRS485: {os.strerror(err)}); use rs485 'none' or 'rts-up'/'rts-down'"
            )
        if rs485 in ("rts-up", "rts-down"):
            mode = lib.MODBUS_RTU_RTS_UP if rs485 == "rts-up" else lib.MODBUS_RTU_RTS_DOWN
            lib.modbus_rtu_set_rts(self._ptr, mode)
            if rts_delay_us is not None:
                lib.modbus_rtu_set_rts_delay(self._ptr, rts_delay_us)

    @property
    def fd(self) -> int:
        return int(lib.modbus_get_socket(self._ptr))

    def set_timeouts(self, response_s: float, byte_s: float) -> None:
        """Response timeout (first byte) and byte timeout (between bytes of one frame)."""
        for setter, seconds in (
            (lib.modbus_set_response_timeout, response_s),
            (lib.modbus_set_byte_timeout, byte_s),
        ):
            usec = max(0, round(seconds * 1_000_000))
            if setter(self._ptr, usec // 1_000_000, usec % 1_000_000) == -1:
                raise ValueError(f"{self.label}: invalid timeout {seconds!r} s")

    def close(self) -> None:
        """Free the context; closes the fd only if libmodbus opened it (serial)."""
        if self._ptr is None:
            return
        if self._owns_fd:
            lib.modbus_close(self._ptr)
        else:
            lib.modbus_set_socket(self._ptr, -1)
        lib.modbus_free(self._ptr)
        self._ptr = None

    # -- transactions ----------------------------------------------------------------
    def read(self, slave: int, function: int, address: int, count: int) -> Block:
        """FC01-04 into this context's buffer; returns the (reused) :class:`Block`."""
        block = self.bits if function in (1, 2) else self.registers
        rc = lib.emb_read(self._ptr, slave, function, address, count, block._ptr)
        if rc == -1:
            raise error_from_errno(
                ffi.errno, f"slave {slave} FC{function:02d} @{address}+{count}"
            )
        block.count = rc
        return block

    def transact(self, slave: int, pdu: bytes) -> bytes:
        """Send ``pdu`` (function code first) to ``slave`` and return the reply ADU.

        libmodbus checks only the CRC (RTU) here; the caller checks the rest.
        """
        n = len(pdu) + 1
        self._req[0] = slave
        ffi.memmove(self._req + 1, pdu, len(pdu))
        rc = lib.emb_transact_raw(self._ptr, slave, self._req, n, self._rsp)
        what = f"slave {slave} FC{pdu[0]:02d}"
        if rc == -1:
            raise error_from_errno(ffi.errno, what)
        if rc == 0:  # libmodbus RTU: a frame from another slave id
            raise ProtocolError(f"{what}: response from the wrong slave id")
        return bytes(ffi.buffer(self._rsp, rc))

    def send(self, slave: int, pdu: bytes) -> None:
        """Send without waiting for a reply (broadcast)."""
        self._req[0] = slave
        ffi.memmove(self._req + 1, pdu, len(pdu))
        if lib.emb_send_raw(self._ptr, slave, self._req, len(pdu) + 1) == -1:
            raise error_from_errno(ffi.errno, f"broadcast FC{pdu[0]:02d}")


def discard_input(fd: int, total_s: float, quiet_s: float) -> int:
    """Throw away input on ``fd`` for up to ``total_s``, ending after ``quiet_s`` of
    silence once something arrived (0 takes only what is pending).  Returns the byte
    count; raises :class:`ModbusConnectionError` if the link failed or was closed."""
    n = lib.emb_discard_input(fd, round(total_s * 1000), max(1, round(quiet_s * 1000)))
    if n == -1:
        raise error_from_errno(ffi.errno, f"fd {fd}: discarding input")
    return int(n)
