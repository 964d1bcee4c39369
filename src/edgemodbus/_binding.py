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


def _load_native() -> Any:
    """The cffi extension; with EDGEMODBUS_NATIVE=asan the AddressSanitizer build from
    build-asan/ (tools/asan_build.py; run with libasan preloaded, see `make test-asan`)."""
    if os.environ.get("EDGEMODBUS_NATIVE", "") != "asan":
        from . import _native

        return _native
    import importlib.util
    import sys

    lib_dir = Path(__file__).resolve().parents[2] / "build-asan" / "lib" / "edgemodbus"
    found = sorted(lib_dir.glob("_native*.so"))
    if not found:
        raise ImportError(f"EDGEMODBUS_NATIVE=asan but {lib_dir} holds no build")
    spec = importlib.util.spec_from_file_location("edgemodbus._native", found[0])
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules["edgemodbus._native"] = module
    return module


try:
    _native_module = _load_native()
    ffi, lib = _native_module.ffi, _native_module.lib
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
    _EMBXGTAR + 2: "bad data (a byte count too large for a frame, or a wrong length)",
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


# errnos of our own reply checks (csrc/emb_io.c): what each says about the reply
_EMB_EXCEPTION: int = lib.EMB_EEXCEPTION
_EMB_PARTIAL: int = lib.EMB_EPARTIAL
_EMB_PROTOCOL_ERRNOS = {
    lib.EMB_EECHO: "the bytes read back as the echo of the request (option 'echo') "
    "differ from it; does this line echo?",
    lib.EMB_EECHOSEEN: "the reply starts with our own request: the line echoes requests "
    "(an RS-485 adapter without echo suppression); set the 'echo' option",
    lib.EMB_ESLAVE: "response from the wrong slave id",
    lib.EMB_EFUNCTION: "function code of the reply is not the request's",
    lib.EMB_EOTHEREXC: "exception response for another function code",
    lib.EMB_ECOUNT: "byte count does not match the request",
    lib.EMB_ETID: "only replies with another MBAP transaction id came (skipped as stale)",
    lib.EMB_EPROTOID: "MBAP protocol id is not 0",
    lib.EMB_EMBAPLEN: "MBAP length does not match the frame",
}


