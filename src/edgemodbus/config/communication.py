"""Communication parameters: :class:`DriverModbusRtuParameter` (the seed's
``modbusRtu.json`` plus ours) and :class:`Parity`.

Limits are those of the layers that use the values (one source of truth): block sizes
come from the planner, offsets from the address parser.  Parity is stored as
:class:`Parity` (a str enum of libmodbus's ``"N"``, ``"O"``, ``"E"``); the spellings
compat.py lists are accepted.
"""

from __future__ import annotations

import enum
import re
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar, Literal

from pydantic import Field, field_serializer, field_validator, model_validator

from .._ffi import MAX_HEARTBEAT
from ..datatypes import DataFormat
from ..poll.planner import BIT_CAP, REGISTER_CAP
from ..protocol.address import MAX_OFFSET
from .base import (
    MAX_MS,
    READ_CYCLE_RANGE,
    Choice,
    Model,
    Ms,
    Range,
    check_encoding,
    lower_literal,
    parse_format,
)
from .compat import NG_KEYS, ng_aliases, parity_letter
from .problems import ConfigError, Problem, WrongType

Transport = Literal["rtu-over-tcp-server", "rtu", "rtu-over-tcp", "tcp"]
Framing = Literal["rtu", "wrapped-report"]
Registration = Literal["none", "text", "hex", "regex"]
AddressPrefixOption = Literal["function-code", "modicon"]
ReportMode = Literal["change", "cycle"]
Rs485Mode = Literal["none", "kernel", "rts-up", "rts-down"]


class Parity(str, enum.Enum):
    """Serial parity, as libmodbus spells it."""

    NONE = "N"
    ODD = "O"
    EVEN = "E"

    @classmethod
    def parse(cls, value: Any) -> Parity:
        if isinstance(value, Parity):
            return value
        letter = parity_letter(value)
        if letter is None:
            raise WrongType("use None|Odd|Even, 0|1|2 or N|O|E")
        return cls(letter)

    @property
    def number(self) -> int:
        """The seed descriptor's numbering: 0 = None, 1 = Odd, 2 = Even."""
        return {Parity.NONE: 0, Parity.ODD: 1, Parity.EVEN: 2}[self]


