"""Opening a link: a TCP connection of our own, and a :class:`~edgemodbus.line.link.ContextLink`
on a libmodbus context with the line's settings (timeouts, echo, a serial line's character
time, a DTU stream's heartbeat and wrapped framing)."""

from __future__ import annotations

import errno
import socket
import termios
from collections.abc import Callable

from .._ffi import Context
from ..errors import ModbusConnectionError, ModbusError
from ..protocol.wrapped import Report
from ..stats import LineStats
from .endpoint import (
    DtuEndpoint,
    Endpoint,
    LineTiming,
    MqttDtuEndpoint,
    SerialPort,
    TcpEndpoint,
)
from .link import ContextLink


def connect_tcp(ep: TcpEndpoint, timeout: float) -> socket.socket:
    """Connect with a bounded time, then hand a blocking, no-delay socket to libmodbus."""
    try:
        sock = socket.create_connection((ep.host, ep.port), timeout=timeout)
    except TimeoutError:
        raise ModbusConnectionError(
            f"{ep.describe()}: connect timed out after {timeout:g} s"
        ) from None
    except OSError as exc:
        raise ModbusConnectionError(f"{ep.describe()}: connect failed: {exc.strerror or exc}") \
            from None
    except UnicodeError as exc:  # the IDNA codec refuses the name before any lookup
        raise ModbusConnectionError(
            f"{ep.describe()}: connect failed: host name {ep.host!r} is not a valid DNS "
            f"name (labels of 1..63 characters, no empty label): {exc}") from None
    sock.settimeout(None)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    return sock


def set_rtscts(fd: int, port: str) -> None:
    """Hardware flow control on an open serial port: CRTSCTS (termios(3)), which
    libmodbus's connect clears with the rest of c_cflag.  A driver that drops the flag
    (no RTS/CTS lines) is a connection error that says so."""
    try:
        attrs = termios.tcgetattr(fd)
        attrs[2] |= termios.CRTSCTS
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
        if not termios.tcgetattr(fd)[2] & termios.CRTSCTS:
            raise OSError(errno.ENOTSUP, "the driver did not keep CRTSCTS")
    except (OSError, termios.error) as exc:
        raise ModbusConnectionError(
            f"serial port {port}: cannot set RTS/CTS flow control ({exc}); use "
            "flowControl 'none'") from None


def context_link(ctx: Context, endpoint: Endpoint, timing: LineTiming, stats: LineStats,
                 sock: socket.socket | None,
                 on_close: Callable[[], None] | None = None,
                 on_report: Callable[[Report], None] | None = None) -> ContextLink:
    """A link on ``ctx`` with the line's timeouts, echo, character time (serial) and
    DTU stream framing (heartbeat, wrapped reports to ``on_report``) set.  A setting the
    context refuses (ValueError) closes ``ctx``; ``sock`` is left to the caller."""
    try:
        ctx.set_timeouts(timing.response_timeout, timing.byte_timeout)
        ctx.set_echo(endpoint.echo)
        if isinstance(endpoint, SerialPort):
            ctx.set_char_time(endpoint.char_time)
        elif isinstance(endpoint, (DtuEndpoint, MqttDtuEndpoint)) or \
                endpoint.transport == "rtu-over-tcp":
            ctx.set_stream(endpoint.heartbeat, endpoint.framing == "wrapped-report")
    except ValueError:
        ctx.close()
        raise
    return ContextLink(ctx, endpoint, timing, stats, sock, on_close,
                       timeouts=(timing.response_timeout, timing.byte_timeout),
                       on_report=on_report)


def open_socket_link(sock: socket.socket, endpoint: Endpoint, timing: LineTiming,
                     stats: LineStats, on_close: Callable[[], None] | None = None,
                     on_report: Callable[[Report], None] | None = None) -> ContextLink:
    """A link on a connected socket we own (RTU over TCP, no MBAP; heartbeats and
    wrapped frames as the endpoint says).  On failure the socket is left to the
    caller."""
    ctx = Context.on_socket(sock.fileno(), endpoint.describe(), mbap=False)
    return context_link(ctx, endpoint, timing, stats, sock, on_close, on_report)


def open_link(ep: SerialPort | TcpEndpoint, timing: LineTiming, stats: LineStats,
              on_report: Callable[[Report], None] | None = None) -> ContextLink:
    """Open a serial port or connect to a TCP peer and return the link on it, with the
    line's settings (see :func:`context_link`).  Used by the line worker, and by callers
    that own one line on their own thread (edgemodbus.commission's scan).  Raises
    :class:`ModbusConnectionError` (or ValueError for a setting the context refuses);
    nothing stays open on failure."""
    if isinstance(ep, SerialPort):
        ctx = Context.rtu(ep.port, ep.baudrate, ep.parity, ep.data_bits, ep.stop_bits)
        try:
            ctx.connect(ep.rs485)
            if ep.flow_control == "rtscts":
                set_rtscts(ctx.fd, ep.port)
        except ModbusError:
            ctx.close()
            raise
        sock = None
    else:
        sock = connect_tcp(ep, timing.connect_timeout)
        try:
            ctx = Context.on_socket(sock.fileno(), ep.describe(), mbap=ep.transport == "tcp")
        except ModbusError:
            sock.close()
            raise
    try:  # heartbeats and wrapped reports are framed in C (csrc/emb_stream.c)
        return context_link(ctx, ep, timing, stats, sock, on_report=on_report)
    except ValueError:
        if sock is not None:
            sock.close()
        raise
