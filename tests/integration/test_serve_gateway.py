"""The ``serve`` section of the gateway file: the gateway's devices served and forwarded
to over Modbus TCP (pymodbus' client as the master, pymodbus as the slaves), through a
reload that changes a device, and a unit naming no device."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

from edgemodbus.gateway import Gateway, load_gateway_config
from tests.conftest import SlaveFactory
from tests.peers import PymodbusSlave, default_register
from tests.waiting import wait_for


def device_file(peer: PymodbusSlave, slave: int, code: str, tags: int) -> dict[str, Any]:
    return {
        "organization": {"deviceCode": code},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": peer.port, "slaveId": slave, "readCycle": 50,
                          "readTimeout": 500, "retries": 0},
        "addressList": [{"name": f"t{i}", "address": f"hr:{i}", "deviceDataType": "UInt16"}
                        for i in range(tags)],
    }


@pytest.fixture
def folder(tmp_path: Path, slave_factory: SlaveFactory) -> Iterator[tuple[Path, PymodbusSlave]]:
    peer = slave_factory("rtu-over-tcp", units=(1, 2), size=200)
    (tmp_path / "meter1.json").write_text(json.dumps(device_file(peer, 1, "meter1", 3)))
    (tmp_path / "meter2.json").write_text(json.dumps(device_file(peer, 2, "meter2", 1)))
    (tmp_path / "gateway.json").write_text(json.dumps({"serve": {
        "listen": "127.0.0.1:0", "maxConnections": 4, "idleTimeoutS": 30,
        "units": [{"unitId": 1, "device": "meter1", "offset": 100, "maxAgeMs": 2000},
                  {"unitId": 9, "forward": "meter2", "timeoutMs": 500},
                  {"unitId": 3, "device": "nosuch"}]}}))
    yield tmp_path, peer


def test_gateway_serves_forwards_and_rebinds_on_reload(
        folder: tuple[Path, PymodbusSlave], caplog: pytest.LogCaptureFixture) -> None:
    path, _peer = folder
    gateway = Gateway(path, load_gateway_config(path / "gateway.json"),
                      path / "gateway.json")
    caplog.set_level(logging.INFO, "edgemodbus.service")
    gateway.start()
    client = None
    try:
        server = gateway.serving.server
        assert server is not None
        assert "'nosuch': no device has this deviceCode; known: meter1, meter2" in caplog.text
        client = ModbusTcpClient("127.0.0.1", port=server.port, timeout=2, retries=0)
        assert client.connect()
        want = [default_register(1, "hr", a) for a in range(3)]
        wait_for(lambda: getattr(client.read_holding_registers(100, count=3, device_id=1),
                                 "registers", None) == want, what="meter1 served at +100")
        rr = client.read_holding_registers(50, count=2, device_id=9)
        assert rr.registers == [default_register(2, "hr", a) for a in (50, 51)]
        assert client.read_holding_registers(0, count=1, device_id=3).exception_code == 0x0A
        # meter1 gets a fourth tag (an address list change: the driver keeps running);
        # the unit is bound again to the new map
        (path / "meter1.json").write_text(json.dumps(device_file(_peer, 1, "meter1", 4)))
        gateway.reload()
        want4 = [default_register(1, "hr", a) for a in range(4)]
        wait_for(lambda: getattr(client.read_holding_registers(100, count=4, device_id=1),
                                 "registers", None) == want4, what="the fourth tag served")
        # a changed unit in the gateway file: the new offset applies on reload
        gateway_file = json.loads((path / "gateway.json").read_text())
        gateway_file["serve"]["units"][0]["offset"] = 200
        (path / "gateway.json").write_text(json.dumps(gateway_file))
        gateway.reload()
        assert gateway.serving.server is server  # same listen settings: same server
        wait_for(lambda: getattr(client.read_holding_registers(200, count=4, device_id=1),
                                 "registers", None) == want4, what="meter1 served at +200")
        assert client.read_holding_registers(100, count=1, device_id=1).exception_code == 2
        # the host's batch callback is not the server's subscription: clearing it (as
        # a chained subscriber's detach once did) leaves the unit served, with no
        # re-hook: values keep following the slave
        meter1 = next(d for d in gateway.devices.values() if d.code == "meter1")
        meter1.driver.addresses_updated_callback = None
        gateway.serving.apply(gateway.config.serve, {
            d.code: (d.driver, d.cfg) for d in gateway.devices.values()})
        _peer.set_registers(1, "hr", 0, [4321])
        wait_for(lambda: getattr(client.read_holding_registers(200, count=1, device_id=1),
                                 "registers", None) == [4321], what="a new value served")
    finally:
        if client is not None:
            client.close()
        gateway.stop()
    assert gateway.serving.server is None
