"""Listen mode (``rtu-over-tcp-server``), heartbeat and framing checks of the
communication parameters, and the source-address lists of the listen keys.

:func:`listen_problems` is the cross-field part of :class:`DriverModbusRtuParameter`'s
validation that concerns DTUs (communication.py calls it with the model); like the
other listen keys, the listen-port and DTU keys are checked against each other only with
transport ``rtu-over-tcp-server`` (elsewhere they are ignored), while each value's own
form (a range, a network) is checked whatever the transport.  :func:`network` and
:func:`allow_list` read ``listenAllowFrom``/``dtuAllowFrom``; :func:`networks` and
:func:`key_bytes` give the driver what the listener takes.
"""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Iterable
from typing import Any, Protocol

from pydantic import SecretStr

from .._ffi import MAX_HEARTBEAT
from .problems import ConfigError, Problem, WrongType

NETWORKS_ALLOWED = ("an IPv4 or IPv6 network in CIDR notation or a single address, e.g. "
                    "10.0.0.0/8, 192.168.1.7, 2001:db8::/32")
KEY_EXAMPLE = r"ID:(\d+);KEY:(?P<key>\w+)"
STREAMS = ("rtu-over-tcp", "rtu-over-tcp-server", "mqtt-dtu")
"""The transports whose link is a DTU stream: heartbeats and wrapped frames apply."""
LOOP_TRANSPORTS = ("rtu-over-tcp-server", "rtu-over-tcp", "tcp")
"""The transports the loop engine serves (engine "loop": line/loop.py)."""


class ListenParams(Protocol):
    """What the listen checks read of DriverModbusRtuParameter (no import of it here:
    communication.py imports this module)."""

    @property
    def transport(self) -> str: ...
    @property
    def listen_host(self) -> str: ...
    @property
    def dtu_id(self) -> str: ...
    @property
    def registration(self) -> str: ...
    @property
    def registration_pattern(self) -> str: ...
    @property
    def registration_length(self) -> int | None: ...
    @property
    def registration_max_bytes(self) -> int: ...
    @property
    def registration_key(self) -> SecretStr: ...
    @property
    def heartbeat(self) -> str: ...
    @property
    def heartbeat_hex(self) -> str: ...
    @property
    def heartbeat_bytes(self) -> bytes: ...
    @property
    def framing(self) -> str: ...
    @property
    def echo(self) -> bool: ...
    @property
    def engine(self) -> str: ...


# --------------------------------------------------------------------------- source lists


def network(text: str) -> str:
    """One entry of an allow-list, normalised (``10.0.0.7`` -> ``10.0.0.7/32``,
    ``2001:DB8::/32`` -> ``2001:db8::/32``).  ValueError says what is allowed; a network
    with host bits set is refused with the network it lies in (a typo in an allow-list
    should not widen or shift it silently)."""
    text = text.strip()
    try:
        return str(ipaddress.ip_network(text))
    except ValueError:
        pass
    try:
        wider = ipaddress.ip_network(text, strict=False)
    except ValueError:
        raise ValueError(f"must be {NETWORKS_ALLOWED}") from None
    raise ValueError(f"has host bits set: use {wider}, or the single address "
                     f"{text.partition('/')[0]}")


def allow_list(value: Any) -> Any:
    """An allow-list as given: a list of texts, or one text of them separated by commas
    or blanks (the form a text box gives); anything else is refused whole."""
    if isinstance(value, str):
        return tuple(part for part in re.split(r"[\s,]+", value) if part)
    if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
        return tuple(value)
    raise WrongType(f"must be a list of networks ({NETWORKS_ALLOWED}), or one text of "
                    "them separated by commas")


def networks(values: Iterable[str], key: str) -> tuple[str, ...]:
    """An allow-list as the listener takes it: normalised, sorted, without repeats (so
    that devices listing one set in another order agree).  A value changed after loading
    is checked again: ConfigError names ``communication.<key>[i]``."""
    found: set[str] = set()
    problems: list[Problem] = []
    for i, value in enumerate(values):
        try:
            found.add(network(value))
        except (ValueError, AttributeError) as exc:
            problems.append(Problem(f"communication.{key}[{i}]", value, str(exc)))
    if problems:
        raise ConfigError(problems)
    return tuple(sorted(found))


LATIN1 = ("must be Latin-1 text (the registration packet is read as Latin-1, one "
          "character per byte)")


def key_bytes(key: SecretStr) -> bytes:
    """registrationKey as the bytes it is compared with (the registration packet is read
    as Latin-1); ConfigError, without the key, when it is not Latin-1 text."""
    try:
        return key.get_secret_value().encode("latin-1")
    except UnicodeEncodeError:
        raise ConfigError([Problem("communication.registrationKey", key,
                                   LATIN1)]) from None


def check_key(key: SecretStr) -> SecretStr:
    """The field check of registrationKey: Latin-1 text (the error shows it masked)."""
    try:
        key.get_secret_value().encode("latin-1")
    except UnicodeEncodeError:
        raise ValueError(LATIN1) from None
    return key


# --------------------------------------------------------------------------- cross checks


