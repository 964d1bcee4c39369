"""The driver's snapshot is strict JSON: the one value conversion of edgemodbus.codec
(NaN and infinities null, bytes hex, times ISO 8601), as in the CLI's JSON lines."""

from __future__ import annotations

import json
import math
import struct
from datetime import datetime, timezone
from typing import Any

import edgemodbus as em
from edgemodbus.datatypes import ItemStatus
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

FLOATS = {100: math.nan, 102: math.inf, 104: -math.inf, 106: 1.5, 108: -0.0}
BINARY = b"\x01\xab\xff\x00"
WHEN = datetime(2026, 1, 18, 12, 16, 58, tzinfo=timezone.utc)


def _registers() -> dict[int, int]:
    regs: dict[int, int] = {}
    for address, value in FLOATS.items():
        hi, lo = struct.unpack(">HH", struct.pack(">f", value))
        regs[address], regs[address + 1] = hi, lo
    regs[200], regs[201] = struct.unpack(">HH", BINARY)
    regs[300], regs[301] = struct.unpack(">HH", struct.pack(">I", int(WHEN.timestamp())))
    return regs


def _strict(obj: Any) -> str:
    return json.dumps(obj, allow_nan=False)


def test_snapshot_of_non_finite_floats_bytes_and_times_is_strict_json() -> None:
    items = [{"name": f"f{a}", "address": f"hr:{a}", "deviceDataType": "Float"} for a in FLOATS]
    items += [
        {"name": "bin", "address": "hr:200", "deviceDataType": "Binary", "quantity": 2},
        {"name": "when", "address": "hr:300", "deviceDataType": "DateTime", "quantity": 2},
    ]
    with PymodbusSlave("rtu-over-tcp", units=(1,), initial={1: {"hr": _registers()}}) as peer:
        cfg = em.load_device_config({
            "organization": {"deviceCode": "snap"},
            "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": peer.port, "slaveId": 1, "readCycle": 200,
                              "readTimeout": 500},
            "addressList": items,
        })
        drv = em.DriverModbusRtu()
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        try:
            wait_for(lambda: all(it.status is ItemStatus.OK for it in cfg.address_list),
                     what="every item Ok")
            snapshot = drv.snapshot()
        finally:
            drv.stop_device()
    by_name = {it.name: it.value for it in cfg.address_list}
    assert math.isnan(by_name["f100"]) and by_name["f102"] == math.inf  # the items keep them
    values = json.loads(_strict(snapshot))["items"]
    for address, value in FLOATS.items():
        got = values[f"f{address}"]["value"]
        if math.isfinite(value):
            assert got == value and math.copysign(1, got) == math.copysign(1, value)
        else:
            assert got is None, (address, got)
    assert values["bin"]["value"] == BINARY.hex()
    assert values["when"]["value"] == WHEN.isoformat()
    for entry in values.values():
        assert entry["status"] == "Ok"
        assert datetime.fromisoformat(entry["updateTs"]).tzinfo is not None
