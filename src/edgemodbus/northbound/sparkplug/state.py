"""The primary host application's STATE (Sparkplug 3.0, 7.3): ``spBv1.0/STATE/<hostId>``,
retained, a JSON payload ``{"online": true|false, "timestamp": <ms>}``.  With a primary
host configured the edge node publishes its births only while the host is online; a
STATE older than the last one accepted (its timestamp) is ignored."""

from __future__ import annotations

import json
import logging

log = logging.getLogger("edgemodbus.sparkplug")


class HostState:
    """What is known of the primary host (always online when none is configured)."""

    def __init__(self, host_id: str | None) -> None:
        self.host_id = host_id
        self.topic = None if host_id is None else f"spBv1.0/STATE/{host_id}"
        self.online = host_id is None
        self._timestamp = -1

    def reset(self) -> None:
        """A new MQTT session: offline until the (retained) STATE says otherwise."""
        if self.host_id is not None:
            self.online = False

    def update(self, payload: bytes) -> bool | None:
        """Take a STATE message: True when the host came online, False when it went
        offline, None for no change (or a STATE that is stale or not valid, logged)."""
        try:
            body = json.loads(payload)
        except (ValueError, UnicodeDecodeError):
            body = None
        online = body.get("online") if isinstance(body, dict) else None
        stamp = body.get("timestamp") if isinstance(body, dict) else None
        if not isinstance(online, bool) or not isinstance(stamp, int) or isinstance(
                stamp, bool):
            log.warning("Sparkplug: STATE of %s ignored: %r is not "
                        '{"online": true|false, "timestamp": <ms>}', self.host_id,
                        payload[:100])
            return None
        if stamp < self._timestamp:
            log.info("Sparkplug: STATE of %s ignored: timestamp %d is older than %d",
                     self.host_id, stamp, self._timestamp)
            return None
        self._timestamp = stamp
        if online == self.online:
            return None
        self.online = online
        log.info("Sparkplug: primary host %s is %s", self.host_id,
                 "online" if online else "offline")
        return online
