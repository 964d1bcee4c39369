"""The JSON the publisher sends (snapshots, statuses, gateway state, replies): strict
JSON, compact, UTF-8; item updates have their own fast encoder in packets.py."""

from __future__ import annotations

import json
from datetime import datetime, timezone
from typing import Any

from ...codec import jsonable
from ...datatypes import enum_value


def dumps(obj: Any) -> bytes:
    try:
        text = json.dumps(obj, ensure_ascii=False, separators=(",", ":"), allow_nan=False,
                          default=str)
    except ValueError:  # a NaN somewhere: the slow, careful path
        text = json.dumps(jsonable(obj), ensure_ascii=False, separators=(",", ":"),
                          default=str)
    return text.encode()


def now() -> str:
    return datetime.now(timezone.utc).isoformat()


def status_text(status: Any) -> str:
    return str(enum_value(status))


def status_payload(gateway_id: str, code: str, status: str) -> bytes:
    """A device's status message (retained on its status topic)."""
    return dumps({"deviceCode": code, "status": status, "gatewayId": gateway_id,
                  "ts": now()})


def gateway_payload(gateway_id: str, online: bool, reason: str | None) -> bytes:
    """The gateway's online/offline message (retained; the last will says offline)."""
    body: dict[str, Any] = {"gatewayId": gateway_id,
                            "status": "online" if online else "offline"}
    if reason is not None:
        body["reason"] = reason
    if reason != "lost":  # the last will is fixed at connect time: no timestamp
        body["ts"] = now()
    return dumps(body)
