"""What the publisher keeps per attached driver: its topics, its listener, counters;
and the check that a device's item topics clash with none of its own topics."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from ...driver import DriverModbusRtu
from ...poll.listeners import Listener
from .settings import FORBIDDEN, check_name

if TYPE_CHECKING:
    from .holding import Holding
    from .settings import MqttSettings


class AttachedDevice:
    """What the publisher keeps per attached driver."""

    __slots__ = (
        "action_topic", "attached", "batch_command_topic", "batch_topic", "code",
        "command_prefix", "driver", "dropped", "fleet", "item_topics", "largest", "listener",
        "published", "published_status", "read_topic", "reply_topic", "seen_status",
        "snapshot_topic", "snapshots", "snapshots_coalesced", "status_topic",
    )

    def __init__(self, settings: MqttSettings, topic: Callable[..., str],
                 driver: DriverModbusRtu, code: str) -> None:
        """``topic(template, device_code, item_name="")`` fills in a topic template."""
        self.driver = driver
        self.code = code
        self.snapshot_topic = topic(settings.snapshot_topic, code)
        self.status_topic = topic(settings.status_topic, code)
        self.reply_topic = topic(settings.reply_topic, code)
        self.batch_command_topic = topic(settings.batch_command_topic, code)
        self.batch_topic = topic(settings.batch_topic, code)  # mode "batch": the values
        self.action_topic = topic(settings.action_topic, code)
        self.read_topic = topic(settings.read_topic, code)  # reads on demand
        self.command_prefix = topic(settings.command_topic, code, "\0").removesuffix("\0")
        self.item_topics: dict[str, str] = {}
        self.attached = True
        self.largest = 0  # the most items one of its reports held (outbox.Outbox.limit)
        self.listener: Listener[DriverModbusRtu] | None = None  # its subscription
        self.published = 0
        self.dropped = 0
        self.snapshots = 0
        self.snapshots_coalesced = 0
        self.published_status: str | None = None
        self.seen_status: Any = None
        self.fleet: Holding | None = None  # in a fleet: published only while held here

    def stats(self) -> dict[str, Any]:
        """Its counters in the publisher's stats(): ``published``, ``dropped``,
        ``snapshotsPublished``, ``snapshotsCoalesced``; in a fleet ``held`` (its DTU is
        here, as the MQTT thread last saw) and ``retainedHolder`` (the instance its
        retained status named when this one last read it back: holding.py)."""
        return {"published": self.published, "dropped": self.dropped,
                "snapshotsPublished": self.snapshots,
                "snapshotsCoalesced": self.snapshots_coalesced,
                "held": self.fleet.holding if self.fleet is not None else None,
                "retainedHolder": self.fleet.seen[0] if self.fleet is not None
                and self.fleet.seen is not None else None}

    def filters(self, writes: bool = True) -> list[str]:
        """Subscriptions for this device's commands (none unless ``writes``), without
        overlaps (an overlap would deliver one command twice)."""
        filters = [self.command_prefix + "#"] if writes else []
        if writes and self.batch_command_topic + "/" != self.command_prefix:
            filters.append(self.batch_command_topic)
        for own in (self.action_topic, self.read_topic):
            if writes and not own.startswith(self.command_prefix):
                filters.append(own)
        if self.fleet is not None:  # its retained status read back (holding.py)
            filters.append(self.status_topic)
        return filters


def check_topics(settings: MqttSettings, topic_of: Callable[..., str],
                 matches: Callable[[str, str], bool], device_code: str,
                 names: Iterable[str]) -> None:
    """Raise ValueError if an item's topic is also a command, status or reply topic
    of this device (a publish there would be read back as a command)."""
    check_name("deviceCode", device_code)
    s = settings
    reserved = {
        topic_of(s.status_topic, device_code): "status",
        topic_of(s.reply_topic, device_code): "reply",
        topic_of(s.action_topic, device_code): "action",
        topic_of(s.read_topic, device_code): "read",
        topic_of(s.snapshot_topic, device_code): "snapshot",
    }
    command = topic_of(s.command_topic, device_code, "\0").removesuffix("\0") + "#"
    batch = topic_of(s.batch_command_topic, device_code)

    def clash_of(topic: str) -> str | None:
        clash = reserved.get(topic)
        if clash is None and (topic == batch or (s.writes and matches(command, topic))):
            clash = "command"
        return clash

    if s.mode == "batch":  # item names are JSON keys, not topics
        topic = topic_of(s.batch_topic, device_code)
        clash = clash_of(topic)
        if clash is not None:
            raise ValueError(
                f"device {device_code!r}: its batch topic {topic!r} is the device's "
                f"{clash} topic; change mqtt.batchTopic"
            )
        return
    for name in names:
        if any(ch in name for ch in FORBIDDEN):
            raise ValueError(
                f"item {name!r} of device {device_code!r}: MQTT topics cannot contain "
                "'+', '#' or NUL; rename the item"
            )
        topic = topic_of(s.item_topic, device_code, name)
        clash = clash_of(topic)
        if clash is not None:
            raise ValueError(
                f"item {name!r} of device {device_code!r}: its topic {topic!r} is the "
                f"device's {clash} topic; rename the item or change mqtt.itemTopic"
            )
