"""What the edge node keeps per Sparkplug device (one attached driver): its metrics as
born (names, node-wide aliases, types), which of them were last published bad, and its
counters."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from ...config import ON_DEMAND, DeviceAddressItem
from ...datatypes import DataType, ItemStatus
from ...driver import DriverModbusRtu
from ...poll.listeners import Listener
from .payloads import MetricDef, Sample, epoch_ms, sparkplug_type

if TYPE_CHECKING:
    from ..mqtt.holding import Holding


DEMAND_ONLY = "read on demand only (Device Control/Read): not read yet"
"""The reason of an on-demand item (``readCycle`` -1) never read: a DBIRTH must give one."""


def sample_of(item: DeviceAddressItem) -> Sample:
    """An item's report as a metric carries it (its fields copied now); an on-demand
    item not read yet says so (else it would look like a poll that has not come yet)."""
    reason = item.error_reason
    if reason is None and item.status is ItemStatus.UNKNOWN and item.read_cycle == ON_DEMAND:
        reason = DEMAND_ONLY
    return Sample(item.name, item.value, item.status, epoch_ms(item.update_ts), reason)


def is_good(sample: Sample) -> bool:
    return sample.status is ItemStatus.OK and sample.value is not None


class NodeDevice:
    """One Sparkplug device of the edge node: an attached driver."""

    __slots__ = ("bad", "born", "born_at", "by_alias", "code", "driver", "dropped", "fleet",
                 "kinds", "listener", "metrics", "offered", "published")

    def __init__(self, driver: DriverModbusRtu, code: str) -> None:
        self.driver = driver
        self.code = code
        self.born = False  # DBIRTH published in this node session, no DDEATH since
        self.offered = 0  # reports queued so far (numbered under the publisher's lock)
        self.born_at = 0  # the last report the latest DBIRTH's values include
        # replaced whole at each birth (read by the MQTT thread for commands)
        self.metrics: dict[str, MetricDef] = {}
        self.by_alias: dict[int, MetricDef] = {}
        self.kinds: dict[str, DataType] = {}  # the type of the values written to an item
        self.bad: set[str] = set()  # metrics last published null
        self.listener: Listener[DriverModbusRtu] | None = None  # its subscription
        self.published = 0
        self.dropped = 0
        self.fleet: Holding | None = None  # in a fleet: whether its DTU is connected here

    def here(self) -> bool:
        """Whether this edge node may speak for the device: always, but in a fleet only
        while its DTU is connected to this instance (northbound/mqtt/holding.py)."""
        return self.fleet is None or not self.fleet.quiet()

    def birth(self, alias: Callable[[str, str], int]) -> list[tuple[Sample, MetricDef]]:
        """The metrics of a DBIRTH, from the items in force now (their types and
        current values); ``alias(device, item)`` gives the node-wide alias."""
        samples: list[tuple[Sample, MetricDef]] = []
        metrics: dict[str, MetricDef] = {}
        kinds: dict[str, DataType] = {}
        for item in self.driver.address_items:
            spec = MetricDef(item.name, alias(self.code, item.name),
                             sparkplug_type(item.device_data_type, item.converted_data_type,
                                            item.data_multiplier))
            metrics[item.name] = spec
            kinds[item.name] = item.converted_data_type or item.device_data_type
            samples.append((sample_of(item), spec))
        self.metrics, self.kinds = metrics, kinds
        self.by_alias = {spec.alias: spec for spec in metrics.values()}
        self.bad = {sample.name for sample, _ in samples if not is_good(sample)}
        return samples

    def first_cycle_done(self) -> bool:
        """The driver ended a cycle.  A device turns Running on its first reply (an
        exception reply too), in the middle of its first cycle, so its DBIRTH waits for
        this, else most of its metrics would be born "not read yet"."""
        return int(self.driver.stats().get("cycles", 0)) > 0

    def changed_items(self) -> bool:
        """True when the driver's items are no longer the metrics as born (a hot update
        of the address list): the device needs a new DBIRTH."""
        items = self.driver.address_items
        return len(items) != len(self.metrics) or any(
            item.name not in self.metrics for item in items)


class DeviceListener(Listener[DriverModbusRtu]):
    """The edge node's subscription to one driver: each batch, as samples copied on the
    line worker, goes to the node's bounded queue (``offer``, never blocking); statuses
    are polled by the node's thread (``statusCheckInterval``)."""

    def __init__(self, offer: Callable[[NodeDevice, list[Sample]], None],
                 dev: NodeDevice) -> None:
        self.offer = offer
        self.dev = dev

    def on_changes(self, source: DriverModbusRtu, items: list[DeviceAddressItem]) -> None:
        self.offer(self.dev, [sample_of(item) for item in items])
