"""What the spool keeps: a message as the sender hands it in, as it is read back, and
what it counts against ``maxBytes``."""

from __future__ import annotations

from typing import NamedTuple

ROW_OVERHEAD = 32
"""Bytes a row counts beyond its topic and payload (id, device, qos, retain, time, and
SQLite's own per-row cost, roughly), so that many empty payloads still fill the bound."""

SYNCHRONOUS = ("normal", "full")


class Message(NamedTuple):
    """One message to keep: the device it belongs to (its per-device order is kept), and
    what the sender hands paho."""

    device: str
    topic: str
    payload: bytes
    qos: int
    retain: bool


class Stored(NamedTuple):
    """A message read back from the spool: its id (what :meth:`Spool.ack` takes) and the
    wall-clock time it was appended (Unix seconds)."""

    id: int
    device: str
    topic: str
    payload: bytes
    qos: int
    retain: bool
    ts: float


def message_size(topic: str, payload: bytes) -> int:
    """What one message counts against ``maxBytes``."""
    return len(topic.encode()) + len(payload) + ROW_OVERHEAD
