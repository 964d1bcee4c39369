"""poll/periodic.py: which items report by period, and the heap of period reports checked
against a plain scan of every item (the definition: an item is reported again once its
last report is at least its period old)."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

import edgemodbus as em
from edgemodbus.config import DriverModbusRtuParameter, validate_items
from edgemodbus.poll.items import ItemState
from edgemodbus.poll.periodic import PeriodicReports, report_period, reports_all

EPOCH = datetime(2026, 1, 1, tzinfo=timezone.utc)


def params(**extra: Any) -> DriverModbusRtuParameter:
    return em.load_communication({"tcpHost": "127.0.0.1", "tcpPort": 502, **extra})


def item(name: str, **extra: Any) -> em.DeviceAddressItem:
    return em.DeviceAddressItem.model_validate(
        {"name": name, "address": "hr:0", "deviceDataType": "UInt16", **extra})


def states(*items: em.DeviceAddressItem, comm: DriverModbusRtuParameter) -> list[ItemState]:
    return [ItemState(p) for p in validate_items(list(items), comm)]


def test_effective_modes_and_periods() -> None:
    change, cycle = params(), params(reportMode="cycle", reportEvery=5000)
    assert report_period(item("a"), 1000, change) is None
    assert report_period(item("a", reportEvery=3000), 1000, change) == 3000
    assert report_period(item("a", reportMode="cycle"), 250, change) == 250
    assert report_period(item("a"), 1000, params(reportEvery=4000)) == 4000
    # a device by cycle: its items report each read, an item of its own by change
    # takes the device's reportEvery, an item's own reportEvery means by change
    assert report_period(item("a"), 1000, cycle) == 1000
    assert report_period(item("a", reportMode="change"), 1000, cycle) == 5000
    assert report_period(item("a", reportEvery=2000), 1000, cycle) == 2000
    # not polled: nothing to report again
    assert report_period(item("a", reportEvery=3000), -1, change) is None
    assert report_period(item("a", reportMode="cycle"), 0, change) is None
    assert reports_all(states(item("a"), item("b", address="hr:1"), comm=cycle), cycle)
    assert not reports_all(states(item("a"), item("b", address="hr:1", reportMode="change"),
                                  comm=cycle), cycle)
    assert not reports_all(states(item("a"), comm=change), change)


def test_a_device_without_periods_has_no_heap() -> None:
    comm = params()
    assert PeriodicReports.build(states(item("a"), comm=comm), [1000], comm, 0.0) is None
    cycle = params(reportMode="cycle")
    assert PeriodicReports.build(states(item("a"), comm=cycle), [1000], cycle, 0.0) is None
    built = PeriodicReports.build(states(item("a", reportEvery=2000), comm=comm), [1000],
                                  comm, 10.0)
    assert built is not None and len(built) == 1
    assert built.next_due == 10.0 + 2.0 - 0.1  # less a tenth of the scan rate


@settings(max_examples=200, deadline=None)
@given(
    periods=st.lists(st.integers(1, 50), min_size=1, max_size=8),
    steps=st.lists(st.tuples(st.integers(1, 20), st.sets(st.integers(0, 7))),
                   min_size=1, max_size=60),
)
def test_the_heap_reports_what_a_scan_of_every_item_reports(
        periods: list[int], steps: list[tuple[int, set[int]]]) -> None:
    """Pass ends ``step`` ms apart; before each, some items change (a report by change,
    which stamps updateTs).  At each pass end an item is reported by period exactly when
    a plain scan says its last report is at least its period old (1 ms either way: the
    heap keeps float due times)."""
    items = [item(f"i{k}") for k in range(len(periods))]
    heap = PeriodicReports([(it, p / 1000) for it, p in zip(items, periods, strict=True)],
                           0.0)
    for it in items:
        it.update_ts = EPOCH  # all read (and reported) at 0
    now_ms = 0
    for step, changed in steps:
        now_ms += step
        stamp = EPOCH + timedelta(milliseconds=now_ms)
        for k in changed:
            if k < len(items):
                items[k].update_ts = stamp - timedelta(microseconds=500)
        ages = {it.name: (stamp - it.update_ts).total_seconds() * 1000 for it in items}
        reported = {it.name for it in heap.due(now_ms / 1000, stamp)}
        for it, period in zip(items, periods, strict=True):
            age = ages[it.name]
            if it.name in reported:
                assert age >= period - 1, (it.name, age, period)
                assert it.update_ts == stamp
            else:
                assert age < period + 1, (it.name, age, period)


def test_a_clock_set_back_waits_one_period() -> None:
    it = item("a")
    heap = PeriodicReports([(it, 1.0)], 0.0)
    it.update_ts = EPOCH + timedelta(seconds=100)  # a report "in the future"
    assert heap.due(1.0, EPOCH + timedelta(seconds=1)) == []
    assert heap.next_due == 2.0