class DriverModbusRtuParameter(Model):
    """Communication parameters (the seed's ``modbusRtu.json`` plus ours).

    Times are int milliseconds.  ``transport`` defaults from ``useTcp`` (true ->
    ``rtu-over-tcp``); NG's ``maxGap``, ``maxBatch`` and ``byteOrder``/``wordOrder`` are
    accepted for ``maxMergeAddressGap``, ``maxBlockReadRegisterCount`` and ``dataFormat``.
    """

    _extra_keys: ClassVar[tuple[str, ...]] = NG_KEYS
    _where: ClassVar[str] = "communication"

    # Field order is the descriptor's order; its UI labels are in labels.py.
    com_port: str = Field(
        default="COM1",
        description="Serial COM port (e.g. COM1, /dev/ttyUSB0)",
    )
    baud_rate: Annotated[int, Range(1200, 921600)] = Field(
        default=9600,
        description="Baud rate of the serial line",
    )
    parity: Parity = Field(
        default=Parity.NONE,
        description="Parity setting (0=None, 1=Odd, 2=Even; also None/Odd/Even or N/O/E)",
    )
    data_bits: Annotated[int, Range(5, 8)] = Field(
        default=8,
        description="Number of data bits",
    )
    stop_bits: Annotated[int, Choice((1, 2))] = Field(
        default=1,
        description="Number of stop bits",
    )
    slave_id: Annotated[int, Range(0, 255)] = Field(
        default=1,
        description="Modbus slave id of the device: 1..247 on RTU lines (rtu, rtu-over-tcp), "
        "0..255 as a Modbus TCP unit id",
    )
    use_tcp: bool = Field(
        default=False,
        description="If true, use a TCP link (RTU frames over TCP unless transport says tcp) "
        "instead of a serial port",
    )
    tcp_host: str = Field(
        default="127.0.0.1",
        description="TCP host for RTU-over-TCP or Modbus TCP",
    )
    tcp_port: Annotated[int, Range(1, 65535)] = Field(
        default=502,
        description="TCP port for RTU-over-TCP or Modbus TCP",
    )
    transport: Transport = Field(
        default="rtu",
        description="rtu: serial RTU; rtu-over-tcp: raw RTU frames over TCP (DTU, serial "
        "server); tcp: Modbus TCP (MBAP); rtu-over-tcp-server: listen for DTUs that dial "
        "in (RTU frames over TCP). When absent: rtu-over-tcp if useTcp, else rtu",
    )
    listen_host: str = Field(
        default="0.0.0.0",
        description="rtu-over-tcp-server: address to listen on for DTUs",
    )
    listen_port: Annotated[int | None, Range(1, 65535)] = Field(
        default=None,
        description="rtu-over-tcp-server: port to listen on (empty = tcpPort); devices "
        "naming one port share its listener",
    )
    dtu_id: str = Field(
        default="",
        description="rtu-over-tcp-server: the registration id of the DTU this device is "
        "behind (text, hex bytes, or what registrationPattern extracts); empty only "
        "with registration none",
    )
    registration: Registration = Field(
        default="none",
        description="rtu-over-tcp-server: how DTUs identify themselves: none (the port's "
        "only DTU takes the connection), text (the first packet is dtuId), hex (the first "
        "packet is the bytes dtuId spells in hex), regex (registrationPattern's first "
        "group, else its whole match, is the id)",
    )
    registration_pattern: str = Field(
        default="",
        description="rtu-over-tcp-server with registration regex: a regular expression "
        "searched in the registration packet (Latin-1 text)",
    )
    registration_length: Annotated[int | None, Range(1, 1024)] = Field(
        default=None,
        description="rtu-over-tcp-server: fixed length of the registration packet in bytes "
        "(empty = as sent)",
    )
    registration_timeout: Annotated[int, Range(1, MAX_MS)] = Field(
        default=5000,
        description="rtu-over-tcp-server: a DTU that has not registered within this time "
        "is logged and closed (ms)",
    )
    heartbeat: str = Field(
        default="",
        description="Heartbeat packet DTUs send on idle links, as text (e.g. HB); "
        "discarded wherever it arrives and counted",
    )
    heartbeat_hex: str = Field(
        default="",
        description="Heartbeat packet as hex bytes (e.g. FE); instead of heartbeat",
    )
    framing: Framing = Field(
        default="rtu",
        description="rtu: plain RTU frames; wrapped-report: edge-MCU frames "
        "FF AA + register address + RTU frame + 0D, with unsolicited reports "
        "(RTU over TCP, client or listen mode)",
    )
    connect_timeout: Ms = Field(
        default=3000,
        description="Timeout of a TCP connect (ms)",
    )
    reconnect_interval: Ms = Field(
        default=5000,
        description="Wait before reopening a lost link (ms)",
    )
    read_timeout: Ms = Field(
        default=1000,
        description="Response timeout of one request (ms)",
    )
    byte_timeout: Ms = Field(
        default=200,
        description="Timeout between two bytes of one reply (ms)",
    )
    read_cycle: Annotated[int, READ_CYCLE_RANGE] = Field(
        default=1000,
        description="Polling cycle (ms); 0 = no polling: report-only (framing "
        "wrapped-report; on other framings nothing would update, which is logged)",
    )
    rs485: Rs485Mode = Field(
        default="none",
        description="RS-485 direction control: none, kernel (TIOCSRS485), rts-up, rts-down",
    )
    echo: bool = Field(
        default=False,
        description="The line echoes our own requests (some 2-wire adapters): skip the echo",
    )
    is_enable: bool = Field(
        default=True,
        description="Poll this device",
    )
    data_format: DataFormat = Field(
        default=DataFormat.ABCD,
        description="Default data format for communication (byte order x word order)",
    )
    max_block_read_register_count: Annotated[int, Range(1, REGISTER_CAP)] = Field(
        default=120,
        description="Maximum number of registers to read in a single block",
    )
    is_block_read_require_address_continuous: bool = Field(
        default=False,
        description="Indicates if block read requires continuous addresses (gap 0)",
    )
    max_merge_address_gap: Annotated[int, Range(0, MAX_OFFSET)] = Field(
        default=10,
        description="Maximum merge address gap when combining non-contiguous blocks",
    )
    max_block_read_bit_count: Annotated[int, Range(1, BIT_CAP)] = Field(
        default=BIT_CAP,
        description="Maximum number of coils/discrete inputs to read in a single block",
    )
    address_prefix: AddressPrefixOption = Field(
        default="function-code",
        description="Numeric address types: function-code (3=holding, 4=input) or modicon "
        "(3=input, 4=holding)",
    )
    address_base: Annotated[int, Choice((0, 1))] = Field(
        default=0,
        description="0: address offsets are protocol (0-based) addresses; 1: they are 1-based",
    )
    retries: Annotated[int, Range(0, 10)] = Field(
        default=1,
        description="Retries of a failed read before its items go Invalid",
    )
    request_interval: Annotated[int, Range(0, MAX_MS)] = Field(
        default=0,
        description="Silence kept between two requests on the line (ms)",
    )
    settle_timeout: Annotated[int | None, Range(0, MAX_MS)] = Field(
        default=None,
        description="After a timeout, discard late replies for this long before the next "
        "request (ms); empty = readTimeout, 0 = off",
    )
    offline_after_failed_cycles: Annotated[int, Range(1, 1000)] = Field(
        default=3,
        description="Failed cycles in a row before the device is reported Offline",
    )
    max_backoff: Ms = Field(
        default=60000,
        description="Longest wait between attempts on an offline device or lost link (ms)",
    )
    report_mode: ReportMode = Field(
        default="change",
        description="change: report items whose value or status changed; cycle: every read",
    )
    encoding: str = Field(
        default="utf-8",
        description="Text encoding of String items (a Python codec, e.g. utf-8, gbk)",
    )
    write_single_register_function: Annotated[int, Choice((6, 16))] = Field(
        default=6,
        description="Function code for writing a one-register value: 6 or 16",
    )
    snapshot_interval: Annotated[int, Range(0, MAX_MS)] = Field(
        default=0,
        description="Publish a device snapshot this often (ms); 0 = off",
    )

    @field_validator("parity", mode="before")
    @classmethod
    def _parity(cls, value: Any) -> Parity:
        return Parity.parse(value)

    @field_validator("data_format", mode="before")
    @classmethod
    def _format(cls, value: Any) -> Any:
        return parse_format(value)

    @field_validator("transport", "address_prefix", "report_mode", "rs485", "framing",
                     "registration", mode="before")
    @classmethod
    def _lower(cls, value: Any) -> Any:
        return lower_literal(value)

    @field_validator("encoding")
    @classmethod
    def _encoding(cls, value: str) -> str:
        return check_encoding(value)

    @model_validator(mode="before")
    @classmethod
    def _ng_aliases(cls, data: Any) -> Any:
        """NG spellings -> ours (after key normalisation); disagreements are errors."""
        if not isinstance(data, Mapping):
            return data
        return ng_aliases(cls.normalize_keys(data, cls._where))

    @model_validator(mode="after")
    def _cross_checks(self) -> DriverModbusRtuParameter:
        problems: list[Problem] = []
        fields_set = self.model_fields_set
        if "transport" not in fields_set:
            self.transport = "rtu-over-tcp" if self.use_tcp else "rtu"
        elif "use_tcp" not in fields_set:
            self.use_tcp = self.transport != "rtu"
        elif self.use_tcp != (self.transport != "rtu"):
            problems.append(
                Problem("useTcp", self.use_tcp, f"contradicts transport {self.transport!r}")
            )
        if self.transport == "tcp":
            pass  # a Modbus TCP unit id may be 0..255
        elif not 1 <= self.slave_id <= 247:
            problems.append(
                Problem(
                    "slaveId",
                    self.slave_id,
                    f"must be 1..247 on an RTU line (transport {self.transport!r}); "
                    "0..255 only as a Modbus TCP unit id",
                )
            )
        if self.transport == "rtu" and not self.com_port.strip():
            problems.append(Problem("comPort", self.com_port, "a serial port is required"))
        if self.transport in ("rtu-over-tcp", "tcp") and not self.tcp_host.strip():
            problems.append(Problem("tcpHost", self.tcp_host, "a host is required"))
        problems += self._dtu_checks()
        if problems:
            raise ConfigError(problems)
        return self

    def _dtu_checks(self) -> list[Problem]:
        """Listen mode, registration, heartbeat and framing options."""
        problems: list[Problem] = []
        server = self.transport == "rtu-over-tcp-server"
        if server:
            if not self.listen_host.strip():
                problems.append(Problem("listenHost", self.listen_host, "a host is required"))
            if self.registration != "none" and not self.dtu_id:
                problems.append(Problem("dtuId", self.dtu_id, f"required with registration "
                                        f"{self.registration!r}"))
            if self.registration == "hex":
                try:
                    if not bytes.fromhex(self.dtu_id):
                        raise ValueError
                except ValueError:
                    problems.append(Problem("dtuId", self.dtu_id, "registration hex needs hex "
                                            "bytes, e.g. '38 36 31 30'"))
            if self.registration == "regex":
                try:
                    re.compile(self.registration_pattern)
                    if not self.registration_pattern:
                        raise re.error("empty pattern")
                except re.error as exc:
                    problems.append(Problem("registrationPattern", self.registration_pattern,
                                            f"not a regular expression: {exc}"))
        if self.heartbeat and self.heartbeat_hex:
            problems.append(Problem("heartbeatHex", self.heartbeat_hex,
                                    "give heartbeat (text) or heartbeatHex, not both"))
        if self.heartbeat_hex:
            try:
                if not bytes.fromhex(self.heartbeat_hex):
                    raise ValueError
            except ValueError:
                problems.append(Problem("heartbeatHex", self.heartbeat_hex,
                                        "must be hex bytes, e.g. 'FE'"))
        if not any(p.path == "heartbeatHex" for p in problems) and \
                len(self.heartbeat_bytes) > MAX_HEARTBEAT:
            problems.append(Problem("heartbeatHex" if self.heartbeat_hex else "heartbeat",
                                    self.heartbeat_hex or self.heartbeat,
                                    f"at most {MAX_HEARTBEAT} bytes"))
        if (self.heartbeat or self.heartbeat_hex) and self.transport not in (
            "rtu-over-tcp", "rtu-over-tcp-server"
        ):
            problems.append(Problem("heartbeat", self.heartbeat or self.heartbeat_hex,
                                    "heartbeats apply to RTU over TCP (rtu-over-tcp, "
                                    "rtu-over-tcp-server)"))
        if self.framing == "wrapped-report" and self.transport not in (
            "rtu-over-tcp", "rtu-over-tcp-server"
        ):
            problems.append(Problem("framing", self.framing, "needs transport rtu-over-tcp or "
                                    f"rtu-over-tcp-server, not {self.transport!r}"))
        if self.framing == "wrapped-report" and self.echo:
            problems.append(Problem("echo", self.echo, "no echo option with framing "
                                    "wrapped-report"))
        if self.echo and self.transport == "tcp":
            problems.append(Problem("echo", self.echo, "a Modbus TCP (MBAP) link has no "
                                    "request echo; the option is for RTU lines"))
        return problems

    @property
    def heartbeat_bytes(self) -> bytes:
        """The heartbeat packet as bytes (empty: none configured)."""
        if self.heartbeat_hex:
            return bytes.fromhex(self.heartbeat_hex)
        return self.heartbeat.encode("latin-1", "replace")

    @property
    def effective_listen_port(self) -> int:
        """listenPort, else tcpPort (the issue accepts tcpPort as the listen port)."""
        return self.listen_port if self.listen_port is not None else self.tcp_port

    @field_serializer("parity")
    def _ser_parity(self, value: Parity) -> str:
        return value.value