def listen_problems(p: ListenParams) -> list[Problem]:
    """Listen mode, registration, heartbeat, framing and engine options, checked
    together."""
    problems: list[Problem] = []
    if p.transport == "rtu-over-tcp-server":
        problems += _registration_problems(p)
    problems += _heartbeat_problems(p)
    if p.framing == "wrapped-report" and p.transport not in STREAMS:
        problems.append(Problem("framing", p.framing, "needs transport rtu-over-tcp, "
                                f"rtu-over-tcp-server or mqtt-dtu, not {p.transport!r}"))
    if p.framing == "wrapped-report" and p.echo:
        problems.append(Problem("echo", p.echo, "no echo option with framing "
                                "wrapped-report"))
    if p.echo and p.transport == "tcp":
        problems.append(Problem("echo", p.echo, "a Modbus TCP (MBAP) link has no "
                                "request echo; the option is for RTU lines"))
    if p.engine == "loop" and p.transport not in LOOP_TRANSPORTS:
        problems.append(Problem("engine", p.engine, "the loop engine serves transports "
                                f"{', '.join(LOOP_TRANSPORTS)}, not {p.transport!r}; "
                                "use engine 'thread'"))
    return problems


def _registration_problems(p: ListenParams) -> list[Problem]:
    """transport rtu-over-tcp-server: the host, the DTU's id, the registration options."""
    problems: list[Problem] = []
    if not p.listen_host.strip():
        problems.append(Problem("listenHost", p.listen_host, "a host is required"))
    if p.registration != "none" and not p.dtu_id:
        problems.append(Problem("dtuId", p.dtu_id, f"required with registration "
                                f"{p.registration!r}"))
    if p.registration == "hex":
        try:
            if not bytes.fromhex(p.dtu_id):
                raise ValueError
        except ValueError:
            problems.append(Problem("dtuId", p.dtu_id, "registration hex needs hex "
                                    "bytes, e.g. '38 36 31 30'"))
    heartbeat = _heartbeat_or_none(p)
    if heartbeat and p.registration in ("text", "hex") and p.dtu_id and \
            not _id_bytes(p).replace(heartbeat, b""):
        problems.append(Problem("dtuId", p.dtu_id, "is nothing but the heartbeat "
                                f"{p.heartbeat_hex or p.heartbeat!r}, which is skipped "
                                "wherever it arrives: the DTU could never register"))
    pattern: re.Pattern[str] | None = None
    if p.registration == "regex":
        try:
            pattern = re.compile(p.registration_pattern)
            if not p.registration_pattern:
                raise re.error("empty pattern")
        except re.error as exc:
            pattern = None
            problems.append(Problem("registrationPattern", p.registration_pattern,
                                    f"not a regular expression: {exc}"))
    length = p.registration_length
    if length is not None and length > p.registration_max_bytes:
        problems.append(Problem("registrationLength", length, "must be at most "
                                f"registrationMaxBytes ({p.registration_max_bytes}): the "
                                "registration would never arrive in full"))
    if p.registration_key.get_secret_value():
        if p.registration != "regex":
            problems.append(Problem("registrationKey", p.registration_key, "needs "
                                    "registration 'regex' and a registrationPattern with a "
                                    f"group named key, e.g. {KEY_EXAMPLE}; registration is "
                                    f"{p.registration!r}"))
        elif pattern is not None and "key" not in pattern.groupindex:
            problems.append(Problem("registrationPattern", p.registration_pattern,
                                    "registrationKey needs a group named key, e.g. "
                                    f"{KEY_EXAMPLE}"))
        elif pattern is not None and pattern.groups == 1:
            # the id would be the whole match, the key in it (and in dtuId, which is logged)
            problems.append(Problem("registrationPattern", p.registration_pattern,
                                    "besides the group named key, the id needs a group "
                                    f"(named id, or any other), e.g. {KEY_EXAMPLE}"))
    return problems


def _heartbeat_or_none(p: ListenParams) -> bytes:
    """The heartbeat's bytes, b"" when there is none or it is not hex."""
    try:
        return p.heartbeat_bytes
    except ValueError:
        return b""


def _id_bytes(p: ListenParams) -> bytes:
    """dtuId as it is sent (hex mode: the bytes it spells; b"" if it is not hex)."""
    if p.registration != "hex":
        return p.dtu_id.encode()
    try:
        return bytes.fromhex(p.dtu_id)
    except ValueError:
        return b"?"  # reported as not hex


def _heartbeat_problems(p: ListenParams) -> list[Problem]:
    problems: list[Problem] = []
    if p.heartbeat and p.heartbeat_hex:
        problems.append(Problem("heartbeatHex", p.heartbeat_hex,
                                "give heartbeat (text) or heartbeatHex, not both"))
    if p.heartbeat_hex:
        try:
            if not bytes.fromhex(p.heartbeat_hex):
                raise ValueError
        except ValueError:
            problems.append(Problem("heartbeatHex", p.heartbeat_hex,
                                    "must be hex bytes, e.g. 'FE'"))
    if not any(q.path == "heartbeatHex" for q in problems) and \
            len(p.heartbeat_bytes) > MAX_HEARTBEAT:
        problems.append(Problem("heartbeatHex" if p.heartbeat_hex else "heartbeat",
                                p.heartbeat_hex or p.heartbeat,
                                f"at most {MAX_HEARTBEAT} bytes"))
    if (p.heartbeat or p.heartbeat_hex) and p.transport not in STREAMS:
        problems.append(Problem("heartbeat", p.heartbeat or p.heartbeat_hex,
                                "heartbeats apply to DTU streams (rtu-over-tcp, "
                                "rtu-over-tcp-server, mqtt-dtu)"))
    return problems


__all__ = ["KEY_EXAMPLE", "NETWORKS_ALLOWED", "ListenParams", "allow_list", "check_key",
           "key_bytes", "listen_problems", "network", "networks"]
