"""The publisher's subscription to one driver (:class:`DeviceListener`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ...driver import DriverModbusRtu
from ...poll.listeners import Listener

if TYPE_CHECKING:
    from ...config import DeviceAddressItem
    from ...datatypes import DeviceDriverStatus
    from .devices import AttachedDevice
    from .outbox import Outbox


class DeviceListener(Listener[DriverModbusRtu]):
    """The publisher's subscription to one driver: its batches and snapshots go to the
    outbox (bounded, never blocking the line worker); a status change, or in a fleet the
    first report after the DTU arrived, has the MQTT thread look at this device
    (Outbox.status_changed): statuses are events, not a poll of every device."""

    def __init__(self, outbox: Outbox, dev: AttachedDevice) -> None:
        self.outbox = outbox
        self.dev = dev

    def on_changes(self, source: DriverModbusRtu, items: list[DeviceAddressItem]) -> None:
        fleet = self.dev.fleet
        if fleet is None:
            self.outbox.offer_items(self.dev, items)
        elif not fleet.quiet():  # in a fleet: only while held here
            if not fleet.holding:  # arrived: the MQTT thread has not seen it yet
                self.outbox.status_changed(self.dev)
            self.outbox.offer_items(self.dev, items)

    def on_status(self, source: DriverModbusRtu, status: DeviceDriverStatus,
                  reason: str | None) -> None:
        self.outbox.status_changed(self.dev)

    def on_snapshot(self, source: DriverModbusRtu, snapshot: dict[str, Any]) -> None:
        fleet = self.dev.fleet
        if fleet is None or not fleet.quiet():
            self.outbox.offer_snapshot(self.dev, snapshot)


__all__ = ["DeviceListener"]
