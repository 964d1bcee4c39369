"""A folder of many template devices starts in one reload (gateway/service.py): the
devices share their read plans and compiled blocks, a bad file is reported and the rest
start, and a deviceCode stays unique without a scan of every device per start."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.codec import decoder
from edgemodbus.gateway import Gateway, load_gateway_config
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
            assert all(dev.driver.device_driver_status.value == "Connecting"
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
