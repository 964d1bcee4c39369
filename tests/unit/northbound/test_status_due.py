"""The MQTT thread's look at statuses (northbound/mqtt/outbox.py ``take_status_due``):
the devices that reported, then those held here, each once, none detached; a device
detached while held leaves the held map there (its departure action may never run when
the broker is away: actions are dropped while disconnected)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from edgemodbus.northbound.mqtt.outbox import Outbox


def dev(code: str) -> Any:
    return SimpleNamespace(code=code, attached=True)


def test_due_then_held_each_once_and_no_detached() -> None:
    outbox = Outbox(100)
    try:
        a, b, c, gone = dev("a"), dev("b"), dev("c"), dev("gone")
        held: dict[str, Any] = {"b": b, "c": c, "gone": gone}
        outbox.status_changed(a)
        outbox.status_changed(b)
        outbox.status_changed(a)  # twice: looked at once
        gone.attached = False
        assert outbox.take_status_due(held) == [a, b, c]
        assert held == {"b": b, "c": c}  # the detached one left the held map
        assert outbox.take_status_due(held) == [b, c]  # nothing new: the held ones only
        assert outbox.take_status_due({}) == []  # an idle instance: nothing at all
        outbox.look_at([a, gone])
        assert outbox.take_status_due({}) == [a]
    finally:
        outbox.close()
