"""The keys of docs/reporting.md: reportMode and reportEvery per device and per item, and
readCycle -1 ("demand"); each refusal names the field, the value and what is allowed."""

from __future__ import annotations

from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.config import ON_DEMAND, ConfigError


def load(items: list[dict[str, Any]], **comm: Any) -> em.DeviceConfig:
    return em.load_device_config({
        "communication": {"tcpHost": "127.0.0.1", "tcpPort": 502, **comm},
        "addressList": items,
    })


def uint16(**extra: Any) -> dict[str, Any]:
    return {"name": "t", "address": "hr:0", "deviceDataType": "UInt16", **extra}


def test_the_keys_load() -> None:
    cfg = load([uint16(reportMode="CYCLE"), uint16(name="u", address="hr:1",
                                                   reportEvery=5000, readCycle=500),
                uint16(name="d", address="hr:2", readCycle="demand"),
                uint16(name="e", address="hr:3", readCycle="on-demand"),
                uint16(name="f", address="hr:4", readCycle=-1)],
               reportEvery=60000, readCycle=1000)
    first, second, *demand = cfg.address_list
    assert first.report_mode == "cycle" and first.report_every is None
    assert (second.report_every, second.read_cycle) == (5000, 500)
    assert [i.read_cycle for i in demand] == [ON_DEMAND] * 3
    assert cfg.communication.report_every == 60000
    # reportEvery equal to the scan rate: every read
    load([uint16(reportEvery=1000)], readCycle=1000)
    # a device by cycle with a reportEvery: for its items that report by change
    load([uint16(reportMode="change")], reportMode="cycle", reportEvery=3000)


@pytest.mark.parametrize(("items", "comm", "message"), [
    ([uint16(readCycle=-2)], {},
     r'addressList\[0\]\.readCycle -2: must be -1 \("demand": read only when asked\), 0 '
     r"\(wrapped reports only\) or 1\.\.86400000 ms"),
    ([uint16(readCycle="sometimes")], {}, r"addressList\[0\]\.readCycle 'sometimes'"),
    ([uint16(reportMode="often")], {},
     r"addressList\[0\]\.reportMode 'often': must be 'change' or 'cycle'"),
    ([uint16(reportEvery=0)], {}, r"addressList\[0\]\.reportEvery 0: must be 1\.\.86400000"),
    ([uint16(reportEvery=86_400_001)], {}, r"reportEvery 86400001: must be 1\.\.86400000"),
    ([uint16()], {"reportEvery": -5}, r"reportEvery -5: must be 1\.\.86400000"),
    ([uint16(reportMode="cycle", reportEvery=5000)], {},
     r"addressList\[0\]\.reportEvery 5000: reportMode 'cycle' reports every read already"),
    ([uint16(reportEvery=999)], {"readCycle": 1000},
     r"addressList\[0\]\.reportEvery 999: shorter than the scan rate of item 't' \(1000 ms\)"
     r": a period report repeats the last read, so use 1000 or more"),
    ([uint16(readCycle=5000), uint16(name="u", address="hr:1", readCycle=6000)],
     {"reportEvery": 2000},
     r"communication\.reportEvery 2000: shorter than the scan rate of item 't' \(5000 ms\)"),
    ([uint16(readCycle="demand", reportEvery=5000)], {},
     r"addressList\[0\]\.reportEvery 5000: the item is not polled \(readCycle -1: on "
     r"demand\), so there is no read to report again"),
])
def test_refusals_name_the_field_the_value_and_what_is_allowed(
        items: list[dict[str, Any]], comm: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message) as info:
        load(items, **comm)
    # the device's reportEvery is refused once, not once per item
    assert str(info.value).count("communication.reportEvery") <= 1


def test_the_device_s_period_skips_items_that_are_not_polled_or_report_by_cycle() -> None:
    load([uint16(readCycle="demand"), uint16(name="c", address="hr:1", reportMode="cycle",
                                             readCycle=500)],
         reportEvery=1000, readCycle=1000)
    # a device by cycle: its reportEvery is for items by change only
    load([uint16(), uint16(name="c", address="hr:1", reportMode="change", readCycle=100)],
         reportMode="cycle", reportEvery=500, readCycle=1000)
    with pytest.raises(ConfigError, match=r"communication\.reportEvery 500: shorter than "
                       r"the scan rate of item 'c' \(1000 ms\)"):
        load([uint16(), uint16(name="c", address="hr:1", reportMode="change")],
             reportMode="cycle", reportEvery=500, readCycle=1000)