def error_from_errno(err: int, what: str) -> ModbusError:
    """Map an errno left by libmodbus (or by our csrc helpers) to a typed error."""
    if err == _errno.ETIMEDOUT:
        return ModbusTimeoutError(f"{what}: no response (timeout)")
    if err == _EMB_PARTIAL:
        return ModbusTimeoutError(f"{what}: incomplete reply (byte timeout)")
    if _EMB_EXCEPTION <= err <= _EMB_EXCEPTION + 255:
        return exception_for_code(err - _EMB_EXCEPTION, what)
    if err in _EMB_PROTOCOL_ERRNOS:
        return ProtocolError(f"{what}: {_EMB_PROTOCOL_ERRNOS[err]}")
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

    @classmethod
    def from_values(cls, values: Sequence[int], bits: bool) -> Block:
        """A block holding ``values`` (registers 0..65535, or bits 0/1), for tests and for
        an item reassembled from pieces read separately."""
        top = 1 if bits else 0xFFFF
        for k, v in enumerate(values):
            if not 0 <= v <= top:
                kind = "bit" if bits else "register"
                raise ValueError(f"{kind} value {v!r} at index {k} is out of range 0..{top}")
        block = cls(ffi.new("uint8_t[]" if bits else "uint16_t[]", list(values) or [0]), bits)
        block.count = len(values)
        return block


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
        self._link = ffi.new("emb_link *")  # per-line state of csrc/emb_io.c
        self._header = 1  # bytes before the PDU in a reply: slave id, or the MBAP header

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
                f"{label}: socket fd {fd} >= {FD_SETSIZE}: libmodbus 3.1.6 cannot select() "
                "on it (it would abort the process); too many files are open in this process"
            )
        if mbap:
            ptr = lib.modbus_new_tcp(b"127.0.0.1", 502)  # address unused: we own the socket
        else:
            ptr = lib.modbus_new_rtu(b"/dev/null", 9600, b"N", 8, 1)  # settings unused
        ctx = cls(ptr, label, owns_fd=False)
        lib.modbus_set_socket(ctx._ptr, fd)
        if mbap:
            ctx._link.mbap = 1
            ctx._header = 7
        return ctx

    def set_echo(self, on: bool) -> None:
        """The line echoes every request (a 2-wire RS-485 adapter without echo
        suppression): read the request's own bytes back before each reply.  RTU only."""
        if on and self._link.mbap:
            raise ValueError(f"{self.label}: the echo option applies to RTU framing only")
        self._link.echo = 1 if on else 0

    def take_discarded(self) -> int:
        """Bytes thrown away since the last call (stale input, echoes, superseded
        frames), counted by the C transaction helpers."""
        n = int(self._link.discarded)
        if n:
            self._link.discarded = 0
        return n

    def last_reply(self) -> bytes:
        """The reply ADU of the last transaction (for frame traces and error details);
        empty when none was received whole."""
        return bytes(ffi.buffer(self._rsp, self._link.rsp_len))

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
        rc = lib.emb_read(self._ptr, self._link, slave, function, address, count, block._ptr,
                          self._rsp)
        if rc == -1:
            raise self._error(ffi.errno, f"slave {slave} FC{function:02d} @{address}+{count}",
                              function, 2 * count if function > 2 else (count + 7) // 8)
        block.count = rc
        return block

    def read_decode(self, slave: int, function: int, address: int, count: int,
                    plan: CodecPlan, mode: int) -> int:
        """:meth:`read`, then decode the block through ``plan`` in the same C call;
        returns the count the decode reports.  The block stays readable as with read."""
        bits = function in (1, 2)
        if bits != plan.bits:
            raise ValueError(f"codec: a plan for {'registers' if bits else 'bits'} used "
                             f"for FC{function:02d}")
        block = self.bits if bits else self.registers
        rc = lib.emb_read_decode(self._ptr, self._link, slave, function, address, count,
                                 block._ptr, self._rsp, plan._plan, mode)
        if rc == -1:
            raise self._error(ffi.errno, f"slave {slave} FC{function:02d} @{address}+{count}",
                              function, 2 * count if function > 2 else (count + 7) // 8)
        block.count = count
        return int(rc)

    def transact(self, slave: int, pdu: bytes) -> bytes:
        """Send ``pdu`` (function code first) to ``slave`` and return the reply ADU.

        The C side checks the header (slave id, or MBAP transaction id, protocol id,
        length and unit id) and the function code, and raises exception responses; the
        caller checks the rest (a write's echo).
        """
        n = len(pdu)
        ffi.memmove(self._req, pdu, n)
        rc = lib.emb_transact(self._ptr, self._link, slave, self._req, n, self._rsp)
        if rc == -1:
            raise self._error(ffi.errno, f"slave {slave} FC{pdu[0]:02d}", pdu[0], -1)
        return bytes(ffi.buffer(self._rsp, rc))

    def send(self, slave: int, pdu: bytes) -> None:
        """Send without waiting for a reply (broadcast)."""
        n = len(pdu)
        ffi.memmove(self._req, pdu, n)
        if lib.emb_send(self._ptr, self._link, slave, self._req, n) == -1:
            raise error_from_errno(ffi.errno, f"broadcast FC{pdu[0]:02d}")

    def _error(self, err: int, what: str, function: int, count: int) -> ModbusError:
        """The typed error for ``err``, with what the rejected reply held when it says
        more than the errno (which byte count, which unit, which function code)."""
        exc = error_from_errno(err, what)
        rsp = self.last_reply()
        h = self._header
        if len(rsp) < h + 2:
            return exc
        detail = ""
        if err == lib.EMB_ECOUNT:
            detail = f"{rsp[h + 1]}, expected {count}"
        elif err == lib.EMB_ESLAVE:
            detail = f"{rsp[h - 1]}"
        elif err == lib.EMB_EFUNCTION:
            detail = f"{rsp[h]:#04x}, expected {function:#04x}"
        elif err == lib.EMB_EOTHEREXC:
            detail = f"{rsp[h]:#04x} code {rsp[h + 1]:#04x}"
        elif err == lib.EMB_EPROTOID:
            detail = f"{rsp[2] << 8 | rsp[3]:#06x}"
        elif err == lib.EMB_EMBAPLEN:
            detail = f"{rsp[4] << 8 | rsp[5]}, frame has {len(rsp) - 6}"
        if detail:
            return type(exc)(f"{exc} ({detail})")
        return exc


def discard_input(fd: int, total_s: float, quiet_s: float, limit_s: float | None = None) -> int:
    """Throw away input on ``fd``: wait up to ``total_s`` for stray bytes; once bytes
    come, go on until ``quiet_s`` of silence, but never past ``limit_s`` (default
    ``total_s`` + 1 s).  0 for both takes only what is pending.  Returns the byte count;
    raises :class:`ModbusConnectionError` if the link failed or was closed."""
    limit = total_s + 1.0 if limit_s is None else limit_s
    n = lib.emb_discard_input(fd, round(total_s * 1000), max(1, round(quiet_s * 1000)),
                              round(limit * 1000))
    if n == -1:
        raise error_from_errno(ffi.errno, f"fd {fd}: discarding input")
    return int(n)


# --- codec ---
# Thin wrappers of the value codec (csrc/emb_codec.c).  codec.py describes items as plain
# CodecItem tuples; CodecPlan lays them out over typed output arrays, owns the C plan and
# state (allocated once per plan, never per decode) and turns C results into Python objects.

import operator  # noqa: E402
import struct  # noqa: E402
from collections.abc import Callable, Sequence  # noqa: E402
from typing import NamedTuple  # noqa: E402

CODEC_MODE_VALUES: int = lib.EMB_MODE_VALUES
CODEC_MODE_TRACK: int = lib.EMB_MODE_TRACK
CODEC_MODE_ALL: int = lib.EMB_MODE_ALL


def codec_constants(prefix: str) -> dict[str, int]:
    """The codec's C constants starting with ``EMB_<prefix>_``, keyed by the rest."""
    head = f"EMB_{prefix}_"
    return {name[len(head) :]: getattr(lib, name) for name in dir(lib) if name.startswith(head)}


class CodecItem(NamedTuple):
    """One item of a read block, as the C codec sees it (see csrc/emb_codec.h)."""

    offset: int
    nregs: int
    wire: int
    flags: int
    bit: int
    target: int
    out: int
    scale: float
    deadband: float


def _fill_item(dst: Any, item: CodecItem, slot: int, aux: int) -> None:
    try:
        dst.offset = item.offset
        dst.nregs = item.nregs
        dst.wire = item.wire
        dst.flags = item.flags
        dst.bit = item.bit
        dst.target = item.target
        dst.out = item.out
        dst.scale = item.scale
        dst.deadband = item.deadband
        dst.slot = slot
        dst.aux = aux
    except (OverflowError, TypeError) as exc:
        raise ValueError(f"codec: {item} does not fit the C item ({exc})") from None


class CodecPlan:
    """A compiled read block: C item array, typed output arrays and change-tracking state.

    ``posts[i]`` (or None) turns item i's raw result into its Python value (bytes for
    BYTES items).  Used by one thread at a time, like the block it decodes.
    """

    def __init__(
        self,
        bits: bool,
        items: Sequence[CodecItem],
        posts: Sequence[Callable[[Any], object] | None],
    ) -> None:
        n = len(items)
        o_bytes = lib.EMB_O_BYTES
        group_of = [it.out for it in items]
        sizes = [0, 0, 0, 0]  # i64, u64 (also BYTES lengths), f64, bool
        slots: list[int] = []
        auxes: list[int] = []
        n_bytes = 0
        for it, group in zip(items, group_of, strict=True):
            g = lib.EMB_O_U64 if group == o_bytes else group
            if not 0 <= g < 4:
                raise ValueError(f"codec item at offset {it.offset}: bad output group {it.out}")
            slots.append(sizes[g])
            sizes[g] += 1
            if group == o_bytes:
                auxes.append(n_bytes)
                n_bytes += 2 * it.nregs
            else:
                auxes.append(0)
        self.bits = bits
        self.n_items = n
        self._citems = ffi.new("emb_item[]", max(n, 1))
        for k, it in enumerate(items):
            _fill_item(self._citems[k], it, slots[k], auxes[k])
        ni, nu, nf, nb = sizes
        self._i64 = ffi.new("int64_t[]", max(ni, 1))
        self._u64 = ffi.new("uint64_t[]", max(nu, 1))
        self._f64 = ffi.new("double[]", max(nf, 1))
        self._bool = ffi.new("_Bool[]", max(nb, 1))
        self._bytes = ffi.new("uint8_t[]", max(n_bytes, 1))
        self._last_bytes = ffi.new("uint8_t[]", max(n_bytes, 1))
        self._status = ffi.new("uint8_t[]", max(n, 1))
        self._errval = ffi.new("emb_errval[]", max(n, 1))
        self._errs = ffi.new("uint32_t[]", max(n, 1))
        self._changed = ffi.new("uint32_t[]", max(n, 1))
        self._last = ffi.new("uint64_t[]", max(n, 1))
        self._last_status = ffi.new("uint8_t[]", max(n, 1))
        plan = ffi.new("emb_plan *")
        plan.items = self._citems
        plan.n_items = n
        plan.bits = 1 if bits else 0
        plan.out_i64, plan.n_i64 = self._i64, ni
        plan.out_u64, plan.n_u64 = self._u64, nu
        plan.out_f64, plan.n_f64 = self._f64, nf
        plan.out_bool, plan.n_bool = self._bool, nb
        plan.out_bytes, plan.n_bytes = self._bytes, n_bytes
        plan.status, plan.errval = self._status, self._errval
        plan.errs, plan.changed = self._errs, self._changed
        plan.last, plan.last_status, plan.last_bytes = (
            self._last,
            self._last_status,
            self._last_bytes,
        )
        bad = lib.emb_plan_check(plan)
        if bad:
            where = f"item {bad - 1}" if bad > 0 else "the plan"
            raise ValueError(f"codec: {where} is inconsistent (a bug in the item compiler)")
        lib.emb_reset(plan)
        self._plan = plan
        self._sizes = (ni, nu, nf, nb)
        self.status_view = memoryview(ffi.buffer(self._status, n))  # EMB_E_* of each item
        # Typed views that turn the integer and bool arrays into lists at C speed (for
        # doubles ffi.unpack is the faster one).
        self._view_i64 = memoryview(ffi.buffer(self._i64, 8 * ni)).cast("q")
        self._view_u64 = memoryview(ffi.buffer(self._u64, 8 * nu)).cast("Q")
        self._view_bool = memoryview(ffi.buffer(self._bool, ffi.sizeof("_Bool") * nb)).cast("?")
        self._bytes_buf = ffi.buffer(self._bytes)
        # Item k's value is lists[src][idx]: src 0..3 the groups, 4 the post-processed items.
        arrays = (self._i64, self._u64, self._f64, self._bool)
        special: list[tuple[int, int, int, Callable[[Any], object] | None, int]] = []
        where: list[tuple[Any, int, Callable[[Any], object] | None, int]] = []
        place: list[tuple[int, int]] = []
        for k, group in enumerate(group_of):
            g = lib.EMB_O_U64 if group == o_bytes else group
            aux = auxes[k] if group == o_bytes else -1
            post = posts[k]
            where.append((arrays[g], slots[k], post, aux))
            if post is None and aux < 0:
                place.append((g, slots[k]))
            else:
                place.append((4, len(special)))
                special.append((k, g, slots[k], post, aux))
        self._where = where
        self._special = special
        # Assemble the values list from runs of consecutive slots (a few list slices for
        # the usual blocks of same-typed items), or with one itemgetter when interleaved.
        runs: list[list[int]] = []
        for src, idx in place:
            if runs and runs[-1][0] == src and runs[-1][2] == idx:
                runs[-1][2] += 1
            else:
                runs.append([src, idx, idx + 1])
        lengths = (ni, nu, nf, nb, len(special))
        self._runs = [
            (src, a, b, a == 0 and b == lengths[src]) for src, a, b in runs
        ]
        self._getter: Callable[[list[object]], Any] | None = None
        if len(runs) > max(4, n // 8):
            base = (0, ni, ni + nu, ni + nu + nf, ni + nu + nf + nb)
            self._getter = operator.itemgetter(*[base[src] + idx for src, idx in place])

    def decode(self, block: Block, mode: int) -> int:
        """Run the C decode over ``block``; returns the reported (or failed) item count."""
        if block.bits != self.bits:
            kind = "bits" if self.bits else "registers"
            raise ValueError(f"codec: this block decoder expects {kind}")
        return int(lib.emb_decode(self._plan, block._ptr, block.count, mode))

    @property
    def n_errors(self) -> int:
        return int(self._plan.n_errors)

    def errors(self) -> list[int]:
        """Indices of the items that failed in the last decode."""
        return ffi.unpack(self._errs, self._plan.n_errors)

    def changed(self, n: int) -> list[int]:
        """Indices of the ``n`` items reported by the last TRACK/ALL decode."""
        return ffi.unpack(self._changed, n)

    def status(self, index: int) -> int:
        return int(self._status[index])

    def errval(self, index: int) -> int | float | None:
        """The value item ``index`` failed for in the last decode, exact: an int (64-bit
        values are not rounded), a float, or None (a register missing from the reply)."""
        ev = self._errval[index]
        bits, kind = int(ev.bits), int(ev.kind)
        if kind == lib.EMB_K_INT:
            return bits - (1 << 64) if bits >> 63 else bits
        if kind == lib.EMB_K_UINT:
            return bits
        if kind == lib.EMB_K_FLOAT:
            return float(struct.unpack("=d", struct.pack("=Q", bits))[0])
        return None

    def values(self) -> list[object]:
        """Every item's value from the last decode (None where it failed)."""
        lists: list[list[Any]] = [
            self._view_i64.tolist(),
            self._view_u64.tolist(),
            ffi.unpack(self._f64, self._sizes[2]),
            self._view_bool.tolist(),
        ]
        extra: list[object] = []
        if self._special:
            status = self.status_view
            buf = self._bytes_buf
            for k, g, slot, post, aux in self._special:
                if status[k]:
                    extra.append(None)
                    continue
                raw = lists[g][slot]
                if aux >= 0:
                    raw = buf[aux : aux + raw]
                extra.append(raw if post is None else post(raw))
        lists.append(extra)
        out: list[object]
        if self._getter is not None:
            out = list(self._getter(lists[0] + lists[1] + lists[2] + lists[3] + extra))
        else:
            runs = self._runs
            if len(runs) == 1 and runs[0][3]:
                out = lists[runs[0][0]]
            else:
                out = []
                for src, a, b, whole in runs:
                    out += lists[src] if whole else lists[src][a:b]
        if self._plan.n_errors:
            for k in ffi.unpack(self._errs, self._plan.n_errors):
                out[k] = None
        return out

    def value(self, index: int) -> object:
        """One item's value from the last decode (call only when its status is OK)."""
        array, slot, post, aux = self._where[index]
        raw = array[slot]
        if aux >= 0:
            raw = self._bytes_buf[aux : aux + raw]
        return raw if post is None else post(raw)

    def reset(self) -> None:
        """Forget the reported state: the next TRACK decode reports every item."""
        lib.emb_reset(self._plan)


def codec_encode(item: CodecItem, raw: int, fval: float, data: bytes) -> list[int]:
    """Pack a raw value into the item's registers (integers as two's complement ``raw``,
    floats as ``fval``, strings/binary as ``data``); ValueError if C refuses it."""
    citem = ffi.new("emb_item *")
    _fill_item(citem, item, 0, 0)
    size = max(item.nregs, 4)
    regs = ffi.new("uint16_t[]", size)
    n = lib.emb_encode(citem, raw & 0xFFFF_FFFF_FFFF_FFFF, fval, data, len(data), regs, size)
    if n < 0:
        raise ValueError(f"codec: cannot pack raw value {raw!r}/{fval!r}/{data!r}")
    return ffi.unpack(regs, n)
