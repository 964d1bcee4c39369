"""The MQTT outbox's limits and the payloads of both modes, without a broker: the queue
holds a device's full report beyond ``queueSize`` while the broker is connected, and
``queueSize`` during an outage, the oldest updates dropped and counted per device."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from datetime import datetime, timedelta, timezone

import pytest

import edgemodbus as em
from edgemodbus.datatypes import ItemStatus
from edgemodbus.northbound.mqtt import MqttSettings, batch_payload, encode_item
from edgemodbus.northbound.mqtt.devices import AttachedDevice
from edgemodbus.northbound.mqtt.outbox import Outbox

T0 = datetime(2026, 11, 23, 17, 31, 46, 125000, tzinfo=timezone.utc)


def items(n: int, start: int = 0) -> list[em.DeviceAddressItem]:
    made = []
    for k in range(start, start + n):
        item = em.DeviceAddressItem.model_validate(
            {"name": f"t{k}", "address": f"hr:{k}", "deviceDataType": "UInt16"})
        item.value, item.status, item.update_ts = k, ItemStatus.OK, T0
        made.append(item)
    return made


@pytest.fixture
def outbox() -> Iterator[Outbox]:
    box = Outbox(queue_size=5)
    yield box
    box.close()


def attached(code: str) -> AttachedDevice:
    settings = MqttSettings()
    return AttachedDevice(settings, lambda t, c, i="": t.format(
        prefix="p", deviceCode=c, itemName=i, gatewayId="g"), em.DriverModbusRtu(), code)


def names(box: Outbox) -> list[str]:
    return [row[0] for report in box.reports for row in report.rows]


def test_a_burst_is_kept_while_connected_and_an_outage_trims_to_queue_size(
        outbox: Outbox) -> None:
    a, b = attached("a"), attached("b")
    outbox.offer_items(a, items(11))  # a's first read: 11 items, queueSize 5
    assert outbox.queued == 11 and outbox.counts["dropped"] == 0
    assert outbox.limit() == 5 + 11
    outbox.offer_items(b, items(3))  # b's burst counts as well
    assert outbox.limit() == 5 + 11 + 3 and outbox.queued == 14
    outbox.offer_items(a, items(6))  # 20 > 19: the oldest one goes
    assert outbox.counts["dropped"] == 1 and a.dropped == 1
    assert names(outbox)[:2] == ["t1", "t2"]

    outbox.set_outage(True)  # the broker went away: queueSize from now on
    assert outbox.limit() == 5 and outbox.queued == 5
    assert outbox.counts["dropped"] == 15 and a.dropped + b.dropped == 15
    assert names(outbox) == ["t1", "t2", "t3", "t4", "t5"]  # the newest, a's last report
    outbox.offer_items(b, items(2, start=100))
    assert names(outbox) == ["t3", "t4", "t5", "t100", "t101"]
    assert outbox.counts["dropped"] == 17

    outbox.set_outage(False)  # connected again
    assert outbox.limit() == 5 + 11 + 3
    outbox.forget(b)  # detached: its burst no longer counts
    assert outbox.limit() == 5 + 11


def test_reports_are_taken_whole_or_cut_to_the_room_and_put_back_in_order(
        outbox: Outbox) -> None:
    a = attached("a")
    outbox.offer_items(a, items(4))
    outbox.offer_items(a, items(4, start=10))
    taken = outbox.take_reports(6, split=True)  # per-item: a message a row
    assert [len(r.rows) for r in taken] == [4, 2] and outbox.queued == 2
    outbox.put_back(taken)
    assert names(outbox) == ["t0", "t1", "t2", "t3", "t10", "t11", "t12", "t13"]
    assert outbox.queued == 8
    taken = outbox.take_reports(1, split=False)  # batch: a message a report
    assert [len(r.rows) for r in taken] == [4] and outbox.queued == 4


def test_batch_payload_carries_every_item_of_the_cycle_by_the_one_conversion() -> None:
    later = T0 + timedelta(milliseconds=40)
    rows = [
        ("f", math.nan, ItemStatus.OK, T0, None),
        ("big", 2**64 - 1, ItemStatus.OK, later, None),
        ("bin", b"\x01\xff", ItemStatus.OK, T0, None),
        ("when", T0, ItemStatus.OK, T0, None),
        ("lost", 7, ItemStatus.INVALID, T0, 'bad "x"'),
        ("never", None, ItemStatus.UNKNOWN, None, None),
    ]
    body = json.loads(batch_payload("dev1", rows))
    assert body == {
        "deviceCode": "dev1",
        "ts": later.isoformat(),
        "values": {"f": "NaN", "big": 2**64 - 1, "bin": "01ff", "when": T0.isoformat(),
                   "lost": 7, "never": None},
        "status": {"f": "Ok", "big": "Ok", "bin": "Ok", "when": "Ok", "lost": "Invalid",
                   "never": "Unknown"},
        "errors": {"lost": 'bad "x"'},
    }
    assert list(body) == ["deviceCode", "ts", "values", "status", "errors"]
    assert json.loads(batch_payload("d", []))["ts"] is None


def test_item_payload_is_the_json_of_its_fields() -> None:
    body = json.loads(encode_item(math.inf, ItemStatus.INVALID, T0, "why"))
    assert body == {"value": "Infinity", "status": "Invalid", "updateTs": T0.isoformat(),
                    "errorReason": "why"}
