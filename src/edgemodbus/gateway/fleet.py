"""The ``fleet`` section of the gateway file: this instance of a dial-in fleet (N
gateways running one config folder behind a TCP load balancer, docs/deploy.md).

```json
"fleet": {"instanceId": "gw-2", "loadBalancers": ["10.0.5.10", "10.0.5.11"]}
```

``instanceId`` names this instance in the retained device statuses it publishes, its
MQTT client id and gateway topic and the ``edgemodbus_dtu_held`` gauge; left out, the
environment's ``EDGEMODBUS_INSTANCE`` (a systemd template unit's ``%i``), else the host
name.  ``loadBalancers``: the balancers' networks; a connection from one of them must
start with a PROXY v2 header (line/proxy_v2.py), which gives the DTU's own address.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, ClassVar, Protocol

from pydantic import AfterValidator, BeforeValidator, Field, field_validator

from ..config import DeviceConfig, DriverModbusRtuParameter, Model
from ..config.limits import MAX_NAME
from ..config.listen import allow_list, network
from ..driver import DriverModbusRtu
from ..northbound.mqtt import check_name

if TYPE_CHECKING:
    from ..northbound.metrics import MetricsExporter
    from ..northbound.mqtt import MqttPublisher
    from ..northbound.sparkplug.publisher import SparkplugPublisher

    Publisher = MqttPublisher | SparkplugPublisher

MAX_BALANCERS = 64
INSTANCE_ENV = "EDGEMODBUS_INSTANCE"


def _bounded(nets: tuple[str, ...]) -> tuple[str, ...]:
    if len(nets) > MAX_BALANCERS:
        raise ValueError(f"at most {MAX_BALANCERS} networks, not {len(nets)}")
    return nets


Balancers = Annotated[tuple[Annotated[str, AfterValidator(network)], ...],
                      BeforeValidator(allow_list), AfterValidator(_bounded)]


class FleetSettings(Model):
    """The ``fleet`` section of the gateway file."""

    _where: ClassVar[str] = "fleet"
    _max_lengths: ClassVar[dict[str, int]] = {"instanceId": MAX_NAME}

    enabled: bool = Field(default=True, description="false: the section is kept, this "
                          "gateway runs alone (publishes every device, reads no PROXY header)")
    instance_id: str | None = Field(default=None, description="This instance's name "
                                    f"(statuses, MQTT client id); left out: ${INSTANCE_ENV}, "
                                    "else the host name")
    load_balancers: Balancers = Field(default=(), description="Networks (CIDR) or addresses "
                                      "of the load balancers that send a PROXY v2 header")

    @field_validator("instance_id")
    @classmethod
    def _topic_level(cls, value: str | None) -> str | None:
        return None if value is None else check_name("instanceId", value)

    @property
    def effective_instance(self) -> str:
        """The instance id: configured, else $EDGEMODBUS_INSTANCE, else the host name."""
        if self.instance_id:
            return self.instance_id
        env = os.environ.get(INSTANCE_ENV, "").strip()
        if env:
            return check_name(INSTANCE_ENV, env)
        return socket.gethostname().split(".")[0] or "edgemodbus"




class FleetConfig(Protocol):
    """What :func:`apply_fleet` reads of the gateway file (GatewayConfig; config.py
    imports this module)."""

    @property
    def fleet(self) -> FleetSettings | None: ...
    @property
    def instance(self) -> str | None: ...
    @property
    def effective_id(self) -> str: ...


def holder(params: DriverModbusRtuParameter,
           instance: str | None) -> Callable[[], bool] | None:
    """In a fleet, whether a listen-mode device's DTU is connected here now (the
    publisher publishes the device only then); None outside a fleet or for a device on
    another transport (a serial port or a TCP device belongs to every instance alike)."""
    if instance is None or params.transport != "rtu-over-tcp-server":
        return None
    registry = DriverModbusRtu.dtu_registry
    host, port, dtu_id = params.listen_host, params.effective_listen_port, params.dtu_id
    return lambda: registry.connected(host, port, dtu_id)


def attach_device(publisher: Publisher, driver: DriverModbusRtu, code: str,
                  cfg: DeviceConfig, instance: str | None) -> None:
    """Attach a device to the publisher; in a fleet with its :func:`holder` (either
    publisher: per-item/batch statuses, or Sparkplug DBIRTH/DDEATH per instance)."""
    held = holder(cfg.effective_parameters(), instance)
    if held is not None and getattr(publisher, "instance", None) is not None:
        publisher.attach(driver, code, held=held)
    else:
        publisher.attach(driver, code)


def apply_fleet(config: FleetConfig | None, exporter: MetricsExporter | None) -> None:
    """Apply a gateway file's fleet section: its load balancers to every DTU listen port
    of the process (None: none), this instance's name (else the gateway id) to the
    exporter's ``edgemodbus_dtu_held`` gauge."""
    fleet = config.fleet if config is not None else None
    enabled = fleet is not None and fleet.enabled
    DriverModbusRtu.dtu_registry.set_load_balancers(
        fleet.load_balancers if fleet is not None and enabled else ())
    if exporter is not None and config is not None:
        exporter.instance = config.instance or config.effective_id


__all__ = ["INSTANCE_ENV", "MAX_BALANCERS", "FleetSettings", "apply_fleet", "attach_device",
           "holder"]
