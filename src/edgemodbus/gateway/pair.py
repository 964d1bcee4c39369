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
from typing import TYPE_CHECKING, Any

from ..config import DeviceConfig, DriverModbusRtuParameter
from ..driver import DriverModbusRtu
from ..line import DtuEndpoint, DtuSlot, Endpoint, LineTiming, LineWorker
from ..line.loop import LoopLine
from ..northbound.sparkplug.bdseq import RedisBdSeqStore
from ..poll.poller import Poller
from .fleet import LeaseSettings
from .lease import Lease, LeaseKeeper, NotLeaderError, RedisEngine

if TYPE_CHECKING:
    from ..northbound.sparkplug.publisher import SparkplugPublisher

log = logging.getLogger("edgemodbus.pair")


def gated(cfg: DeviceConfig) -> bool:
    """Whether a device runs on the leader only (every transport the gateway connects
    on; not a DTU that dials in)."""
    return cfg.effective_parameters().transport != "rtu-over-tcp-server"


class Pair:
    """The lease of this instance and what follows from it: ``on_change(leader)`` runs on
    the lease's thread at each change (the gateway starts or stops its gated devices);
    a Sparkplug edge node the pair shares (:meth:`follow`) is connected while it leads."""

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
        self.node: SparkplugPublisher | None = None  # a shared edge node: follow()

        def gained(fence: int) -> None:
            on_change(True)  # the devices first: the NBIRTH's DBIRTHs follow it
            if self.node is not None:
                self.node.lead(True)

        def lost(reason: str) -> None:
            if self.node is not None:  # NDEATH before the devices' stop
                self.node.lead(False)
            on_change(False)

        self.lease = Lease(engine, settings.lease_ms, renew_ms, token=token,
                           on_gain=gained, on_loss=lost, margin_ms=settings.margin_ms)
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

    def bd_seq_store(self) -> RedisBdSeqStore:
        """Where the edge node the pair shares keeps its bdSeq (``<keyPrefix>bdseq``)."""
        return RedisBdSeqStore(self.engine.client, f"{self.key[1]}bdseq", self.lease.check)

    def follow(self, node: SparkplugPublisher) -> None:
        """The Sparkplug edge node the two instances share (``sharedByPair``; the
        gateway's publisher, also one swapped on reload): connected while this instance
        leads, from now on."""
        self.node = node
        if self.lease.check():
            node.lead(True)

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
    poll transaction on the line before its own).

    Its line is gated by the lease too (line/worker.py ``lease``): past the lease's
    :meth:`~Lease.deadline` the engine in C starts no poll and no retry, a job's request
    is refused as it is about to go out, and the link is closed until the lease is
    renewed; so a leader paused past its lease sends nothing when it wakes."""

    def __init__(self, lease: Lease, cfg: DeviceConfig) -> None:
        super().__init__()
        params = cfg.effective_parameters()
        self.pair_lease = lease
        self.gated_line: LineWorker | None = None  # while running: its line, gated
        self.write_budget = 2 * params.read_timeout / 1000 * (params.retries + 1)

    def _acquire(self, params: DriverModbusRtuParameter, endpoint: Endpoint,
                 timing: LineTiming, poller: Poller) -> tuple[LineWorker, DtuSlot | None]:
        """The line, gated by the lease before the poller is on it (the base's steps;
        a gated device is never a DTU that dials in, so no DTU slot)."""
        if isinstance(endpoint, DtuEndpoint):
            raise ValueError(f"{endpoint.describe()}: a DTU that dials in connects to one "
                             "instance only and is not gated by the pair's lease: use "
                             "DriverModbusRtu for it")
        line = self.registry.acquire(endpoint, timing)
        try:
            if isinstance(line, LoopLine):
                raise ValueError(f"{endpoint.describe()}: engine \"loop\" does not follow "
                                 "the pair's lease (line/loop.py): a connect-mode device of "
                                 "a redundant pair needs engine \"thread\" (the default)")
            line.lease = self.pair_lease.deadline
            self.pair_lease.watch(line.lease_changed)
            poller.start(line)
        except BaseException:
            self.pair_lease.unwatch(line.lease_changed)
            poller.stop()
            line.detach(poller)
            self.registry.release(line)
            raise
        self.gated_line = line
        return line, None

    def stop_device(self) -> bool:
        line, self.gated_line = self.gated_line, None
        if line is not None:
            self.pair_lease.unwatch(line.lease_changed)
        return super().stop_device()

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

    async def write_addresses_async(self, items: Iterable[tuple[str, Any]],
                                    exact: bool = False) -> tuple[bool, str | None]:
        why = self.refusal()
        return (False, why) if why else await super().write_addresses_async(items, exact)

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
