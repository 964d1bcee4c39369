"""Issues #24 and #25: misspelt keys are errors, unknown ones bounded warnings; JSON we
read within size and depth limits; strings of bounded length; host names checked at
load; a duration that would round to 0 refused; a non-regular file refused."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.config import (
    ConfigError,
    DeviceAddressItem,
    DeviceConfig,
    DeviceOrganizationParameter,
    DriverModbusRtuParameter,
    load_device_config,
)
from edgemodbus.config.compat import norm_key
from edgemodbus.config.jsonfile import MAX_JSON_BYTES, MAX_JSON_DEPTH
from edgemodbus.config.keys import (
    UI_KEYS,
    UNKNOWN_KEY_LINES,
    allowed_distance,
    distance,
    misspelt,
)
from edgemodbus.gateway.config import load_gateway_config
from edgemodbus.northbound.mqtt import MqttSettings
from edgemodbus.serve import ServeSettings

DATA = Path(__file__).resolve().parents[2] / "data"
ITEM = {"name": "t", "address": "hr:1", "deviceDataType": "Int16"}


def problems(source: Any) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_device_config(source)
    return [str(p) for p in info.value.problems]


def gateway_problems(source: dict[str, Any]) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_gateway_config(source)
    return [str(p) for p in info.value.problems]


# --- misspelt keys (#24) ------------------------------------------------------------------

@pytest.mark.parametrize(("source", "expected"), [
    ({"addressList": [{**ITEM, "dataMultipler": 0.1}]},
     "addressList[0].dataMultipler: unknown key: did you mean dataMultiplier?"),
    ({"communication": {"slaveID": 1, "baudRtae": 9600}},
     "communication.baudRtae: unknown key: did you mean baudRate?"),
    ({"organization": {"deviceCdoe": "x"}},
     "organization.deviceCdoe: unknown key: did you mean deviceCode?"),
    ({"comunication": {}}, "comunication: unknown key: did you mean communication?"),
    ({"addressList": [ITEM], "actions": [{"name": "a", "functonCode": 6, "parameters": [
        {"name": "p", "item": "t"}]}]},
     "actions[0].functonCode: unknown key: did you mean functionCode?"),
])
def test_a_misspelt_key_is_an_error_naming_the_key_meant(source: dict[str, Any],
                                                          expected: str) -> None:
    """It used to be a warning, and the item read unscaled."""
    found = problems(source)
    assert any(line.startswith(expected) for line in found), found


def test_a_misspelt_mqtt_key_is_an_error() -> None:
    """"hots" connected to the default host."""
    assert gateway_problems({"mqtt": {"hots": "broker.local"}}) == [
        "mqtt.hots: unknown key: did you mean host? (a misspelt key would be ignored)"]
    assert any(p.startswith("serve.idleTimeotS: unknown key: did you mean idleTimeoutS?")
               for p in gateway_problems({"serve": {"idleTimeotS": 5}}))


def test_ui_keys_and_other_unknown_keys_stay_warnings(caplog: pytest.LogCaptureFixture
                                                      ) -> None:
    caplog.set_level(logging.WARNING, logger="edgemodbus.config")
    descriptor = json.loads((DATA / "seed-descriptor.json").read_text(encoding="utf-8"))
    ui = {k: v for k, v in descriptor["addressParameter"][0].items()
          if norm_key(k) not in DeviceAddressItem.key_table()}
    assert ui  # label, orderNo, controlType, category...
    cfg = load_device_config({"communication": {"label": "x", "Speed": 1},
                              "addressList": [{**ITEM, **ui, "colour": "red"}]})
    assert cfg.address_list[0].name == "t"
    messages = [r.getMessage() for r in caplog.records]
    assert "communication: unknown key 'label' ignored" in messages
    assert "addressList[0]: unknown key 'colour' ignored" in messages
    # the seed's own file loads without an error
    assert load_device_config(DATA / "seed-device.json").communication.slave_id == 2


SECTIONS = [DeviceConfig, DeviceOrganizationParameter, DriverModbusRtuParameter,
            DeviceAddressItem, MqttSettings, ServeSettings]


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_one_edit_of_a_long_key_is_always_caught(data: st.DataObject) -> None:
    """Any key of six or more characters with one letter dropped, doubled, changed or
    swapped with its neighbour is refused naming a key of the section, unless the edit
    made another known key or a UI key."""
    section = data.draw(st.sampled_from(SECTIONS), label="section")
    table = section.key_table()
    known = data.draw(st.sampled_from(sorted(k for k in table if len(k) >= 6)), label="key")
    at = data.draw(st.integers(0, len(known) - 2), label="at")
    edit = data.draw(st.sampled_from(["drop", "double", "change", "swap"]), label="edit")
    letter = data.draw(st.sampled_from("abcdefghijklmnopqrstuvwxyz"), label="letter")
    typo = {"drop": known[:at] + known[at + 1:],
            "double": known[:at] + known[at] + known[at:],
            "change": known[:at] + letter + known[at + 1:],
            "swap": known[:at] + known[at + 1] + known[at] + known[at + 2:]}[edit]
    if typo in table or typo in UI_KEYS or typo == known:
        return
    with pytest.raises((ConfigError, ValueError)) as info:
        section.model_validate({typo: 1})
    assert f"unknown key: did you mean {table[known]}?" in str(info.value) or \
        "unknown key: did you mean" in str(info.value), str(info.value)


def reference_osa(a: str, b: str) -> int:
    """Optimal string alignment distance, the textbook full table (independent of the
    early-exit implementation under test)."""
    d = [[0] * (len(b) + 1) for _ in range(len(a) + 1)]
    for i in range(len(a) + 1):
        d[i][0] = i
    for j in range(len(b) + 1):
        d[0][j] = j
    for i in range(1, len(a) + 1):
        for j in range(1, len(b) + 1):
            cost = 0 if a[i - 1] == b[j - 1] else 1
            d[i][j] = min(d[i - 1][j] + 1, d[i][j - 1] + 1, d[i - 1][j - 1] + cost)
            if i > 1 and j > 1 and a[i - 1] == b[j - 2] and a[i - 2] == b[j - 1]:
                d[i][j] = min(d[i][j], d[i - 2][j - 2] + 1)
    return d[len(a)][len(b)]


@settings(max_examples=500, deadline=None)
@given(a=st.text("abcd", max_size=8), b=st.text("abcd", max_size=8),
       limit=st.integers(0, 3))
def test_distance_agrees_with_the_textbook_table(a: str, b: str, limit: int) -> None:
    assert distance(a, b, limit) == min(reference_osa(a, b), limit + 1)


@settings(max_examples=400, deadline=None)
@given(data=st.data())
def test_the_indexed_lookup_agrees_with_comparing_every_key(data: st.DataObject) -> None:
    """misspelt() compares an unknown key only with the keys its deletion variants
    reach; comparing it with every key of the section (the textbook distance) finds
    the same key."""
    table = data.draw(st.sampled_from(SECTIONS), label="section").key_table()
    base = data.draw(st.sampled_from(sorted(table)), label="key")
    key = data.draw(st.one_of(
        st.text("abcdefghijklmnopqrstuvwxyz", min_size=3, max_size=12),
        st.lists(st.sampled_from(["drop", "swap", "change", "add"]), max_size=3).map(
            lambda edits: _edited(base, edits))), label="unknown")
    if norm_key(key) in table:
        return
    close = sorted((reference_osa(norm_key(key), known), known) for known in table
                   if len(norm_key(key)) >= 3
                   and reference_osa(norm_key(key), known) <= allowed_distance(known))
    expected = table[close[0][1]] if close else None
    assert misspelt(table, key, frozenset()) == expected


def _edited(word: str, edits: list[str]) -> str:
    for k, edit in enumerate(edits):
        at = (7 * k + 3) % max(1, len(word) - 1)
        if edit == "drop":
            word = word[:at] + word[at + 1:]
        elif edit == "swap" and len(word) > at + 1:
            word = word[:at] + word[at + 1] + word[at] + word[at + 2:]
        elif edit == "change":
            word = word[:at] + "q" + word[at + 1:]
        else:
            word = word[:at] + "x" + word[at:]
    return word


def test_short_keys_allow_one_edit_only() -> None:
    assert allowed_distance("host") == 1 and allowed_distance("datamultiplier") == 2
    assert allowed_distance("id") == 0
    # "unit" and "type", "metrics" and "retries" (two edits) are no typos of each other
    load_device_config({"communication": {"metrics": 1},
                        "addressList": [{**ITEM, "typo": 1, "unitxy": "V", "Quality": 1}]})


# --- unknown keys, bounded (#25) -----------------------------------------------------------

def test_200k_unknown_keys_are_a_bounded_number_of_lines(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="edgemodbus.config")
    many = {f"k{i:06d}": i for i in range(200_000)}
    started = time.perf_counter()
    load_device_config({"organization": many, "addressList": [ITEM]})
    took = time.perf_counter() - started
    messages = [r.getMessage() for r in caplog.records if r.name == "edgemodbus.config"]
    assert len(messages) == UNKNOWN_KEY_LINES + 1, len(messages)
    assert messages[0] == "organization: unknown key 'k000000' ignored"
    assert messages[-1] == f"...: and {200_000 - UNKNOWN_KEY_LINES:,} more unknown keys ignored"
    assert sum(map(len, messages)) < 5000
    assert took < 60, took  # measured: a few seconds on a loaded 2-core machine


def test_a_huge_unknown_key_is_cut_in_the_warning(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="edgemodbus.config")
    load_device_config({"communication": {"x" * 1_000_000: 1}})
    (message,) = [r.getMessage() for r in caplog.records if r.name == "edgemodbus.config"]
    assert len(message) < 120, message


# --- string lengths, hosts, durations (#25) ------------------------------------------------

@pytest.mark.parametrize(("source", "path"), [
    ({"organization": {"deviceCode": "d" * 10_000_000}}, "organization.deviceCode"),
    ({"communication": {"transport": "rtu-over-tcp", "tcpHost": "h" * 10_000_000}},
     "communication.tcpHost"),
    ({"communication": {"dtuId": "i" * 300}}, "communication.dtuId"),
    ({"addressList": [{**ITEM, "description": "x" * 5000}]}, "addressList[0].description"),
])
def test_a_too_long_string_names_the_field_and_is_not_echoed(source: dict[str, Any],
                                                              path: str) -> None:
    found = problems(source)
    assert len(found) == 1 and found[0].startswith(path), found
    assert "characters: at most" in found[0] and len(found[0]) < 400, found[0][:500]


def test_a_10mb_gateway_id_or_mqtt_host_is_refused_in_one_short_line() -> None:
    for source, path in (({"gatewayId": "g" * 10_000_000}, "gatewayId"),
                         ({"mqtt": {"host": "h" * 10_000_000}}, "mqtt.host")):
        (line,) = gateway_problems(source)
        assert line.startswith(path) and len(line) < 400, line[:500]


@pytest.mark.parametrize("host", ["plc..local", "a" * 64 + ".local", ".plc", "plc 1",
                                  "tcp://plc1:502", "x" * 254])
def test_a_host_that_cannot_be_resolved_is_refused_at_load(host: str) -> None:
    """"plc..local" or a label over 63 characters raised UnicodeError in the line's
    worker thread (socket.getaddrinfo's IDNA encoding) and killed it."""
    found = problems({"communication": {"transport": "rtu-over-tcp", "tcpHost": host}})
    assert found and found[0].startswith("communication.tcpHost"), found
    with pytest.raises(UnicodeError):
        if "." in host and len(host) < 254 and " " not in host and "/" not in host:
            host.encode("idna")  # what the old code let through to the resolver
        else:
            raise UnicodeError("not an IDNA case")
    (line,) = gateway_problems({"mqtt": {"host": host}})
    assert line.startswith("mqtt.host"), line


@pytest.mark.parametrize("host", ["plc1.local", "192.168.0.10", "::1", "plc_1", "localhost",
                                  "münchen.example", "plc1.local."])
def test_good_hosts_are_accepted(host: str) -> None:
    cfg = load_device_config({"communication": {"transport": "rtu-over-tcp",
                                                "tcpHost": host}})
    assert cfg.communication.tcp_host == host


def test_an_idle_timeout_that_rounds_to_zero_is_refused() -> None:
    (line,) = gateway_problems({"serve": {"idleTimeoutS": 1e-12}})
    assert line.startswith("serve.idleTimeoutS 1e-12: rounds to 0 ms"), line
    assert load_gateway_config({"serve": {"idleTimeoutS": 0}}).serve is not None
    assert load_gateway_config({"serve": {"idleTimeoutS": 0.001}}).serve is not None


# --- JSON size and depth; files that are no regular file (#24, #25) -------------------------

def test_a_deeply_nested_file_is_one_error_naming_the_file_and_the_limit(
        tmp_path: Path) -> None:
    """A 100,000-deep nesting raised RecursionError (a traceback)."""
    deep = tmp_path / "deep.json"
    deep.write_text('{"organization": {"metadata": ' + "[" * 100_000 + "]" * 100_000 + "}}")
    (line,) = problems(deep)
    assert line.startswith(f"{deep}: nested more than {MAX_JSON_DEPTH} levels"), line
    # within what json decodes, the depth is still bounded and the place named
    nested: Any = 1
    for _ in range(MAX_JSON_DEPTH + 5):
        nested = {"a": nested}
    (line,) = problems({"organization": {"metadata": nested}})
    assert line.startswith("<dict>: organization.metadata.a.a.a.a...: nested more than"), line


def test_a_file_over_the_size_limit_is_refused_unread(tmp_path: Path) -> None:
    huge = tmp_path / "huge.json"
    with open(huge, "wb") as file:
        file.truncate(MAX_JSON_BYTES + 1)  # sparse: nothing written
    (line,) = problems(huge)
    assert line == f"{huge}: {MAX_JSON_BYTES + 1:,} bytes: a JSON file we read has at most " \
        f"{MAX_JSON_BYTES:,}"


def test_a_fifo_is_refused_without_blocking(tmp_path: Path) -> None:
    fifo = tmp_path / "device.json"
    os.mkfifo(fifo)
    (line,) = problems(fifo)  # the old code blocked in open() until a writer came
    assert line == f"{fifo}: is a FIFO: give a JSON file"
    (line,) = problems(tmp_path)
    assert line == f"{tmp_path}: is a directory: give a JSON file"


def test_a_fifo_as_spool_or_tls_file_is_a_field_error(tmp_path: Path) -> None:
    fifo = tmp_path / "spool.db"
    os.mkfifo(fifo)
    (line,) = gateway_problems({"mqtt": {"storeAndForward": {"path": str(fifo)}}})
    assert line.startswith(
        f"mqtt.storeAndForward.path {str(fifo)!r}: is a FIFO, not a regular file"), line
    (line,) = gateway_problems({"mqtt": {"tls": {"caFile": str(fifo)}}})
    assert line == f"mqtt.tls.caFile {str(fifo)!r}: is a FIFO, not a regular file"


def test_the_cli_says_one_line_and_exits_2_for_a_nested_file(tmp_path: Path) -> None:
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 50_000 + "]" * 50_000)
    out = subprocess.run([sys.executable, "-m", "edgemodbus.cli", "plan", str(deep)],
                         capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 2, out.stderr
    assert out.stderr.splitlines() == [
        f"edgemodbus plan: {deep}: nested more than {MAX_JSON_DEPTH} levels deep (objects "
        "and lists): the limit of JSON we read"], out.stderr


def test_a_fifo_as_gateway_file_is_reported_on_reload_without_blocking(tmp_path: Path) -> None:
    """The reload's digest read the file whole: a FIFO blocked the main loop."""
    from edgemodbus.gateway.config import GatewayConfig, gateway_digest

    fifo = tmp_path / "gateway.json"
    os.mkfifo(fifo)
    assert gateway_digest(fifo, GatewayConfig()) is not None  # changed: it is loaded
    with pytest.raises(ConfigError, match="is a FIFO: give a JSON file"):
        load_gateway_config(fifo)


def test_the_metrics_host_is_checked_at_load() -> None:
    (line,) = gateway_problems({"metrics": {"host": "plc..local"}})
    assert line.startswith("metrics.host 'plc..local': is not a host name"), line
