"""A folder of many template devices starts in one reload (gateway/service.py,
gateway/bulk.py): the devices share their read plans and compiled blocks, a bad file is
reported and the rest start, a deviceCode stays unique without a scan of every device
per start, each file is read once, and the folder stops on a few threads."""

from __future__ import annotations

import gc
import hashlib
import json
import logging
import threading
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.codec import decoder
from edgemodbus.config import ConfigError, load_device_config
from edgemodbus.config.templates import template_bytes
from edgemodbus.gateway import Gateway, load_gateway_config
from edgemodbus.gateway.bulk import STOP_THREADS, read_device
from tests.engines import with_engine
from tests.peers import free_port

N = 40


def _device(port: int, n: int, code: str | None = None) -> dict[str, Any]:
    return {
        "organization": {"deviceCode": code or f"dtu{n:03d}"},
        "communication": with_engine({
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
            "dtuId": f"DTU{n:03d}", "registration": "text", "slaveId": 1, "readCycle": 5000}),
        "addressList": [{"name": f"t{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
                        for a in range(20)],
    }


def _gateway(folder: Path) -> Gateway:
    gateway_file = folder / "gateway.json"
    gateway_file.write_text("{}")
    return Gateway(folder, load_gateway_config(gateway_file), gateway_file)


@pytest.mark.usefixtures("engine")
def test_a_folder_of_template_devices_starts_sharing_plans_and_reports_the_bad_file(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    port = free_port()
    for n in range(N):
        (tmp_path / f"dtu{n:03d}.json").write_text(json.dumps(_device(port, n)))
    bad = _device(port, N)
    bad["addressList"][3]["deviceDataType"] = "UInt99"
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    gateway = _gateway(tmp_path)
    with caplog.at_level(logging.ERROR, logger="edgemodbus"):
        try:
            gateway.start()
            assert len(gateway.devices) == N
            # waiting for its DTU: Connecting, or Reconnecting once a try found no DTU (a
            # loop line tries at once, a line thread waits out its connect timeout)
            assert all(dev.driver.device_driver_status.value in ("Connecting", "Reconnecting")
                       for dev in gateway.devices.values())
            pollers = [dev.driver._poller for dev in gateway.devices.values()]
            shapes = {id(d._shape) for p in pollers if p is not None
                      for s in p.slots if (d := s.decoder) is not None}
            assert len(shapes) == 1  # one compiled block for the 40 devices
            assert len(decoder._SHAPES) >= 1
        finally:
            gateway.stop()
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "bad.json" in errors[0] and "UInt99" in errors[0], errors


def test_a_device_code_is_refused_while_held_and_free_once_its_holder_is_gone(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    port = free_port()
    (tmp_path / "a.json").write_text(json.dumps(_device(port, 1, "pump")))
    (tmp_path / "b.json").write_text(json.dumps(_device(port, 2, "pump")))
    gateway = _gateway(tmp_path)
    try:
        with caplog.at_level(logging.ERROR, logger="edgemodbus"):
            gateway.start()
        assert [p.name for p in gateway.devices] == ["a.json"]
        assert any("b.json" in r.getMessage() and "already used by a.json" in r.getMessage()
                   for r in caplog.records)
        (tmp_path / "a.json").write_text(json.dumps(_device(port, 1, "pump2")))
        gateway.reload_devices()  # a.json restarts as pump2: pump is free for b.json
        assert sorted(dev.code for dev in gateway.devices.values()) == ["pump", "pump2"]
        (tmp_path / "a.json").unlink()
        (tmp_path / "c.json").write_text(json.dumps(_device(port, 3, "pump2")))
        gateway.reload_devices()  # a.json gone: its code is free for c.json
        assert sorted(p.name for p in gateway.devices) == ["b.json", "c.json"]
    finally:
        gateway.stop()


def test_a_folder_stops_on_a_few_threads_not_one_per_device(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Before, the gateway stopped each device on a thread of its own (5,000 thread
    starts to stop 5,000 DTUs)."""
    port = free_port()
    for n in range(N):
        (tmp_path / f"dtu{n:03d}.json").write_text(json.dumps(_device(port, n)))
    gateway = _gateway(tmp_path)
    try:
        gateway.start()
        assert len(gateway.devices) == N
        drivers = [dev.driver for dev in gateway.devices.values()]
    finally:
        started: list[str] = []
        real_start = threading.Thread.start

        def counting(thread: threading.Thread) -> None:
            started.append(thread.name)
            real_start(thread)

        monkeypatch.setattr(threading.Thread, "start", counting)
        gateway.stop()
        monkeypatch.undo()
    assert all(d.device_driver_status.value == "Stopped" for d in drivers)
    assert 1 <= len(started) <= STOP_THREADS, started


def test_a_file_read_once_gives_the_digest_and_the_load_of_reading_it_twice(
        tmp_path: Path) -> None:
    """read_device against the two reads it replaces: the digest of the file's bytes
    and its template's, and load_device_config of its path (also for a bad file)."""
    port = free_port()
    templates = tmp_path / "templates"
    templates.mkdir()
    (templates / "meter.json").write_text(json.dumps(
        {"addressList": [{"name": "v", "address": "3:100", "deviceDataType": "Float"}]}))
    good = _device(port, 1)
    good["template"], good["templateDirs"] = "meter", ["templates"]
    cases = {"good.json": json.dumps(good), "bom.json": "\ufeff" + json.dumps(_device(port, 2)),
             "bad.json": json.dumps({**_device(port, 3), "addressList": [{"name": "x"}]}),
             "broken.json": "{\"organization\": ", "list.json": "[1, 2]"}
    for name, text in cases.items():
        path = tmp_path / name
        path.write_text(text)
        digest, load = read_device(path)
        assert digest == hashlib.sha256(path.read_bytes() + template_bytes(path)).hexdigest()
        try:
            expected: Any = load_device_config(path).to_dict(secrets=True)
        except ConfigError as exc:
            expected = str(exc)
        try:
            got: Any = load().to_dict(secrets=True)
        except ConfigError as exc:
            got = str(exc)
        assert got == expected, name
    assert template_bytes(tmp_path / "good.json") != b""  # the template took part


def test_the_folder_lists_regular_files_but_not_the_gateway_file_under_another_name(
        tmp_path: Path) -> None:
    gateway = _gateway(tmp_path)
    (tmp_path / "a.json").write_text("{}")
    (tmp_path / ".hidden.json").write_text("{}")
    (tmp_path / "dir.json").mkdir()
    (tmp_path / "alias.json").symlink_to(tmp_path / "gateway.json")
    (tmp_path / "link.json").symlink_to(tmp_path / "a.json")
    (tmp_path / "dangling.json").symlink_to(tmp_path / "nothing.json")
    assert [p.name for p in gateway.device_files()] == ["a.json", "link.json"]


def test_a_folder_started_is_frozen_for_the_collector_until_a_device_stops(
        tmp_path: Path) -> None:
    """The collector's first pass after a bulk start walked every object of every
    device (a sixth of the start); frozen, they are skipped until a device stops, when
    they are given back (its cycles collected as before)."""
    port = free_port()
    for n in range(3):
        (tmp_path / f"dtu{n:03d}.json").write_text(json.dumps(_device(port, n)))
    gateway = _gateway(tmp_path)
    try:
        gateway.start()
        assert gc.get_freeze_count() > 0 and gc.isenabled()
        (tmp_path / "dtu001.json").unlink()
        gateway.reload_devices()  # a device stops: everything thawed, nothing frozen
        assert gc.get_freeze_count() == 0
        (tmp_path / "dtu009.json").write_text(json.dumps(_device(port, 9)))
        gateway.reload_devices()  # one started, none stopped: frozen again
        assert gc.get_freeze_count() > 0
        (tmp_path / "dtu009.json").write_text(json.dumps(_device(port, 9, "other")))
        gateway.reload_devices()  # restarted (a stop inside the block): not frozen
        assert gc.get_freeze_count() == 0 and len(gateway.devices) == 3
    finally:
        gateway.stop()
        gc.unfreeze()
    assert gc.get_freeze_count() == 0


def test_a_file_named_like_json_text_finds_its_templates_beside_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The file's folder is where its templateDirs are, also for a path that starts
    with "{" (a str starting so is JSON text to load_device_config)."""
    folder = tmp_path / "{site}"
    (folder / "templates").mkdir(parents=True)
    (folder / "templates" / "meter.json").write_text(json.dumps(
        {"addressList": [{"name": "v", "address": "3:100", "deviceDataType": "UInt16"}]}))
    device = _device(free_port(), 1)
    device["template"], device["templateDirs"] = "meter", ["templates"]
    (folder / "x.json").write_text(json.dumps(device))
    monkeypatch.chdir(tmp_path)  # not the file's folder
    _, load = read_device(Path("{site}/x.json"))
    assert load().address_list[0].name == "v"
