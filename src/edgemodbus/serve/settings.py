"""The ``serve`` section of the gateway file: where the Modbus TCP server listens, its
limits, and its units (a device served from the cache, or a device forwarded to).

```json
"serve": {"listen": "127.0.0.1:1502", "maxConnections": 16, "idleTimeoutS": 60,
          "maxPendingPerMaster": 8,
          "allowFrom": ["10.0.0.0/8", "127.0.0.1"],
          "units": [{"unitId": 1, "device": "meter1", "offset": 0, "maxAgeMs": 5000},
                    {"unitId": 9, "forward": "meter2", "timeoutMs": 1000,
                     "allowFrom": ["10.1.2.0/24"]}]}
```

``allowFrom`` (docs/links.md): the source networks (IPv4 CIDR or single addresses) a
connection may come from (others are reset at once) and, per unit, those whose requests
it answers (others get exception 0A, as for a unit not served); empty: any.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping, Sequence
from typing import Annotated, Any, ClassVar

from pydantic import (
    AfterValidator,
    BeforeValidator,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from .._ffi.serve import MAX_NETS
from ..config import ConfigError, Model, OptionalMs, Problem, Range
from ..config.limits import MAX_NAME, check_seconds
from ..config.listen import allow_list, network
from ..protocol.limits import MAX_UNIT_ID

DEFAULT_PORT = 502
#: Requests of one master (source address) waiting for a line at most, across its
#: connections (forwards, writes to served devices); one more is answered 06.
DEFAULT_PENDING_PER_MASTER = 8


def ipv4_network(text: str) -> str:
    """One entry of a server allow-list, normalised: an IPv4 network or address (the
    server listens on IPv4 only)."""
    normal = network(text)
    if ipaddress.ip_network(normal).version != 4:
        raise ValueError("the server listens on IPv4 only: use IPv4 networks or "
                         "addresses, e.g. 10.0.0.0/8, 192.168.1.7")
    return normal


def _bounded(nets: tuple[str, ...]) -> tuple[str, ...]:
    if len(nets) > MAX_NETS:
        raise ValueError(f"at most {MAX_NETS} networks, not {len(nets)}")
    return nets


AllowFrom = Annotated[tuple[Annotated[str, AfterValidator(ipv4_network)], ...],
                      BeforeValidator(allow_list), AfterValidator(_bounded)]
"""A server allow-list: IPv4 networks (CIDR) or single addresses, normalised."""


def ipv4_masks(nets: Sequence[str]) -> list[tuple[int, int]]:
    """An allow-list as the C server takes it: (address, netmask) ints.  ValueError
    names an entry that is not an IPv4 network or address."""
    masks = []
    for i, text in enumerate(nets):
        try:
            net = ipaddress.IPv4Network(ipv4_network(text))
        except ValueError as exc:
            raise ValueError(f"allowFrom[{i}] {text!r}: {exc}") from None
        masks.append((int(net.network_address), int(net.netmask)))
    return masks


class ServeUnit(Model):
    """One unit id of the server: ``device`` (served from the driver's latest values,
    at the device's own addresses plus ``offset``) or ``forward`` (every request passed
    to that device's slave on its line)."""

    _where: ClassVar[str] = "serve.units[]"
    _max_lengths: ClassVar[dict[str, int]] = {"device": MAX_NAME, "forward": MAX_NAME}

    unit_id: Annotated[int, Range(0, MAX_UNIT_ID)]
    device: str | None = None
    forward: str | None = None
    offset: Annotated[int, Range(-65535, 65535)] = 0
    max_age_ms: OptionalMs = None  # None: no age limit (Invalid items still get 0B)
    timeout_ms: OptionalMs = None  # forward: None is the device's readTimeout
    allow_from: AllowFrom = ()  # sources whose requests this unit answers (empty: any)

    @model_validator(mode="after")
    def _one_target(self) -> ServeUnit:
        if (self.device is None) == (self.forward is None):
            raise ValueError(f"unit {self.unit_id}: give exactly one of 'device' (serve "
                             "from the cache) and 'forward' (pass requests to the slave)")
        if self.forward is not None and (self.offset or self.max_age_ms is not None):
            raise ValueError(f"unit {self.unit_id}: 'offset' and 'maxAgeMs' are for a "
                             "'device' unit; a 'forward' unit passes requests unchanged")
        if self.device is not None and self.timeout_ms is not None:
            raise ValueError(f"unit {self.unit_id}: 'timeoutMs' is for a 'forward' unit")
        if self.timeout_ms == 0:
            raise ValueError(f"unit {self.unit_id}: timeoutMs 0: must be at least 1 ms")
        return self

    @property
    def target(self) -> str:
        """The device code this unit serves or forwards to."""
        return self.device if self.device is not None else str(self.forward)


class ServeSettings(Model):
    """The ``serve`` section of the gateway file."""

    _where: ClassVar[str] = "serve"
    _max_lengths: ClassVar[dict[str, int]] = {"listen": MAX_NAME}

    enabled: bool = True
    listen: str = f"127.0.0.1:{DEFAULT_PORT}"
    max_connections: Annotated[int, Range(1, 1024)] = 32
    # 0: never closed for idling; else at least 1 ms (a shorter one rounded to 0: never)
    idle_timeout_s: Annotated[float, Range(0, 86400), AfterValidator(check_seconds)] = 60.0
    allow_from: AllowFrom = ()  # sources that may connect (empty: any)
    max_pending_per_master: Annotated[int, Range(1, 64)] = Field(
        DEFAULT_PENDING_PER_MASTER, description="Requests of one master (source address) "
        "waiting for lines at most, across its connections (forwards, writes); one more is "
        "answered 06 (server busy), other masters are still served")
    units: list[ServeUnit] = Field(default_factory=list)

    @field_validator("listen")
    @classmethod
    def _listen(cls, value: str) -> str:
        split_listen(value)
        return value

    @model_validator(mode="after")
    def _unique(self) -> ServeSettings:
        seen: set[int] = set()
        for unit in self.units:
            if unit.unit_id in seen:
                raise ValueError(f"unitId {unit.unit_id} is given twice: each unit id "
                                 "serves one device")
            seen.add(unit.unit_id)
        return self

    @property
    def host(self) -> str:
        return split_listen(self.listen)[0]

    @property
    def port(self) -> int:
        return split_listen(self.listen)[1]

    @classmethod
    def load(cls, data: Mapping[str, Any], where: str = "serve") -> ServeSettings:
        """Validate a mapping; ConfigError with paths under ``where``."""
        try:
            return cls.model_validate(dict(data))
        except ValidationError as exc:
            raise ConfigError.from_validation_error(exc, where) from None


def split_listen(value: str) -> tuple[str, int]:
    """``"host:port"`` (an IPv4 address; ``0.0.0.0`` for every interface; port 0 for any
    free one) as (host, port); ValueError says what is allowed."""
    host, sep, port = value.rpartition(":")
    if not sep:
        host, port = value, str(DEFAULT_PORT)
    try:
        ipaddress.IPv4Address(host)
    except ValueError:
        raise ValueError(f"listen {value!r}: the host must be an IPv4 address such as "
                         "127.0.0.1 (0.0.0.0: every interface)") from None
    if not (port.isdigit() and 0 <= int(port) <= 65535):
        raise ValueError(f"listen {value!r}: the port must be 0..65535 (0: any free port)")
    return host, int(port)


def unknown_devices(settings: ServeSettings, devices: Sequence[str]) -> list[Problem]:
    """The units naming a device that is not among ``devices`` (device codes)."""
    return [
        Problem(f"serve.units[{i}].{'device' if unit.device is not None else 'forward'}",
                unit.target, f"no device has this deviceCode; known: "
                             f"{', '.join(sorted(devices)) or '(none)'}")
        for i, unit in enumerate(settings.units) if unit.target not in devices
    ]
