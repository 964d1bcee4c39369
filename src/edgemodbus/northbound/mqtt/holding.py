"""A dial-in fleet (docs/deploy.md): an instance publishes a listen-mode device only
while it holds the device's DTU (the DTU is connected to it), and is silent about the
others.  :class:`Holding` is one device's state; the rule for its retained status:

* on arrival (the DTU registered here) the instance publishes the status with its
  ``instance`` and ``heldSince`` (when the DTU registered here), and subscribes to the
  device's command topics and its status topic (to read back what is retained there);
* while it holds the device it publishes status changes as a lone gateway does; if the
  retained status names another instance with an older ``heldSince`` (on a tie the larger
  instance id wins), or another instance's ``"NotHere"``, it publishes its own again;
* on departure it unsubscribes, and publishes ``"NotHere"`` unless the retained status it
  last read names another instance with a stronger claim (a later ``heldSince``, as
  above): an instance never overwrites the status of one that took the device after it,
  and a status of its own still in flight is always followed by its ``"NotHere"``.

A holder answers another's ``"NotHere"`` with its own status, so the retained status
ends up naming the instance that holds the device, or, when none does, the last one that
did with ``"status": "NotHere"``.  tests/unit/northbound/test_holding_property.py checks
this against a model of the broker in every interleaving it draws."""

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
        last read names no other instance with a stronger claim than this one's."""
        seen = self.seen
        return seen is None or seen[0] == instance or (seen[1], seen[0]) < (self.since, instance)

    def read_back(self, payload: bytes, instance: str) -> bool:
        """Note a retained status read back; True when this instance holds the device
        and the status names an instance that took it earlier: publish ours again."""
        found = holder_of(payload)
        if found is None:
            return False
        other, since, status = found
        self.seen = (other, since)
        return self.holding and other != instance and (
            status == NOT_HERE or (since, other) < (self.since, instance))


def holder_of(payload: bytes) -> tuple[str, float, str] | None:
    """(instance, heldSince, status) of a retained status; None for one without them."""
    try:
        body: Any = orjson.loads(payload)
        instance, since, status = body["instance"], float(body["heldSince"]), body["status"]
    except (orjson.JSONDecodeError, KeyError, TypeError, ValueError):
        return None
    return (instance, since, status) if isinstance(instance, str) else None


__all__ = ["NOT_HERE", "Holding", "holder_of"]
