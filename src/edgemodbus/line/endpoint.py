"""What a line is: its endpoint (serial port, TCP peer, DTU behind a listener) and its
timing.  Plain data, shared by the line worker and the link (the counters the worker
keeps are :class:`edgemodbus.stats.LineStats`); :func:`endpoint_for` makes the endpoint
of a device's communication parameters."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

from ..config.links import split_host_port
from ..config.listen import STREAMS
from ..config.mqtt_dtu import topic_for
from ..datatypes import enum_value
from ..protocol.limits import MAX_RTU_ADU

if TYPE_CHECKING:
    from ..config import DriverModbusRtuParameter


@dataclass(frozen=True)
class SerialPort:
    """Settings of a serial line (Modbus over Serial Line v1.02, 2.5)."""

    port: str
    baudrate: int = 9600
    parity: str = "N"  # N, E or O
    data_bits: int = 8
    stop_bits: int = 1
    rs485: str = "none"  # none | kernel (TIOCSRS485) | rts-up | rts-down
    echo: bool = False  # the adapter echoes every request (2-wire, no echo suppression)
    flow_control: str = "none"  # none | rtscts (CRTSCTS set after libmodbus's termios)
    alternates: tuple[str, ...] = ()  # backup serial ports, same settings (failover.py)
    failover_after: int = 3  # with alternates: failed connects/cycles before moving on
    failback_interval: float = 30.0  # on an alternate: probe the primary this often (0: no)

    @property
    def key(self) -> tuple[str, ...]:
        return ("rtu", self.port)

    def targets(self) -> tuple[SerialPort, ...]:
        """The primary, then each alternate: the ports a failover line opens in turn."""
        return (replace(self, alternates=()),
                *(replace(self, port=port, alternates=()) for port in self.alternates))

    @property
    def char_time(self) -> float:
        """Seconds per character: start + data + parity + stop bits."""
        bits = 1 + self.data_bits + (0 if self.parity == "N" else 1) + self.stop_bits
        return bits / self.baudrate

    @property
    def frame_gap(self) -> float:
        """Silence between frames: 3.5 characters, fixed at 1.75 ms above 19200 baud
        (Modbus over Serial Line v1.02, 2.5.1.1)."""
        return 0.00175 if self.baudrate > 19200 else 3.5 * self.char_time

    def describe(self) -> str:
        return (
            f"{self.port} {self.baudrate} {self.data_bits}{self.parity}{self.stop_bits}"
            f" rs485={self.rs485}" + (" echo" if self.echo else "")
            + (" rtscts" if self.flow_control == "rtscts" else "")
        )

    @property
    def max_frame_time(self) -> float:
        """Seconds to transmit the largest RTU frame (256 bytes, Serial Line 2.5.1)."""
        return MAX_RTU_ADU * self.char_time


@dataclass(frozen=True)
class TcpEndpoint:
    """A TCP peer: raw RTU frames without MBAP ("rtu-over-tcp") or Modbus TCP ("tcp")."""

    host: str
    port: int
    transport: str = "rtu-over-tcp"
    echo: bool = False  # RTU over TCP: the serial side echoes every request
    framing: str = "rtu"  # rtu | wrapped-report (RTU over TCP only)
    heartbeat: bytes = b""  # a DTU's idle heartbeat packet, skipped (RTU over TCP only)
    alternates: tuple[tuple[str, int], ...] = ()  # backup host:port pairs (failover.py)
    failover_after: int = 3  # with alternates: failed connects/cycles before moving on
    failback_interval: float = 30.0  # on an alternate: probe the primary this often (0: no)
    connections: int = 1  # Modbus TCP: parallel connections to this host:port
    channel: int = 0  # which of them this line is (0..connections-1)
    engine: str = "thread"  # what serves the line: thread, or loop (line/loop.py)
    loop_threads: int | None = field(default=None, compare=False)  # the pool's, with loop

    def __post_init__(self) -> None:
        if self.transport not in ("rtu-over-tcp", "tcp"):
            raise ValueError(
                f"transport {self.transport!r}: a TCP endpoint uses 'rtu-over-tcp' or 'tcp'"
            )
        if self.echo and self.transport == "tcp":
            raise ValueError("echo: a Modbus TCP (MBAP) link has no request echo; "
                             "the option is for RTU lines")
        if not 1 <= self.port <= 65535:
            raise ValueError(f"tcpPort {self.port}: must be 1..65535")
        if self.transport == "tcp" and (self.framing != "rtu" or self.heartbeat):
            raise ValueError(f"framing {self.framing!r}/heartbeat: Modbus TCP (MBAP) has its "
                             "own framing; use transport rtu-over-tcp or rtu-over-tcp-server")
        if self.engine not in ("thread", "loop"):
            raise ValueError(f"engine {self.engine!r}: must be one of thread, loop")
        if not 0 <= self.channel < self.connections or (
                self.connections > 1 and self.transport != "tcp"):
            raise ValueError(f"channel {self.channel} of {self.connections} connections: "
                             "connections > 1 is for Modbus TCP, channel 0..connections-1")

    @property
    def key(self) -> tuple[str, ...]:
        """The line's identity: the primary host:port, and the channel when the
        endpoint has several connections (each its own line)."""
        base = (self.transport, self.host, str(self.port))
        return base if self.connections == 1 else (*base, f"#{self.channel}")

    def targets(self) -> tuple[TcpEndpoint, ...]:
        """The primary, then each alternate: the peers a failover line connects to in
        turn."""
        return (replace(self, alternates=()), *(
            replace(self, host=host, port=port, alternates=()) for host, port in self.alternates))

    def describe(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.transport}://{host}:{self.port}" + (
            " echo" if self.echo else "") + (
            " wrapped" if self.framing == "wrapped-report" else "") + (
            f" channel {self.channel}/{self.connections}" if self.connections > 1 else "")

    @property
    def max_frame_time(self) -> float:
        return 0.0


@dataclass(frozen=True)
class DtuEndpoint:
    """One DTU that dials in to our listen port (``rtu-over-tcp-server``): raw RTU
    frames (or wrapped reports) over a TCP connection the DTU opened."""

    listen_host: str
    listen_port: int
    dtu_id: str  # "" with registration none: the port's only DTU
    echo: bool = False
    framing: str = "rtu"  # rtu | wrapped-report
    heartbeat: bytes = b""

    @property
    def key(self) -> tuple[str, ...]:
        return ("dtu", self.listen_host, str(self.listen_port), self.dtu_id)

    def describe(self) -> str:
        name = self.dtu_id or "(single)"
        return f"dtu {name}@{self.listen_host}:{self.listen_port}" + (
            " echo" if self.echo else "") + (
            " wrapped" if self.framing == "wrapped-report" else "")

    @property
    def max_frame_time(self) -> float:
        return 0.0


@dataclass(frozen=True)
class MqttBroker:
    """Where MQTT DTUs are reached: one MQTT connection per distinct value, shared by
    every DTU on it (line/mqtt_dtu.py)."""

    host: str
    port: int = 1883
    username: str = ""
    password: str = field(default="", repr=False)  # never shown
    client_id: str = ""
    keepalive: int = 30
    qos: int = 0
    tls: bool = False
    ca_file: str = ""
    cert_file: str = ""
    key_file: str = ""
    tls_insecure: bool = False

    def describe(self) -> str:
        return f"mqtt{'s' if self.tls else ''}://{self.host}:{self.port}"


@dataclass(frozen=True)
class MqttDtuEndpoint:
    """A DTU that bridges its RS-485 side to MQTT topics (``mqtt-dtu``): requests are
    published to ``downlink``, replies arrive on ``uplink``; ``status`` (may be empty)
    carries ``online``/``offline`` (its will).  Framed like a DTU stream."""

    broker: MqttBroker
    dtu_id: str
    uplink: str
    downlink: str
    status: str = ""
    online: bytes = b"online"
    offline: bytes = b"offline"
    echo: bool = False
    framing: str = "rtu"  # rtu | wrapped-report
    heartbeat: bytes = b""

    @property
    def key(self) -> tuple[str, ...]:
        return ("mqtt-dtu", self.broker.host, str(self.broker.port), self.dtu_id)

    def describe(self) -> str:
        return f"mqtt-dtu {self.dtu_id}@{self.broker.host}:{self.broker.port}" + (
            " echo" if self.echo else "") + (
            " wrapped" if self.framing == "wrapped-report" else "")

    @property
    def max_frame_time(self) -> float:
        return 0.0


Endpoint = SerialPort | TcpEndpoint | DtuEndpoint | MqttDtuEndpoint


@dataclass(frozen=True)
class LineTiming:
    """Timeouts and pacing of a line, in seconds."""

    response_timeout: float = 1.0
    byte_timeout: float = 0.2
    settle_timeout: float | None = None  # None: the response timeout; 0 disables settling
    connect_timeout: float = 3.0
    reconnect_interval: float = 5.0  # first wait after a lost link or failed connect
    max_backoff: float = 60.0  # the wait doubles per failed connect up to this
    request_interval: float = 0.0  # extra silence between requests, for slow devices
    turnaround_delay: float = 0.1  # after a broadcast, before the next request

    @property
    def settle(self) -> float:
        return self.response_timeout if self.settle_timeout is None else self.settle_timeout


def endpoint_for(params: DriverModbusRtuParameter) -> Endpoint:
    """The endpoint of a device's communication parameters (the config refuses these
    combinations too; parameters may have been changed after they were loaded)."""
    if params.framing == "wrapped-report" and params.transport not in STREAMS:
        raise ValueError(f"framing 'wrapped-report': needs transport rtu-over-tcp, "
                         f"rtu-over-tcp-server or mqtt-dtu, not {params.transport!r}")
    if params.transport == "rtu-over-tcp-server":
        return DtuEndpoint(params.listen_host, params.effective_listen_port, params.dtu_id,
                           echo=params.echo, framing=params.framing,
                           heartbeat=params.heartbeat_bytes)
    if params.transport == "mqtt-dtu":
        return mqtt_dtu_endpoint(params)
    if params.transport == "rtu":
        return SerialPort(
            port=params.com_port,
            baudrate=params.baud_rate,
            parity=_parity_letter(params.parity),
            data_bits=params.data_bits,
            stop_bits=params.stop_bits,
            rs485=params.rs485,
            echo=params.echo,
            flow_control=params.flow_control,
            alternates=params.alternates,
            failover_after=params.failover_after,
            failback_interval=params.failback_interval / 1000,
        )
    connections = params.connections if params.transport == "tcp" else 1
    channel = params.slave_id if params.channel is None else params.channel
    return TcpEndpoint(params.tcp_host, params.tcp_port, params.transport, echo=params.echo,
                       framing=params.framing, heartbeat=params.heartbeat_bytes,
                       alternates=tuple(split_host_port(a) for a in params.alternates),
                       connections=connections, channel=channel % connections,
                       failover_after=params.failover_after,
                       failback_interval=params.failback_interval / 1000,
                       engine="loop" if params.engine == "loop" else "thread",
                       loop_threads=params.loop_threads)



def mqtt_dtu_endpoint(params: DriverModbusRtuParameter) -> MqttDtuEndpoint:
    """The endpoint of an ``mqtt-dtu`` device: its broker and its topics."""
    broker = MqttBroker(
        params.mqtt_host, params.mqtt_port, params.mqtt_username,
        params.mqtt_password.get_secret_value(), params.mqtt_client_id,
        params.mqtt_keepalive, params.mqtt_qos, params.mqtt_tls, params.mqtt_ca_file,
        params.mqtt_cert_file, params.mqtt_key_file, params.mqtt_tls_insecure)
    dtu = params.dtu_id
    return MqttDtuEndpoint(
        broker, dtu, topic_for(params.uplink_topic, dtu), topic_for(params.downlink_topic, dtu),
        topic_for(params.status_topic, dtu), params.online_payload.encode(),
        params.offline_payload.encode(), echo=params.echo, framing=params.framing,
        heartbeat=params.heartbeat_bytes)


def _parity_letter(parity: Any) -> str:
    text = str(enum_value(parity))
    return text[0].upper() if text else "N"
