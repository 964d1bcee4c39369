"""What the publisher keeps per attached driver: its topics, chained callbacks, counters."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ...config import DeviceAddressItem
    from ...driver import DriverModbusRtu
    from .settings import MqttSettings


class AttachedDevice:
    """What the publisher keeps per attached driver."""

    __slots__ = (
        "action_topic", "attached", "batch_command_topic", "batch_topic", "code",
        "command_prefix", "driver", "dropped", "item_topics", "largest",
        "prev_batch", "prev_snapshot", "published", "published_status", "reply_topic",
        "seen_status", "snapshot_topic", "snapshots", "snapshots_coalesced", "status_topic",
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
        self.command_prefix = topic(settings.command_topic, code, "\0").removesuffix("\0")
        self.item_topics: dict[str, str] = {}
        self.attached = True
        self.largest = 0  # the most items one of its reports held (outbox.Outbox.limit)
        self.prev_batch: Callable[[list[DeviceAddressItem]], None] | None = None
        self.prev_snapshot: Callable[[str, dict[str, Any]], None] | None = None
        self.published = 0
        self.dropped = 0
        self.snapshots = 0
        self.snapshots_coalesced = 0
        self.published_status: str | None = None
        self.seen_status: Any = None

    def filters(self) -> list[str]:
        """Subscriptions for this device's commands, without overlaps (an overlap
        would deliver one command twice)."""
        filters = [self.command_prefix + "#"]
        if self.batch_command_topic + "/" != self.command_prefix:
            filters.append(self.batch_command_topic)
        if not self.action_topic.startswith(self.command_prefix):
            filters.append(self.action_topic)
        return filters

