"""The gateway's Modbus TCP server in C (csrc/emb_serve.c): a thin wrapper.

:class:`ServerCore` owns one ``emb_server``: its listening socket, the masters'
connections and the units' register images.  :meth:`ServerCore.run` is called by one
thread (the server's), with the GIL released; :meth:`post`, :meth:`update`,
:meth:`set_unit`, :meth:`set_fresh` and :meth:`stop` may be called from any thread.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from typing import Any, NamedTuple

from .native import ffi, lib

EV_DEADLINE: int = lib.EMB_SV_EV_DEADLINE
EV_REQUEST: int = lib.EMB_SV_EV_REQUEST
EV_STOP: int = lib.EMB_SV_EV_STOP
EV_ERROR: int = lib.EMB_SV_EV_ERROR

MODE_NONE: int = lib.EMB_SV_NONE
MODE_CACHED: int = lib.EMB_SV_CACHED
MODE_FORWARD: int = lib.EMB_SV_FORWARD

STATE_UNMAPPED: int = lib.EMB_SV_UNMAPPED
STATE_VALID: int = lib.EMB_SV_VALID
STATE_INVALID: int = lib.EMB_SV_INVALID
STATE_WRITABLE: int = lib.EMB_SV_WRITABLE

MAX_NETS: int = lib.EMB_SV_NETS

POST_PDU: int = lib.EMB_SV_POST_PDU
POST_EXCEPTION: int = lib.EMB_SV_POST_EXCEPTION
POST_WRITTEN: int = lib.EMB_SV_POST_WRITTEN


class ImageRun(NamedTuple):
    """``count`` addresses of ``area`` (0 coils, 1 discrete inputs, 2 holding, 3 input
    registers) of ``unit`` from ``start`` take ``state`` and, when valid, ``values``."""

    unit: int
    area: int
    start: int
    state: int
    values: Sequence[int]


class Request(NamedTuple):
    """A request the C loop hands to Python: the connection (slot and generation, for
    :meth:`ServerCore.post`), the request ADU (MBAP header, unit id, PDU) and the
    master's IPv4 address (an int, host byte order)."""

    conn: int
    gen: int
    adu: bytes
    src: int = 0


class ServerCounters(NamedTuple):
    accepted: int
    refused: int
    closed_idle: int
    closed_bad: int
    closed_peer: int
    requests: int
    cached_replies: int
    to_python: int
    exceptions: dict[int, int]
    accept_errors: int = 0  # accept failed for want of fds or memory: accepting paused
    accept_errno: int = 0   # the last of those failures' errno
    refused_source: int = 0  # connections from outside the server's allow-list (reset)
    refused_unit: int = 0    # requests from outside their unit's allow-list (0A)


