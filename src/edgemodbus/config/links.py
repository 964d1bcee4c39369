"""The link keys of the communication parameters (docs/links.md): backup endpoints
(``alternates``, ``failoverAfter``, ``failbackInterval``), parallel Modbus TCP
connections (``connections``, ``channel``) and serial hardware flow control
(``flowControl``).

:class:`LinkFields` holds the fields (communication.py's model inherits them after its
own, so the descriptor lists them last); :func:`link_problems` checks them against the
transport and each other, the cross-field part communication.py calls with the model.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal, Protocol

from pydantic import BeforeValidator, Field, field_validator

from .base import MAX_MS, Model, Range, lower_literal
from .limits import MAX_NAME, check_host
from .problems import Problem, WrongType

FlowControl = Literal["none", "rtscts"]
MAX_ALTERNATES = 8
MAX_CONNECTIONS = 16
ALTERNATES_ALLOWED = ("alternate endpoints of the line's own kind: host:port (or "
                      "[IPv6]:port) for a TCP line, a serial port (e.g. /dev/ttyUSB1, COM4) "
                      "for a serial line")


def _alternates(value: Any) -> Any:
    """A list of texts, or one text of them separated by commas or blanks."""
    if isinstance(value, str):
        return tuple(part for part in re.split(r"[\s,]+", value) if part)
    if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
        return tuple(value)
    raise WrongType(f"must be a list of {ALTERNATES_ALLOWED}")


Alternates = Annotated[tuple[str, ...], BeforeValidator(_alternates)]


class LinkFields(Model):
    """The link keys (see the module docstring); validated together in
    :func:`link_problems`."""

    alternates: Alternates = Field(
        default=(),
        description="Backup endpoints of the line, tried in turn after failoverAfter "
        "failed connects or failed cycles: host:port for rtu-over-tcp and tcp (a "
        "redundant network path, a second serial server), serial ports for rtu (same "
        f"settings); at most {MAX_ALTERNATES}",
    )
    failover_after: Annotated[int, Range(1, 100)] = Field(
        default=3,
        description="With alternates: failed connects in a row, or failed cycles in a "
        "row of every device on the line, before it moves to the next endpoint",
    )
    failback_interval: Annotated[int, Range(0, MAX_MS)] = Field(
        default=30000,
        description="With alternates: while on an alternate, probe the primary this often "
        "(a connect, or opening the serial port) and move back once it succeeds (ms); "
        "0 = stay until the alternate fails",
    )
    connections: Annotated[int, Range(1, MAX_CONNECTIONS)] = Field(
        default=1,
        description="Modbus TCP (transport tcp): connections to this host:port (a gateway "
        "with several serial ports behind one IP); devices are spread over them by unit "
        "id (or channel), each connection polled on its own, so a dead slave on one port "
        "does not slow the others; every device of the endpoint must give the same number",
    )
    channel: Annotated[int | None, Range(0, MAX_CONNECTIONS - 1)] = Field(
        default=None,
        description="With connections > 1: the connection (0..connections-1) this device "
        "is polled on; empty = its unit id modulo connections (ignored with one "
        "connection)",
    )
    flow_control: FlowControl = Field(
        default="none",
        description="Serial (transport rtu; ignored on TCP lines): none, or rtscts "
        "(hardware flow control, the RTS/CTS handshake some adapters need); not with "
        "RS-485 direction control (rs485)",
    )

    @field_validator("flow_control", mode="before")
    @classmethod
    def _lower_flow(cls, value: Any) -> Any:
        return lower_literal(value)


class LinkParams(Protocol):
    """What the link checks read of DriverModbusRtuParameter."""

    @property
    def transport(self) -> str: ...
    @property
    def com_port(self) -> str: ...
    @property
    def tcp_host(self) -> str: ...
    @property
    def tcp_port(self) -> int: ...
    @property
    def slave_id(self) -> int: ...
    @property
    def rs485(self) -> str: ...
    @property
    def alternates(self) -> tuple[str, ...]: ...
    @property
    def connections(self) -> int: ...
    @property
    def channel(self) -> int | None: ...
    @property
    def flow_control(self) -> str: ...


def split_host_port(text: str) -> tuple[str, int]:
    """``host:port`` or ``[IPv6]:port`` as (host, port); ValueError says what is
    allowed."""
    match = re.fullmatch(r"\[([0-9A-Fa-f:.]+)\]:(\d{1,5})|([^\s:\[\]]+):(\d{1,5})", text)
    if match is None:
        raise ValueError("must be host:port (or [IPv6]:port) on a TCP line, e.g. "
                         "10.0.1.20:502")
    host = match.group(1) or match.group(3)
    port = int(match.group(2) or match.group(4))
    if not 1 <= port <= 65535:
        raise ValueError(f"port {port}: must be 1..65535")
    return check_host(host), port


def link_problems(p: LinkParams) -> list[Problem]:
    """alternates, connections, channel and flowControl against the transport."""
    problems = _alternate_problems(p)
    if p.connections > 1 and p.transport != "tcp":
        problems.append(Problem("connections", p.connections, "more than one connection "
                                "is for Modbus TCP (transport tcp), whose transaction ids "
                                f"pair replies with requests; transport is {p.transport!r}"))
    if p.channel is not None and 1 < p.connections <= p.channel:  # one connection: ignored
        problems.append(Problem("channel", p.channel, f"must be 0..{p.connections - 1} "
                                f"(connections is {p.connections})"))
    if p.flow_control != "none" and p.rs485 != "none":  # (both ignored off serial lines)
        problems.append(Problem("flowControl", p.flow_control, "RTS/CTS flow control and "
                                f"RS-485 direction control (rs485 {p.rs485!r}) both drive "
                                "RTS: use one, rs485 'none' with rtscts"))
    return problems


def _alternate_problems(p: LinkParams) -> list[Problem]:
    if not p.alternates:
        return []
    if p.transport in ("rtu-over-tcp-server", "mqtt-dtu"):
        return [Problem("alternates", list(p.alternates), "a DTU that dials in "
                        f"({p.transport}) picks its own path; alternates are for "
                        "lines we open (rtu, rtu-over-tcp, tcp)")]
    problems: list[Problem] = []
    if len(p.alternates) > MAX_ALTERNATES:
        problems.append(Problem("alternates", len(p.alternates),
                                f"at most {MAX_ALTERNATES} alternates"))
    seen: set[object] = set()
    for i, text in enumerate(p.alternates):
        where = f"alternates[{i}]"
        if len(text) > MAX_NAME:
            problems.append(Problem(where, text[:32] + "...", f"at most {MAX_NAME} characters"))
            continue
        try:
            target = _target(p, text)
        except ValueError as exc:
            problems.append(Problem(where, text, str(exc)))
            continue
        primary = p.com_port if p.transport == "rtu" else (p.tcp_host, p.tcp_port)
        if target == primary or target in seen:
            problems.append(Problem(where, text, "repeats the primary endpoint or another "
                                    "alternate"))
        seen.add(target)
    return problems


def _target(p: LinkParams, text: str) -> str | tuple[str, int]:
    """One alternate, checked against the line's kind."""
    if p.transport == "rtu":
        if re.fullmatch(r"\[?[\w.\-:]*\]?:\d{1,5}", text) and not text.startswith("/"):
            raise ValueError("a serial line's alternates are serial ports (e.g. "
                             "/dev/ttyUSB1); host:port is for rtu-over-tcp and tcp lines")
        return text
    return split_host_port(text)


__all__ = ["ALTERNATES_ALLOWED", "FlowControl", "LinkFields", "LinkParams", "link_problems",
           "split_host_port"]
