"""The gateway's side of a redundant pair (docs/deploy.md "Redundant pair"): the lease
(gateway/lease.py) decides whether this instance runs its connect-mode devices.

Connect-mode devices (a serial port, Modbus TCP, RTU over TCP, an MQTT DTU: the gateway
is the one that connects) run only on the leader; listen-mode DTUs (they dial in, and a
DTU connects to one instance only) run on both.  The standby keeps every file loaded,
its connect-mode devices not started and with no connection.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Callable

from ..config import DeviceConfig
from .fleet import LeaseSettings
from .lease import Lease, LeaseKeeper, RedisEngine

log = logging.getLogger("edgemodbus.pair")


def gated(cfg: DeviceConfig) -> bool:
    """Whether a device runs on the leader only (every transport the gateway connects
    on; not a DTU that dials in)."""
    return cfg.effective_parameters().transport != "rtu-over-tcp-server"


class Pair:
    """The lease of this instance and what follows from it: ``on_change(leader)`` runs on
    the lease's thread at each change (the gateway starts or stops its gated devices)."""

    def __init__(self, settings: LeaseSettings, instance: str,
                 on_change: Callable[[bool], None]) -> None:
        renew_ms = settings.effective_renew_ms
        try:
            engine = RedisEngine(settings.url, settings.key_prefix, timeout=renew_ms / 1000)
        except ImportError as exc:
            raise ImportError(f"fleet.lease needs the redis client: pip install "
                              f"'edgemodbus[fleet]' ({exc})") from None
        token = f"{instance}@{socket.gethostname()}:{os.getpid()}"
        self.engine = engine
        self.lease = Lease(engine, settings.lease_ms, renew_ms, token=token,
                           on_gain=lambda fence: on_change(True),
                           on_loss=lambda reason: on_change(False))
        self.keeper = LeaseKeeper(self.lease)
        self.key = (settings.url, settings.key_prefix, settings.lease_ms, renew_ms)

    def start(self) -> Pair:
        log.info("pair: standby until this instance holds the lease (%s, %d ms)",
                 self.key[1], self.key[2])
        self.keeper.start()
        return self

    def stop(self) -> None:
        """Stop renewing and release the lease (the other instance takes over at its
        next attempt)."""
        self.keeper.stop()
        self.engine.close()

    def may_run(self, cfg: DeviceConfig) -> bool:
        """Whether this device may run here now."""
        return not gated(cfg) or self.lease.check()


__all__ = ["Pair", "gated"]
