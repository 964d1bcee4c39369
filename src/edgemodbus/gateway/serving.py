"""The gateway file's ``serve`` section applied to the running devices: one Modbus TCP
server (edgemodbus/serve/), its units bound to the drivers of the devices they name by
deviceCode, and bound again when a reload restarts or changes one of them."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from ..config import DeviceConfig
from ..driver import DriverModbusRtu
from ..serve import ModbusTcpServer, ServeSettings, ServeUnit, unknown_devices

log = logging.getLogger("edgemodbus.service")


class GatewayServer:
    """The server of a gateway (none while the ``serve`` section is absent or
    disabled)."""

    def __init__(self) -> None:
        self.server: ModbusTcpServer | None = None
        self._key: dict[str, Any] | None = None  # what the server was made from
        # unit id -> what it was bound with: its device's driver and config, its settings
        self._bound: dict[int, tuple[DriverModbusRtu, DeviceConfig, ServeUnit]] = {}

    def apply(self, settings: ServeSettings | None,
              devices: Mapping[str, tuple[DriverModbusRtu, DeviceConfig]]) -> list[str]:
        """Bring the server in line with ``settings`` and ``devices`` (device code ->
        its driver and config); what was done, in words.  A unit is bound again only
        when its driver, config or settings changed.  Raises OSError
        when the server cannot listen (the old one is stopped: serving is off)."""
        done: list[str] = []
        key = None
        if settings is not None and settings.enabled:
            key = {k: v for k, v in settings.to_dict().items() if k != "units"}
        if key != self._key:
            self.stop()
            if settings is not None and key is not None:
                self.server = ModbusTcpServer(settings.host, settings.port,
                                              max_connections=settings.max_connections,
                                              idle_timeout=settings.idle_timeout_s,
                                              allow_from=settings.allow_from,
                                              max_pending_per_master=settings
                                              .max_pending_per_master).start()
                self._key = key
                done.append(f"Modbus TCP server on {settings.host}:{self.server.port}")
            else:
                done.append("Modbus TCP server off")
        server = self.server
        if server is None or settings is None:
            return done
        for problem in unknown_devices(settings, list(devices)):
            log.error("gateway file: %s; that unit answers exception 0A", problem)
        wanted: dict[int, tuple[DriverModbusRtu, DeviceConfig, ServeUnit]] = {}
        for unit in settings.units:
            target = devices.get(unit.target)
            if target is None:
                continue
            driver, cfg = target
            # a restarted device is a new driver, a changed address list a new config
            wanted[unit.unit_id] = (driver, cfg, unit)
            bound = self._bound.get(unit.unit_id)
            if (bound is not None and bound[0] is driver and bound[1] is cfg
                    and bound[2] == unit):
                continue
            try:
                if unit.device is not None:
                    server.serve_device(unit.unit_id, driver, cfg, offset=unit.offset,
                                        max_age=None if unit.max_age_ms is None
                                        else unit.max_age_ms / 1000,
                                        allow_from=unit.allow_from)
                    done.append(f"unit {unit.unit_id} serves {unit.target}")
                else:
                    server.forward_device(unit.unit_id, driver, None if unit.timeout_ms
                                          is None else unit.timeout_ms / 1000,
                                          allow_from=unit.allow_from)
                    done.append(f"unit {unit.unit_id} forwards to {unit.target}")
            except (ValueError, OSError) as exc:
                log.error("serve: unit %d (%s) not served: %s", unit.unit_id, unit.target,
                          exc)
                wanted.pop(unit.unit_id)
        for unit_id in set(self._bound) - set(wanted):
            server.remove_unit(unit_id)
            done.append(f"unit {unit_id} removed")
        self._bound = wanted
        return done

    def stats(self) -> dict[str, Any] | None:
        return self.server.stats() if self.server is not None else None

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
        self.server = None
        self._key = None
        self._bound = {}