class ServerCore:
    """One ``emb_server`` (see the module's docstring)."""

    def __init__(self, host: str, port: int, *, max_connections: int, idle_timeout: float,
                 backlog: int = 64) -> None:
        ptr = lib.emb_sv_new(host.encode(), port, backlog, max_connections,
                             int(idle_timeout * 1e9))
        if ptr == ffi.NULL:
            err = ffi.errno
            raise OSError(err, f"Modbus TCP server: cannot listen on {host}:{port}: "
                               f"{os.strerror(err)}")
        self._ptr = ptr
        self._lock = threading.Lock()  # the pointer's lifetime against close()
        self.port: int = lib.emb_sv_port(ptr)

    def set_unit(self, unit: int, mode: int, spans: Sequence[tuple[int, int]] = ()) -> None:
        """Serve ``unit`` in ``mode``; a cached unit's image covers ``spans`` (start,
        count) of the four areas, every address unmapped until :meth:`update`."""
        flat = [x for span in (list(spans) or [(0, 0)] * 4) for x in span]
        with self._lock:
            if lib.emb_sv_unit_set(self._live(), unit, mode, ffi.new("int[8]", flat)) < 0:
                err = ffi.errno
                raise OSError(err, f"serve: unit {unit}: no image ({os.strerror(err)})")

    def allow(self, unit: int | None, nets: Sequence[tuple[int, int]]) -> None:
        """The allow-list of the server (``unit`` None: connections accepted from now
        on) or of ``unit`` (every request): IPv4 (address, netmask) pairs as ints;
        empty: every source."""
        if len(nets) > MAX_NETS:
            raise ValueError(f"at most {MAX_NETS} networks per allow-list, not {len(nets)}")
        flat = [x for net in nets for x in net] or [0]
        with self._lock:
            if lib.emb_sv_allow(self._live(), -1 if unit is None else unit,
                                ffi.new("uint32_t[]", flat), len(nets)) < 0:
                raise ValueError(f"serve: allow-list of {unit}: {os.strerror(ffi.errno)}")

    def set_fresh(self, unit: int, until_ns: int) -> None:
        """Reads of ``unit`` after ``until_ns`` (``time.monotonic_ns``) get exception 0B."""
        with self._lock:
            if self._ptr is not None:  # (a driver's callback racing close(): nothing to do)
                lib.emb_sv_unit_fresh(self._ptr, unit, until_ns)

    def update(self, runs: Sequence[ImageRun]) -> None:
        """Apply ``runs`` to the images in one C call (one lock of the server); nothing
        once the server is closed."""
        if not runs:
            return
        ops = ffi.new("emb_sv_run_op[]", len(runs))
        values: list[int] = []
        for op, run in zip(ops, runs, strict=True):
            op.unit, op.area, op.start, op.state = run.unit, run.area, run.start, run.state
            op.count = len(run.values)
            op.first = len(values)
            values += run.values
        buf = ffi.new("uint16_t[]", values or [0])
        with self._lock:
            if self._ptr is not None:  # (a driver's callback racing close(): nothing to do)
                lib.emb_sv_update(self._ptr, ops, len(runs), buf)

    def post(self, conn: int, gen: int, kind: int, data: bytes) -> bool:
        """Answer the request of connection ``conn`` (generation ``gen``); False when the
        connection is gone (the answer is dropped)."""
        with self._lock:
            if self._ptr is None:
                return False
            return bool(lib.emb_sv_post(self._ptr, conn, gen, kind, data, len(data)) > 0)

    def run(self, until_ns: int) -> int:
        """Serve until ``until_ns`` (``time.monotonic_ns``) or an event (EV_*)."""
        return int(lib.emb_sv_run(self._live(), until_ns))

    def request(self) -> Request:
        """The request of the last EV_REQUEST."""
        ptr = self._live()
        return Request(ptr.ev_conn, ptr.ev_gen, bytes(ffi.buffer(ptr.ev_adu, ptr.ev_len)),
                       ptr.ev_src)

    def stale(self, unit: int) -> tuple[int, int]:
        """``unit``'s reads answered 0B since it was set: (older than its max age, an
        item Invalid or not read yet); (0, 0) once the server is closed."""
        out = ffi.new("uint64_t[2]")
        with self._lock:
            if self._ptr is not None:
                lib.emb_sv_unit_stale(self._ptr, unit, out)
        return int(out[lib.EMB_SV_STALE_AGE]), int(out[lib.EMB_SV_STALE_INVALID])

    def counters(self) -> ServerCounters:
        """The C loop's counters, read live."""
        with self._lock:
            c = self._live().c
            return ServerCounters(c.accepted, c.refused, c.closed_idle, c.closed_bad,
                                  c.closed_peer, c.requests, c.cached_replies, c.to_python,
                                  {k: c.exceptions[k] for k in range(12) if c.exceptions[k]},
                                  c.accept_errors, c.accept_errno, c.refused_source,
                                  c.refused_unit)

    def open_connections(self) -> int:
        with self._lock:
            return int(lib.emb_sv_open_connections(self._live()))

    def stop(self) -> None:
        """Any thread: make :meth:`run` return EV_STOP."""
        with self._lock:
            if self._ptr is not None:
                lib.emb_sv_stop(self._ptr)

    def close(self) -> None:
        """Close every socket and free the images (after the run thread ended)."""
        with self._lock:
            ptr, self._ptr = self._ptr, None
            if ptr is not None:
                lib.emb_sv_free(ptr)

    def _live(self) -> Any:
        if self._ptr is None:
            raise RuntimeError("the Modbus TCP server is closed")
        return self._ptr
