"""A dial-in fleet (docs/deploy.md): an instance publishes a listen-mode device only
while it holds the device's DTU (the DTU is connected to it), and is silent about the
others.  :class:`Holding` is one device's state; the rule for its retained status:

* on arrival (the DTU registered here) the instance publishes the status with its
  ``instance`` and ``heldSince`` (when the DTU registered here), and subscribes to the
  device's command topics and its status topic (to read back what is retained there);
* while it holds the device it publishes status changes as a lone gateway does; if the
  retained status names another instance with an older ``heldSince`` (on a tie the larger
  instance id wins), it publishes its own again;
* on departure it unsubscribes, and publishes ``"NotHere"`` only if the retained status
  it last read names itself: an instance never overwrites a fresher status of another.

So the retained status ends up naming the instance that holds the device, or, when none
does, the last one that did with ``"status": "NotHere"``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import orjson

NOT_HERE = "NotHere"


class Holding:
    """One device's place in the fleet: whether this instance holds it."""

    __slots__ = ("held", "holding", "seen", "since")

    def __init__(self, held: Callable[[], bool]) -> None:
        self.held = held  # whether the device's DTU is connected here now
        self.holding = False  # as the MQTT thread last saw it
        self.since = 0.0  # when it was last seen arriving (Unix time)
        self.seen: tuple[str, float] | None = None  # the retained status read back

    def quiet(self) -> bool:
        """Whether the device's data is not ours to publish (its DTU is not here)."""
        return not self.held()

    def turn(self, now: float) -> str | None:
        """Look at the DTU: "arrived", "left" or None (no change)."""
        held = self.held()
        if held == self.holding:
            return None
        self.holding = held
        if held:
            self.since, self.seen = now, None
            return "arrived"
        return "left"

    def may_say_left(self, instance: str) -> bool:
        """Whether the "NotHere" of a departure may be published: the retained status
        last read names this instance (or none was read)."""
        return self.seen is None or self.seen[0] == instance

    def read_back(self, payload: bytes, instance: str) -> bool:
        """Note a retained status read back; True when this instance holds the device
        and the status names an instance that took it earlier: publish ours again."""
        seen = holder_of(payload)
        if seen is None:
            return False
        self.seen = seen
        return self.holding and seen[0] != instance and \
            (seen[1], seen[0]) < (self.since, instance)


def holder_of(payload: bytes) -> tuple[str, float] | None:
    """(instance, heldSince) of a retained status; None for one without them."""
    try:
        body: Any = orjson.loads(payload)
        instance, since = body["instance"], float(body["heldSince"])
    except (orjson.JSONDecodeError, KeyError, TypeError, ValueError):
        return None
    return (instance, since) if isinstance(instance, str) else None


__all__ = ["NOT_HERE", "Holding", "holder_of"]
