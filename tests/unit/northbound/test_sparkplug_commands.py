"""Sparkplug commands are untrusted input: caps on size, metrics and names, values taken
only without loss, rebirths paced, refusals counted and their logs rate-limited.  Commands
are written by the independent encoder of tests/sparkplug_wire.py."""

from __future__ import annotations

import logging
import math
import struct
from collections import Counter
from typing import Any, cast

import pytest
from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.northbound.sparkplug.commands import (
    MAX_COMMAND_BYTES,
    MAX_COMMAND_METRICS,
    MAX_NAME_CHARS,
    CommandMetric,
    command_value,
    parse_command,
)
from edgemodbus.northbound.sparkplug.devices import NodeDevice
from edgemodbus.northbound.sparkplug.inbox import CommandInbox, CommandLog, RebirthPacer
from tests.sparkplug_wire import TYPES, encode, encode_metric


def one(datatype: str, value: Any, declared: str | None = None) -> CommandMetric:
    (metric,) = parse_command(encode([encode_metric(name="m", datatype=declared or datatype,
                                                    value=value)]))
    return metric


def refused(metric: CommandMetric, datatype: str) -> str:
    with pytest.raises(ValueError) as info:
        command_value(metric, TYPES[datatype])
    return str(info.value)


def test_the_issues_silent_conversions_are_refused() -> None:
    """Float 12.5 to a UInt16 was written as 12, true as 1, "99" as 99."""
    assert "12.5 is not a whole number; UInt16 takes integers only" in refused(
        one("Float", 12.5), "UInt16")
    assert refused(one("Boolean", True), "UInt16") == (
        "its datatype Boolean does not match the metric's UInt16")
    assert refused(one("String", "99"), "UInt16") == (
        "its datatype String does not match the metric's UInt16")
    assert refused(one("UInt16", 1), "Boolean") == (
        "its datatype UInt16 does not match the metric's Boolean")


def test_lossless_conversions_are_taken() -> None:
    assert command_value(one("Double", 12.0), TYPES["UInt16"]) == 12
    assert command_value(one("Int32", -7), TYPES["Double"]) == -7.0
    assert command_value(one("Float", 0.5), TYPES["Double"]) == 0.5
    assert command_value(one("Int16", -2), TYPES["Int16"]) == -2
    assert command_value(one("Int16", -2), TYPES["Int64"]) == -2  # declared signed
    assert command_value(one("Boolean", False), TYPES["Boolean"]) is False
    assert command_value(one("String", "x"), TYPES["String"]) == "x"
    assert command_value(one("DateTime", 1_700_000_000_000), TYPES["DateTime"]) == (
        1_700_000_000_000)
    assert "no exact Float (32-bit) value" in refused(one("Double", 0.1), "Float")
    assert "no exact Double value" in refused(one("Int64", (1 << 53) + 1), "Double")


@given(st.floats(allow_nan=True, allow_infinity=True, width=64))
def test_a_double_reaches_an_integer_metric_only_when_whole(x: float) -> None:
    metric = one("Double", x)
    whole = math.isfinite(x) and x == int(x) and 0 <= x <= 0xFFFF_FFFF_FFFF_FFFF
    if whole:
        assert command_value(metric, TYPES["UInt64"]) == int(x)
    elif not (math.isfinite(x) and x == int(x)):
        with pytest.raises(ValueError, match="not a whole number"):
            command_value(metric, TYPES["UInt64"])


@given(st.floats(allow_nan=False, allow_infinity=False, width=64))
def test_a_double_reaches_a_float_metric_only_when_exact(x: float) -> None:
    try:
        exact = struct.unpack("<f", struct.pack("<f", x))[0] == x
    except OverflowError:
        exact = False
    metric = one("Double", x)
    if exact:
        assert command_value(metric, TYPES["Float"]) == x
    else:
        with pytest.raises(ValueError, match="no exact Float"):
            command_value(metric, TYPES["Float"])


def test_caps_refuse_the_message_without_echoing_it() -> None:
    huge_name = "n" * (5 * 1024 * 1024)
    payload = encode([encode_metric(name=huge_name, datatype="UInt16", value=1)])
    with pytest.raises(ValueError) as info:
        parse_command(payload)
    assert str(info.value) == (f"payload of {len(payload)} bytes is over the limit of "
                               f"{MAX_COMMAND_BYTES}")
    with pytest.raises(ValueError, match=f"a name of {MAX_NAME_CHARS + 1} characters"):
        parse_command(encode([encode_metric(name="n" * (MAX_NAME_CHARS + 1),
                                            datatype="UInt16", value=1)]))
    many = encode([encode_metric(alias=1, datatype="Boolean", value=True)]
                  * (MAX_COMMAND_METRICS + 1))
    with pytest.raises(ValueError, match=f"{MAX_COMMAND_METRICS + 1} metrics in one "
                                         f"message, over the limit of {MAX_COMMAND_METRICS}"):
        parse_command(many)


def test_rebirths_are_paced_and_folded() -> None:
    now = [100.0]
    pacer = RebirthPacer(5.0, clock=lambda: now[0])
    assert pacer.request() is True
    assert [pacer.request() for _ in range(999)] == [False] * 999
    assert pacer.due == 105.0 and not pacer.take_due()
    now[0] = 105.0
    assert pacer.take_due() and not pacer.take_due()
    assert pacer.request() is False  # within 5 s of the folded one
    assert RebirthPacer(0.0).request() and RebirthPacer(0.0).request()


