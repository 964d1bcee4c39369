"""Item updates as bytes: their JSON payload without json.dumps, and QoS 0 PUBLISH packets
built by hand and handed to paho's own output queue (the fast path of sender.py)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

from ...codec import jsonable
from ...datatypes import enum_value

if TYPE_CHECKING:
    from paho.mqtt.client import Client

    from .outbox import Row


def raw_packet_queue(client: Client) -> Callable[..., Any] | None:
    """paho's internal ``_packet_queue(command, packet, mid, qos, info)`` if this paho
    has it with that shape (checked, since it is not public API), else None: then every
    message goes through publish()."""
    import inspect

    queue = getattr(client, "_packet_queue", None)
    if queue is None:
        return None
    try:
        params = list(inspect.signature(queue).parameters)
    except (TypeError, ValueError):
        return None
    if params[:5] != ["command", "packet", "mid", "qos", "info"]:
        return None
    return cast("Callable[..., Any]", queue)


def fixed_header(first: int, remaining: int) -> bytes:
    """Packet type byte + remaining length (MQTT 3.1.1, 2.2.3: 7 bits a byte)."""
    out = bytearray((first,))
    while True:
        byte, remaining = remaining & 0x7F, remaining >> 7
        out.append(byte | 0x80 if remaining else byte)
        if not remaining:
            return bytes(out)


class ItemEncoder:
    """JSON of one item update, {"value","status","updateTs","errorReason"}, without
    json.dumps for the common cases (ints, finite floats, bools, None; the timestamp
    shared by the items of one block is formatted once)."""

    __slots__ = ("iso", "ts")

    def __init__(self) -> None:
        self.ts: Any = None
        self.iso = "null"

    def __call__(self, value: Any, status: Any, ts: Any, error: Any) -> bytes:
        kind = type(value)
        if kind is int:
            text = str(value)
        elif kind is float:
            text = repr(value) if math.isfinite(value) else "null"
        elif value is None:
            text = "null"
        elif kind is bool:
            text = "true" if value else "false"
        else:
            text = json.dumps(jsonable(value), ensure_ascii=False, default=str)
        if ts is not self.ts:
            self.ts = ts
            self.iso = "null" if ts is None else f'"{ts.isoformat()}"'
        err = "null" if error is None else json.dumps(str(error), ensure_ascii=False)
        state = enum_value(status)
        return (f'{{"value":{text},"status":"{state}","updateTs":{self.iso},'
                f'"errorReason":{err}}}').encode()


def encode_item(value: Any, status: Any, ts: Any, error: Any) -> bytes:
    """The JSON payload of one item update (what the item topic carries)."""
    return ItemEncoder()(value, status, ts, error)


def publish_packets(rows: list[Row], retain: bool,
                    item_topic: Callable[[str, str], str]) -> bytes:
    """The QoS 0 PUBLISH packets of item updates, as one buffer (MQTT 3.1.1, 3.3); each
    device keeps its items' encoded topics."""
    encode = ItemEncoder()
    fixed = 0x31 if retain else 0x30  # PUBLISH, QoS 0 (MQTT 3.1.1, 3.3)
    chunks: list[bytes] = []
    for dev, name, value, status, ts, error in rows:
        head = dev.item_heads.get(name)
        if head is None:
            topic = item_topic(dev.code, name).encode()
            head = dev.item_heads[name] = len(topic).to_bytes(2, "big") + topic
        payload = encode(value, status, ts, error)
        chunks.append(fixed_header(fixed, len(head) + len(payload)) + head + payload)
    return b"".join(chunks)
