"""Communication parameters: :class:`DriverModbusRtuParameter` (the seed's
``modbusRtu.json`` plus ours; :class:`Parity` is compat.py's).

Limits are those of the layers that use the values (one source of truth): block sizes
come from the planner, offsets from the address parser.  Parity is stored as
:class:`Parity` (a str enum of libmodbus's ``"N"``, ``"O"``, ``"E"``); the spellings
compat.py lists are accepted.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, ClassVar, Literal

from pydantic import (
    AfterValidator,
    BeforeValidator,
    ConfigDict,
    Field,
    SecretStr,
    field_serializer,
    field_validator,
    model_validator,
)

from ..datatypes import DataFormat, DataFormat64
from ..protocol.address import MAX_OFFSET
from ..protocol.limits import (
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
    MAX_SLAVE_ID,
    MAX_UNIT_ID,
    MIN_SLAVE_ID,
    slave_id_problem,
)
from .base import (
    MAX_MS,
    READ_CYCLE_RANGE,
    Choice,
    Model,
    Ms,
    OptionalMs,
    Range,
    check_encoding,
    lower_literal,
    parse_format,
)
from .compat import NG_KEYS, Parity, ng_aliases
from .limits import MAX_HOST, MAX_NAME, check_host
from .links import LinkFields, link_problems
from .listen import KEY_EXAMPLE, NETWORKS_ALLOWED, allow_list, check_key, listen_problems, network
from .mqtt_dtu import MqttDtuFields, mqtt_dtu_problems
from .problems import NO_VALUE, ConfigError, Problem
from .secret import Secret

Transport = Literal["rtu-over-tcp-server", "rtu", "rtu-over-tcp", "tcp", "mqtt-dtu"]
Framing = Literal["rtu", "wrapped-report"]
Registration = Literal["none", "text", "hex", "regex"]
AddressPrefixOption = Literal["function-code", "modicon", "entity"]
ReportMode = Literal["change", "cycle"]
Rs485Mode = Literal["none", "kernel", "rts-up", "rts-down"]
DuplicateId = Literal["keep-existing", "replace"]
DtuEngine = Literal["auto", "thread", "loop"]
AllowFrom = Annotated[tuple[Annotated[str, AfterValidator(network)], ...],
                      BeforeValidator(allow_list)]
"""A source-address allow-list: networks (CIDR) or single addresses, normalised."""


_CAMEL = {"tcp_host": "tcpHost", "tcp_port": "tcpPort"}


class _CommunicationFields(Model):
    """The fields of :class:`DriverModbusRtuParameter` but the link keys (links.py)."""

    _extra_keys: ClassVar[tuple[str, ...]] = NG_KEYS
    _where: ClassVar[str] = "communication"
    _max_lengths: ClassVar[dict[str, int]] = {
        "comPort": MAX_NAME, "tcpHost": MAX_HOST, "listenHost": MAX_HOST, "dtuId": MAX_NAME,
        "heartbeat": MAX_NAME, "heartbeatHex": MAX_NAME, "encoding": MAX_NAME}
    # registrationKey is a secret: pydantic's own error text must not show the input
    model_config = ConfigDict(hide_input_in_errors=True)  # merged with Model's

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
    slave_id: Annotated[int, Range(0, MAX_UNIT_ID)] = Field(
        default=1,
        description=f"Modbus slave id of the device: {MIN_SLAVE_ID}..{MAX_SLAVE_ID} on RTU "
        f"lines (rtu, rtu-over-tcp), 0..{MAX_UNIT_ID} as a Modbus TCP unit id",
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
        "in (RTU frames over TCP); mqtt-dtu: a DTU that bridges RS-485 to topics on an MQTT "
        "broker (mqttHost, uplinkTopic, downlinkTopic, statusTopic). When absent: "
        "rtu-over-tcp if useTcp, else rtu; without useTcp either: rtu-over-tcp when "
        "tcpHost or tcpPort is given (not comPort), rtu otherwise; tcpHost/tcpPort and "
        "comPort together are refused as ambiguous",
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
        "with registration none; mqtt-dtu: the {dtuId} of its topics",
    )
    registration: Registration = Field(
        default="none",
        description="rtu-over-tcp-server: how DTUs identify themselves: none (the port's "
        "only DTU takes the connection), text (the first packet is dtuId), hex (the first "
        "packet is the bytes dtuId spells in hex), regex (registrationPattern's group "
        "named id, else its first group other than key, else its whole match, is the id)",
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
    # what a connection that has not registered may cost, who may connect and who may be
    # which DTU (the listener faces the internet); every device of a port must agree on
    # the port's keys, and every device behind one DTU on dtuAllowFrom and registrationKey
    registration_max_bytes: Annotated[int, Range(1, 65536)] = Field(
        default=256,
        description="rtu-over-tcp-server: bytes a new connection may send without "
        "registering (heartbeats included); then it is closed",
    )
    registration_byte_rate: Annotated[int, Range(0, 100_000_000)] = Field(
        default=1024,
        description="rtu-over-tcp-server: bytes per second read from a connection before it "
        "registers (0 = no limit)",
    )
    max_unregistered: Annotated[int, Range(1, 1_000_000)] = Field(
        default=512,
        description="rtu-over-tcp-server: connections of the port waiting to register; "
        "beyond it new ones are closed at once",
    )
    max_unregistered_per_source: Annotated[int, Range(1, 1_000_000)] = Field(
        default=64,
        description="rtu-over-tcp-server: the same, per source address",
    )
    listen_allow_from: AllowFrom = Field(
        default=(),
        description="rtu-over-tcp-server: source addresses that may connect to the port "
        f"({NETWORKS_ALLOWED}; a list, or one text separated by commas); empty = any",
    )
    duplicate_id: DuplicateId = Field(
        default="keep-existing",
        description="rtu-over-tcp-server: a second connection registering as a connected "
        "DTU: keep-existing (held for registrationTimeout, then refused if the old "
        "connection answered meanwhile, else it takes over) or replace (takes over at once)",
    )
    id_flip_limit: Annotated[int, Range(1, 1000)] = Field(
        default=5,
        description="rtu-over-tcp-server: an id that changes connection more often than "
        "this within idFlipWindow is contested (two DTUs claim it): both are closed and "
        "the id is refused for idFlipWindow",
    )
    id_flip_window: Ms = Field(
        default=60000,
        description="rtu-over-tcp-server: the window of idFlipLimit (ms)",
    )
    dtu_allow_from: AllowFrom = Field(
        default=(),
        description="rtu-over-tcp-server: source addresses that may register as this "
        "device's DTU (as listenAllowFrom); empty = as the port",
    )
    registration_key: Secret = Field(
        default=SecretStr(""),
        description="rtu-over-tcp-server with registration regex: the secret this "
        f"device's DTU sends in the registrationPattern group named key (e.g. {KEY_EXAMPLE}); "
        "compared in constant time, never shown nor logged",
    )
    engine: DtuEngine = Field(
        default="auto",
        description="rtu-over-tcp-server, rtu-over-tcp, tcp: what polls the line: auto (loop "
        "for plain DTUs, thread for wrapped ones and endpoints), loop (a few loop threads: any "
        "DTU, plain rtu-over-tcp and tcp endpoints without alternates; docs/scale.md) or "
        "thread (a thread per line); a port's or endpoint's devices must agree",
    )
    loop_threads: Annotated[int | None, Range(1, 1024)] = Field(
        default=None,
        description="engine loop: loop threads of the process (unset = one per core); the "
        "largest asked by the open lines wins, for threads started later (docs/scale.md)",
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
        description="Default data format for communication (byte order x word order) of "
        "values of two or more registers; a one-register value is never reordered by it",
    )
    byte_swap16: bool = Field(
        default=False,
        description="Swap the two bytes of one-register values (16-bit types, register "
        "bits); NG's byteOrder LittleEndian sets it",
    )
    data_format64: DataFormat64 | None = Field(
        default=None,
        description="Byte order of 64-bit values: ABCDEFGH, BADCFEHG, CDABGHEF, DCBAHGFE, "
        "EFGHABCD (first DWord low), FEHGBADC, GHEFCDAB, HGFEDCBA; default: dataFormat's",
    )
    max_block_read_register_count: Annotated[int, Range(1, MAX_READ_REGISTERS)] = Field(
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
    max_block_read_bit_count: Annotated[int, Range(1, MAX_READ_BITS)] = Field(
        default=MAX_READ_BITS,
        description="Maximum number of coils/discrete inputs to read in a single block",
    )
    address_prefix: AddressPrefixOption = Field(
        default="function-code",
        description="Numeric address types: function-code (3=holding, 4=input), modicon "
        "(3=input, 4=holding), or entity: Modicon entity numbers (40001 or 400001 = "
        "holding register 0, 30001 input, 10001 discrete input, 00001 coil; typed "
        "addresses such as hr:0 as under function-code)",
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
    forward_coalesce: Annotated[int, Range(0, MAX_MS)] = Field(
        default=0,
        description="Gateway forward mode: a forwarded read that a block of this device "
        "read within this many ms covers is answered from that block, with no line "
        "traffic (ms); 0 = off (every forwarded read goes to the slave)",
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
    report_mode: ReportMode = Field(default="change", description="change: report items "
                                    "whose value or status changed; cycle: every read")
    report_every: OptionalMs = Field(default=None, description="reportMode change: report an "
                                     "unchanged item again once its last report is this old (ms)")
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

    @field_validator("data_format64", mode="before")
    @classmethod
    def _format64(cls, value: Any) -> Any:
        if isinstance(value, str) and not value.strip():
            return None
        return parse_format(value, DataFormat64)

    @field_validator("transport", "address_prefix", "report_mode", "rs485", "framing",
                     "registration", "duplicate_id", mode="before")
    @classmethod
    def _lower(cls, value: Any) -> Any:
        return lower_literal(value)

    @field_validator("encoding")
    @classmethod
    def _encoding(cls, value: str) -> str:
        return check_encoding(value)

    @field_validator("tcp_host", "listen_host")
    @classmethod
    def _host(cls, value: str) -> str:
        return check_host(value)

    @field_validator("registration_key")
    @classmethod
    def _key(cls, value: SecretStr) -> SecretStr:
        return check_key(value)

    @model_validator(mode="before")
    @classmethod
    def _ng_aliases(cls, data: Any) -> Any:
        """NG spellings -> ours (after key normalisation); disagreements are errors."""
        if not isinstance(data, Mapping):
            return data
        return ng_aliases(cls.normalize_keys(data, cls._where))

    def _problems(self) -> list[Problem]:
        """The cross-field checks of these fields (transport, ids, listen mode)."""
        problems: list[Problem] = []
        fields_set = self.model_fields_set
        if "transport" not in fields_set:
            if "use_tcp" in fields_set:
                self.transport = "rtu-over-tcp" if self.use_tcp else "rtu"
            else:
                problems += self._infer_transport(fields_set)
        elif "use_tcp" not in fields_set:
            self.use_tcp = self.transport != "rtu"
        elif self.use_tcp != (self.transport != "rtu"):
            problems.append(
                Problem("useTcp", self.use_tcp, f"contradicts transport {self.transport!r}")
            )
        slave_problem = slave_id_problem(self.slave_id, self.transport)  # protocol/limits.py
        if slave_problem is not None:
            problems.append(Problem("slaveId", self.slave_id, slave_problem))
        if self.transport == "rtu" and not self.com_port.strip():
            problems.append(Problem("comPort", self.com_port, "a serial port is required"))
        if self.transport in ("rtu-over-tcp", "tcp") and not self.tcp_host.strip():
            problems.append(Problem("tcpHost", self.tcp_host, "a host is required"))
        return problems + listen_problems(self)

    def _infer_transport(self, fields_set: set[str]) -> list[Problem]:
        """Neither ``transport`` nor ``useTcp``: the transport the other keys name.

        The seed (driver-modbus-rtu-design.zh.md) calls ``UseTcp``/``TcpHost``/``TcpPort``
        its "TCP-over-RTU" settings: a ``tcpHost`` or ``tcpPort`` alone means RTU frames
        over TCP (a DTU, a serial server), never the serial port ``comPort`` defaults to;
        ``comPort`` alone means the serial line.  Both named: ambiguous, refused (the seed's
        own ``modbusRtu.json`` names both and says ``UseTcp: false``)."""
        tcp_keys = [k for k in ("tcp_host", "tcp_port") if k in fields_set]
        if not tcp_keys:
            self.transport, self.use_tcp = "rtu", False
            return []
        if "com_port" in fields_set:
            tcp = " and ".join(f"{_CAMEL[k]} {getattr(self, k)!r}" for k in tcp_keys)
            return [Problem("transport", NO_VALUE,
                            f"missing: comPort {self.com_port!r} and {tcp} are both "
                            "given; say which "
                            "line this is: transport 'rtu' (the serial port), "
                            "'rtu-over-tcp' (RTU frames over TCP: a DTU, a serial server) "
                            "or 'tcp' (Modbus TCP), or useTcp true/false")]
        self.transport, self.use_tcp = "rtu-over-tcp", True
        return []

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


class DriverModbusRtuParameter(MqttDtuFields, LinkFields, _CommunicationFields):
    """Communication parameters (the seed's ``modbusRtu.json`` plus ours).

    Times are int milliseconds.  ``transport`` defaults from ``useTcp`` (true ->
    ``rtu-over-tcp``), else from the keys given (``tcpHost``/``tcpPort`` without
    ``comPort``: ``rtu-over-tcp``; both: refused as ambiguous); NG's ``maxGap``,
    ``maxBatch`` and ``byteOrder``/``wordOrder`` are accepted for ``maxMergeAddressGap``,
    ``maxBlockReadRegisterCount`` and ``dataFormat``.  The link keys (alternates,
    connections, flowControl: config/links.py) and the MQTT DTU keys (mqtt_dtu.py) come
    last.
    """

    _max_lengths: ClassVar[dict[str, int]] = {
        **_CommunicationFields._max_lengths, "mqttHost": MAX_HOST, "mqttUsername": MAX_NAME,
        "mqttClientId": MAX_NAME}

    @model_validator(mode="after")
    def _cross_checks(self) -> DriverModbusRtuParameter:
        problems = self._problems() + link_problems(self) + mqtt_dtu_problems(self)
        if problems:
            raise ConfigError(problems)
        return self