class Recorder:
    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self.events: list[tuple[Any, ...]] = []
        self.writes: list[list[CommandMetric]] = []


def inbox(rec: Recorder, devices: dict[str, NodeDevice] | None = None) -> CommandInbox:
    return CommandInbox(lambda key: rec.counts.update([key]), rec.events.append,
                        (devices or {}).get, lambda dev, ms: rec.writes.append(ms),
                        CommandLog(logging.getLogger("edgemodbus.sparkplug")))


def test_a_flood_of_bad_commands_is_counted_and_logs_a_few_lines(
        caplog: pytest.LogCaptureFixture) -> None:
    """The issue's NCMD of 200,000 unsupported metrics, 1,000 of them, and DCMDs for
    an unknown device with a long topic: every message counted, three log lines per kind,
    no long text in them."""
    caplog.set_level(logging.INFO, logger="edgemodbus.sparkplug")
    rec = Recorder()
    box = inbox(rec)
    flood = encode([encode_metric(name=f"x{i}", datatype="Boolean", value=True)
                    for i in range(200_000)])
    unsupported = encode([encode_metric(name="Other/" + "y" * 200, datatype="Int32",
                                        value=1)])
    for _ in range(3):
        box.node(flood)
    for _ in range(1000):
        box.node(unsupported)
        box.device_command("d" * 100_000, b"")
    for _ in range(1000):
        box.node(encode([encode_metric(name="Node Control/Rebirth", datatype="Boolean",
                                       value=True)]))
    assert rec.counts["commands"] == 3003
    assert rec.counts["commandErrors"] == 2003
    assert rec.events == [("rebirth", "NCMD")] * 1000  # paced by the publisher's thread
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 9, lines
    assert max(len(line) for line in lines) < 300, lines
    assert "over the limit" in lines[0]


def test_unsupported_ncmd_metric_is_named_by_a_short_prefix(
        caplog: pytest.LogCaptureFixture) -> None:
    rec = Recorder()
    inbox(rec).node(encode([encode_metric(name="Other/" + "y" * 200, datatype="Int32",
                                          value=1)]))
    (line,) = [r.getMessage() for r in caplog.records]
    assert line == ("Sparkplug: NCMD: 1 metric(s) ignored, e.g. 'Other/yyyyyyyyyyyyyyyyyyyyy"
                    "yyyyy'... (206 chars) (only Node Control/Rebirth or Node Control/Read "
                    "= true is supported)")


def test_read_metrics_start_reads_and_bad_ones_are_refused_whole() -> None:
    """docs/reporting.md: Device Control/Read = true in a DCMD reads that device (after
    the writes it came with), Node Control/Read = true in an NCMD every device; any
    other value refuses the message, nothing written or read."""
    rec = Recorder()
    reads: list[tuple[str | None, list[str] | None]] = []
    dev = NodeDevice(cast(Any, None), "dev1")
    dev.metrics = {"sp": cast(Any, None), "t0": cast(Any, None)}  # as born
    box = CommandInbox(lambda key: rec.counts.update([key]), rec.events.append,
                       {"dev1": dev}.get, lambda d, ms: rec.writes.append(ms),
                       CommandLog(logging.getLogger("edgemodbus.sparkplug")),
                       lambda d, names: reads.append((None if d is None else d.code, names)))
    read = encode_metric(name="Device Control/Read", datatype="Boolean", value=True)

    def read_item(name: str) -> bytes:
        return encode_metric(name="Device Control/Read", datatype="String", value=name)

    box.device_command("dev1", encode([read]))
    box.device_command("dev1", encode([encode_metric(name="sp", datatype="UInt16", value=1),
                                       read]))
    box.node(encode([encode_metric(name="Node Control/Read", datatype="Boolean",
                                   value=True)]))
    box.device_command("dev1", encode([read_item("t0"), read_item("sp"), read_item("t0")]))
    box.device_command("dev1", encode([read_item("t0"), read]))  # true: the whole device
    assert reads == [("dev1", None), ("dev1", None), (None, None), ("dev1", ["t0", "sp"]),
                     ("dev1", None)]
    assert [[m.name for m in ms] for ms in rec.writes] == [["sp"]]
    for bad in (encode_metric(name="Device Control/Read", datatype="Boolean", value=False),
                encode_metric(name="Device Control/Read", datatype="UInt16", value=1),
                read_item("nosuch")):
        box.device_command("dev1", encode([encode_metric(name="sp", datatype="UInt16",
                                                         value=2), bad]))
    box.node(encode([encode_metric(name="Node Control/Read", datatype="String", value="x")]))
    assert len(reads) == 5 and len(rec.writes) == 1  # nothing read or written
    assert rec.counts == {"commands": 9, "readsRefused": 3, "commandErrors": 1}


def test_a_dcmd_with_a_5_mb_name_is_refused_in_one_short_line(
        caplog: pytest.LogCaptureFixture) -> None:
    rec = Recorder()
    dev = NodeDevice(cast(Any, None), "dev1")
    box = inbox(rec, {"dev1": dev})
    box.device_command("dev1", encode([encode_metric(name="n" * (5 << 20), datatype="UInt16",
                                                     value=1)]))
    box.device_command("dev1", encode([encode_metric(name="sp", datatype="UInt16", value=1)]))
    assert rec.counts == {"commands": 2, "writesRefused": 1}
    assert [[m.name for m in ms] for ms in rec.writes] == [["sp"]]
    (line,) = [r.getMessage() for r in caplog.records]
    assert line.startswith("dev1: DCMD write (payload) refused: payload of 5242") and len(
        line) < 120, line
