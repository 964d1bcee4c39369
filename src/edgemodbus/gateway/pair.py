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
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future
from typing import Any

from ..config import DeviceConfig
from ..driver import DriverModbusRtu
from .fleet import LeaseSettings
from .lease import Lease, LeaseKeeper, NotLeaderError, RedisEngine

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

    def driver(self, cfg: DeviceConfig) -> DriverModbusRtu:
        """The driver for a device of the file: a :class:`LeaderDriver` if gated."""
        return LeaderDriver(self.lease, cfg) if gated(cfg) else DriverModbusRtu()


class LeaderDriver(DriverModbusRtu):
    """A gated device's driver: every write, action and forwarded request is refused
    (``NotLeaderError``'s words) unless the lease is known to hold for as long as it may
    take: twice the device's readTimeout x (retries + 1) (the request may wait for one
    poll transaction on the line before its own)."""

    def __init__(self, lease: Lease, cfg: DeviceConfig) -> None:
        super().__init__()
        params = cfg.effective_parameters()
        self.pair_lease = lease
        self.write_budget = 2 * params.read_timeout / 1000 * (params.retries + 1)

    def refusal(self) -> str | None:
        """Why a write must not go out now, or None."""
        try:
            self.pair_lease.require(self.write_budget)
        except NotLeaderError as exc:
            return str(exc)
        return None

    def write_addresses(self, items: Iterable[tuple[str, Any]]) -> tuple[bool, str | None]:
        why = self.refusal()
        return (False, why) if why else super().write_addresses(items)

    async def write_addresses_async(
            self, items: Iterable[tuple[str, Any]]) -> tuple[bool, str | None]:
        why = self.refusal()
        return (False, why) if why else await super().write_addresses_async(items)

    def submit_writes(self, items: Iterable[tuple[str, Any]]) -> Future[tuple[bool, str | None]]:
        why = self.refusal()
        if why:
            raise NotLeaderError(why)
        return super().submit_writes(items)

    def run_action(self, name: str,
                   params: Mapping[str, Any] | None = None) -> tuple[bool, str | None]:
        why = self.refusal()
        return (False, why) if why else super().run_action(name, params)

    async def run_action_async(self, name: str, params: Mapping[str, Any] | None = None
                               ) -> tuple[bool, str | None]:
        why = self.refusal()
        return (False, why) if why else await super().run_action_async(name, params)

    def forward(self, pdu: bytes, timeout: float | None = None) -> Future[bytes]:
        why = self.refusal()
        if why:
            future: Future[bytes] = Future()
            future.set_exception(NotLeaderError(why))
            return future
        return super().forward(pdu, timeout)


__all__ = ["LeaderDriver", "Pair", "gated"]
