"""The retained-status rule of a fleet (northbound/mqtt/holding.py) against a model of
the broker: two instances publish and subscribe through FIFO connections, the broker
serves them in any interleaving, keeps the last status retained and sends it to a new
subscriber first; the instances read their messages whenever.  Whatever the order,
once everything is delivered the retained status names the one instance that holds the
device (never "NotHere", never the instance that left)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import orjson
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.northbound.mqtt.holding import NOT_HERE, Holding

NAMES = ("A", "B")


@dataclass
class Node:
    """One instance: its Holding, its connection to the broker, its inbox."""

    name: str
    here: bool = False
    holding: Holding = field(init=False)
    out: deque[tuple[str, bytes | None]] = field(default_factory=deque)
    inbox: deque[bytes] = field(default_factory=deque)
    subscribed: bool = False

    def __post_init__(self) -> None:
        self.holding = Holding(lambda: self.here)

    def status(self, text: str) -> bytes:
        return orjson.dumps({"status": text, "instance": self.name,
                             "heldSince": self.holding.since})

    def check(self, now: float) -> None:
        """The publisher's status check (publisher._fleet_turn)."""
        turn = self.holding.turn(now)
        if turn == "arrived":
            self.out.append(("sub", None))
            self.out.append(("pub", self.status("Running")))
        elif turn == "left":
            self.out.append(("unsub", None))
            if self.holding.may_say_left(self.name):
                self.out.append(("pub", self.status(NOT_HERE)))

    def read(self) -> None:
        """One message read back (publisher._on_message)."""
        payload = self.inbox.popleft()
        if self.holding.holding and self.holding.read_back(payload, self.name):
            self.out.append(("pub", self.status("Running")))
        elif not self.holding.holding:
            self.holding.read_back(payload, self.name)


class Broker:
    def __init__(self, nodes: dict[str, Node]) -> None:
        self.nodes = nodes
        self.retained: bytes | None = None

    def serve(self, node: Node) -> None:
        kind, payload = node.out.popleft()
        if kind == "sub":
            node.subscribed = True
            if self.retained is not None:
                node.inbox.append(self.retained)
        elif kind == "unsub":
            node.subscribed = False
        else:
            assert payload is not None
            self.retained = payload
            for other in self.nodes.values():
                if other.subscribed:
                    other.inbox.append(payload)


steps = st.lists(st.tuples(st.sampled_from(["toggle", "check", "serve", "read"]),
                           st.sampled_from(NAMES)), max_size=60)


@settings(max_examples=1000, deadline=None)
@given(steps, st.sampled_from(NAMES))
def test_the_retained_status_ends_naming_the_holder(script: list[tuple[str, str]],
                                                    final: str) -> None:
    nodes = {name: Node(name) for name in NAMES}
    broker = Broker(nodes)
    clock = 0.0
    for action, name in script:
        node = nodes[name]
        clock += 1.0
        if action == "toggle":
            node.here = not node.here
        elif action == "check":
            node.check(clock)
        elif action == "serve" and node.out:
            broker.serve(node)
        elif action == "read" and node.inbox:
            node.read()
    # the end: only ``final`` holds the DTU (it moved there); then quiescence
    for name, node in nodes.items():
        node.here = name == final
    clock += 1.0
    for node in sorted(nodes.values(), key=lambda n: n.name != final):  # either order
        node.check(clock)
    for _ in range(1000):
        busy = [n for n in nodes.values() if n.out or n.inbox]
        if not busy:
            break
        for node in busy:
            if node.out:
                broker.serve(node)
            if node.inbox:
                node.read()
    assert broker.retained is not None
    body = orjson.loads(broker.retained)
    assert (body["instance"], body["status"]) == (final, "Running"), body
