"""The JSON the publisher sends (item updates, batches, snapshots, statuses, gateway
state, replies): strict JSON, compact, UTF-8, all through the one value conversion of
edgemodbus.codec (:func:`~edgemodbus.codec.json_bytes`: a Float item's value as its
shortest float32 text, NaN and infinities as the strings "NaN", "Infinity", "-Infinity",
bytes hex, times ISO 8601; docs/library.md "Values as text and JSON")."""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime, timezone
from typing import Any

from ...codec import json_bytes, json_value
from ...datatypes import enum_value

dumps = json_bytes


def now() -> str:
    return datetime.now(timezone.utc).isoformat()


def encode_item(value: Any, status: Any, ts: Any, error: Any) -> bytes:
    """The payload of one item update on its item topic (mode "per-item"):
    ``{"value", "status", "updateTs", "errorReason"}``."""
    # the value converted here: its payload has a null (errorReason) nearly always, which
    # would have json_bytes write it twice to tell a null from NaN
    return json_bytes({"value": json_value(value), "status": status, "updateTs": ts,
                       "errorReason": error}, converted=True)


def batch_payload(code: str, rows: Iterable[tuple[str, Any, Any, Any, Any]]) -> bytes:
    """The payload of one device's report of one cycle on its batch topic (mode
    "batch"), from rows ``(name, value, status, updateTs, errorReason)``::

        {"deviceCode": "dev1", "ts": "2026-...+00:00",
         "values": {"t0": 1, "t1": 2.5}, "status": {"t0": "Ok", "t1": "Invalid"},
         "errors": {"t1": "..."}}

    ``values`` and ``status`` have every item reported in the cycle (a changed value or
    status; an Invalid item keeps its last good value, null if it never had one),
    ``errors`` the reason of each item that has one (``{}`` if none), ``ts`` the newest
    ``updateTs`` of them (null if none has one).  The values are not converted one by
    one: json_bytes does it only for a payload with a null in it."""
    values: dict[str, Any] = {}
    statuses: dict[str, Any] = {}
    errors: dict[str, Any] = {}
    newest: Any = None
    for name, value, status, ts, error in rows:
        values[name] = value
        statuses[name] = status  # an ItemStatus is a str: orjson writes its value
        if error is not None:
            errors[name] = error
        if ts is not None and (newest is None or ts > newest):
            newest = ts
    return json_bytes({"deviceCode": code, "ts": newest, "values": values,
                       "status": statuses, "errors": errors})


def status_text(status: Any) -> str:
    return str(enum_value(status))


def status_payload(gateway_id: str, code: str, status: str,
                   held: tuple[str, float] | None = None) -> bytes:
    """A device's status message (retained on its status topic); in a fleet ``held`` is
    (the instance, when the DTU registered there: Unix time), see holding.py."""
    body: dict[str, Any] = {"deviceCode": code, "status": status, "gatewayId": gateway_id,
                            "ts": now()}
    if held is not None:
        body["instance"], body["heldSince"] = held
    return dumps(body)


def gateway_payload(gateway_id: str, online: bool, reason: str | None) -> bytes:
    """The gateway's online/offline message (retained; the last will says offline)."""
    body: dict[str, Any] = {"gatewayId": gateway_id,
                            "status": "online" if online else "offline"}
    if reason is not None:
        body["reason"] = reason
    if reason != "lost":  # the last will is fixed at connect time: no timestamp
        body["ts"] = now()
    return dumps(body)
