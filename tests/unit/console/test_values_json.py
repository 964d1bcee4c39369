"""The console's JSON carries values as every JSON output of edgemodbus does
(codec/jsonable.py, docs/device-files.md "Values in JSON"): a Float item as the shortest
decimal that reads back to its float32, NaN and the infinities as the strings "NaN",
"Infinity", "-Infinity" (strict JSON: no bare NaN token), and null only for no value.
Both the tag table (GET /api/devices/{code}/tags) and the live stream (server-sent
events) are read as raw bytes and parsed by a strict parser."""

from __future__ import annotations

import http.client
import json
from pathlib import Path
from typing import Any

from tests.conftest import SlaveFactory
from tests.console_gateway import console_gateway
from tests.unit.console.test_server import open_stream, port, read_event
from tests.value_reference import float32_text
from tests.waiting import wait_for

ITEMS = [
    {"name": "level", "address": "hr:0", "deviceDataType": "Float"},
    {"name": "nan", "address": "hr:2", "deviceDataType": "Float"},
    {"name": "inf", "address": "hr:4", "deviceDataType": "Float"},
    {"name": "ninf", "address": "hr:6", "deviceDataType": "Double"},
    {"name": "count", "address": "hr:10", "deviceDataType": "UInt16"},
    {"name": "gone", "address": "hr:9999", "deviceDataType": "Float"},  # past the slave's
]
REGISTERS = [0x428B, 0x7D5F, 0x7FC0, 0x0000, 0x7F80, 0x0000, 0xFFF0, 0, 0, 0, 7]


def strict(body: bytes) -> Any:
    """JSON as a strict parser takes it: a bare NaN or Infinity token is an error."""
    def refuse(token: str) -> Any:
        raise AssertionError(f"not strict JSON: {token} in {body[:300]!r}")
    return json.loads(body, parse_constant=refuse)


def get_raw(console_port: int, path: str) -> bytes:
    conn = http.client.HTTPConnection("127.0.0.1", console_port, timeout=30)
    try:
        conn.request("GET", path, headers={"Host": f"127.0.0.1:{console_port}"})
        response = conn.getresponse()
        body = response.read()
        assert response.status == 200, body
        return body
    finally:
        conn.close()


def check_values(rows: dict[str, dict[str, Any]], level_text: str) -> None:
    assert rows["nan"]["value"] == "NaN" and rows["nan"]["status"] == "Ok"
    assert rows["inf"]["value"] == "Infinity" and rows["inf"]["status"] == "Ok"
    assert rows["ninf"]["value"] == "-Infinity" and rows["ninf"]["status"] == "Ok"
    assert rows["count"]["value"] == 7
    assert repr(rows["level"]["value"]) == level_text
    # no value: null, told apart from NaN by the status and the reason
    assert rows["gone"]["value"] is None and rows["gone"]["status"] == "Invalid"
    assert rows["gone"]["reason"]


def test_tags_and_stream_carry_float32_nan_and_infinities_as_strict_json(
        tmp_path: Path, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp")
    slave.set_registers(1, "hr", 0, REGISTERS)
    comm = {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": slave.port,
            "slaveId": 1, "readCycle": 100, "readTimeout": 1000, "byteTimeout": 50,
            "retries": 0, "maxMergeAddressGap": 4}
    with console_gateway(tmp_path / "cfg", slave.port,
                         extra={"communication": comm, "addressList": ITEMS}) as gateway:
        console_port = port(gateway)

        def rows() -> dict[str, dict[str, Any]]:
            data = strict(get_raw(console_port, "/api/devices/Dev1/tags"))
            return {r["name"]: r for r in data["tags"]}

        wait_for(lambda: rows()["nan"]["status"] == "Ok" and
                 rows()["gone"]["status"] == "Invalid", what="first reads")
        body = get_raw(console_port, "/api/devices/Dev1/tags")
        assert b'"value":69.744865' in body.replace(b" ", b""), body[:400]
        check_values(rows(), float32_text(69.74486541748047))

        sock = open_stream(console_port, "/api/devices/Dev1/events")
        try:
            # a new float32 with a long double form: the stream writes its short one
            slave.set_registers(1, "hr", 0, [0x3DCC, 0xCCCD])  # float32 0.1
            line = read_event(sock, '"name":"level","value":0.1,', timeout=30)
            event = strict(line[5:].encode())
            level = next(r for r in event["rows"] if r["name"] == "level")
            assert level["value"] == 0.1 and level["status"] == "Ok"
            slave.set_registers(1, "hr", 0, [0x7FC0, 0x0001])  # another NaN payload
            line = read_event(sock, '"name":"level","value":"NaN"', timeout=30)
            strict(line[5:].encode())
        finally:
            sock.close()

