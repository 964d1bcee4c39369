"""``edgemodbus check`` (issue 29): device files, gateway files and config folders checked
the way the gateway loads them; one line per problem naming the file and the field,
exit 2 on any, a summary and exit 0 when all is well.  Nothing connects: the files name
a TCP port on 127.0.0.1 that nobody listens on, and the check still passes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.cli import main


def _device(code: str = "pump1", **comm: Any) -> dict[str, Any]:
    return {
        "organization": {"deviceCode": code},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": 9, "slaveId": 1, **comm},
        "addressList": [
            {"name": "Speed", "address": "hr:0", "deviceDataType": "UInt16"},
            {"name": "Level", "address": "hr:1", "deviceDataType": "Float"},
            {"name": "Alarm", "address": "coil:3", "deviceDataType": "Boolean"},
        ],
    }


def _write(path: Path, doc: dict[str, Any]) -> Path:
    path.write_text(json.dumps(doc))
    return path


def _check(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, list[str]]:
    code = main(["check", *args])
    out = capsys.readouterr().out
    return code, out.splitlines()


def test_a_good_device_file_sums_up(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    file = _write(tmp_path / "pump.json", _device())
    code, lines = _check(capsys, str(file))
    assert code == 0
    # hr:0 and hr:1-2 merge into one FC03 request, the coil is one FC01 request
    assert lines == ["ok: 1 device file (3 items, 2 requests per cycle), 0 gateway files"]


def test_each_problem_of_a_device_file_is_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = _device(dataFormat="XYZW")
    doc["communication"]["slaveId"] = 300
    doc["addressList"].append({"name": "Bad", "address": "hr:70000", "deviceDataType": "UInt16"})
    file = _write(tmp_path / "bad.json", doc)
    code, lines = _check(capsys, str(file))
    assert code == 2
    assert all(line.startswith(f"{file}: ") for line in lines), lines
    text = "\n".join(lines)
    assert "communication.slaveId 300" in text and "communication.dataFormat 'XYZW'" in text
    assert "hr:70000" in text
    assert not any(line.startswith("ok:") for line in lines)


def test_templates_are_resolved(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = _write(tmp_path / "meter.json", {
        "template": "eastron-sdm120",
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": 9}})
    code, lines = _check(capsys, str(good))
    assert code == 0 and lines[-1].startswith("ok: 1 device file ("), lines
    assert "(0 items" not in lines[-1]  # the template's items were checked
    missing = _write(tmp_path / "other.json", {**_device(), "template": "no-such-meter"})
    code, lines = _check(capsys, str(missing))
    assert code == 2 and len(lines) == 1 and "no-such-meter" in lines[0], lines


def test_an_unknown_key_warns_without_failing(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = _device()
    doc["communication"]["colour"] = "blue"
    file = _write(tmp_path / "pump.json", doc)
    code, lines = _check(capsys, str(file))
    assert code == 0
    assert lines[0].startswith(f"{file}: warning: ") and "colour" in lines[0], lines
    assert lines[-1].endswith("1 warnings")


def test_a_gateway_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = _write(tmp_path / "gateway.json", {"gatewayId": "gw1", "logFormat": "json"})
    code, lines = _check(capsys, str(good))
    assert (code, lines) == (0, ["ok: 0 device files (0 items, 0 requests per cycle), "
                                 "1 gateway file"])
    bad = _write(tmp_path / "site.json", {"gatewayId": "gw1", "logFormat": "xml",
                                           "statusCheckInterval": -5})
    code, lines = _check(capsys, "--gateway", str(bad), str(tmp_path / "gateway.json"))
    assert code == 2 and len(lines) == 2, lines
    assert all(line.startswith(f"{bad}: ") for line in lines)
    assert any("logFormat 'xml'" in line and "json" in line for line in lines), lines


def test_a_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _write(tmp_path / "gateway.json", {"gatewayId": "gw1", "serve": {
        "listen": "127.0.0.1:0", "units": [{"unitId": 1, "device": "pump1"}]}})
    _write(tmp_path / "a.json", _device("pump1"))
    _write(tmp_path / "b.json", _device("pump2"))
    (tmp_path / "notes.txt").write_text("not a device file")
    code, lines = _check(capsys, str(tmp_path))
    assert (code, lines) == (0, ["ok: 2 device files (6 items, 4 requests per cycle), "
                                 "1 gateway file"])


def test_a_folder_with_problems(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gateway = _write(tmp_path / "gateway.json", {"serve": {
        "listen": "127.0.0.1:0", "units": [{"unitId": 1, "device": "pump9"}]}})
    _write(tmp_path / "a.json", _device("pump1"))
    twin = _write(tmp_path / "b.json", _device("pump1"))
    code, lines = _check(capsys, str(tmp_path))
    assert code == 2
    assert lines == [
        f"{twin}: organization.deviceCode 'pump1': already used by a.json (the gateway "
        "starts only one)",
        f"{gateway}: serve.units[0].device 'pump9': no device has this deviceCode; "
        "known: pump1",
    ]


def test_a_path_that_is_not_there(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, lines = _check(capsys, str(tmp_path / "missing.json"))
    assert (code, lines) == (2, [f"{tmp_path / 'missing.json'}: no such file or directory"])


def test_entity_lookalikes_get_the_notice_in_check_too(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 24: ``40001`` without ``addressPrefix: entity`` gets the notice the gateway
    logs and ``plan`` prints (check said only "ok"); a notice does not fail the check."""
    path = tmp_path / "meter.json"
    path.write_text(json.dumps({
        "communication": {"transport": "tcp", "tcpHost": "127.0.0.1"},
        "addressList": [{"name": "a", "address": "40001", "deviceDataType": "UInt16"},
                        {"name": "b", "address": "30002", "deviceDataType": "UInt16"}]}))
    assert main(["check", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith(f"{path}: notice: item 'a': address '40001' is read as "
                               "holding register 40001 (hr:40001)"), lines
    assert lines[0].endswith("for Modicon numbering set addressPrefix: entity"), lines
    assert lines[-1] == ("ok: 1 device file (2 items, 2 requests per cycle), 0 gateway "
                         "files, 1 notices")
    path.write_text(json.dumps({
        "communication": {"transport": "tcp", "tcpHost": "127.0.0.1",
                          "addressPrefix": "entity"},
        "addressList": [{"name": "a", "address": "40001", "deviceDataType": "UInt16"}]}))
    assert main(["check", str(path)]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "ok: 1 device file (1 items, 1 requests per cycle), 0 gateway files"]
