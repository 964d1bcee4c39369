"""Issue 24, "DTU registration" on both engines: an id that contains its port's heartbeat
registers and is polled whether the DTU's line runs on a thread of its own or on the loop
engine (the default for DTUs that dial in).  The registration is told by the listener
before either engine takes the connection (line/dtu_listener.py); this checks that the
id it tells is the one the line of each engine serves, with heartbeats before the
registration and between the replies."""

from __future__ import annotations

from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.sim import Simulator, default_register
from tests.engines import with_engine
from tests.peers import free_port
from tests.waiting import wait_for


def _device(port: int, dtu_id: str, **keys: Any) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"dev-{dtu_id}"},
        "communication": with_engine({
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
            "listenPort": port, "dtuId": dtu_id, "registrationTimeout": 2000,
            "slaveId": 1, "readTimeout": 500, "readCycle": 100, "reconnectInterval": 300,
            **keys}),
        "addressList": [{"name": "r7", "address": "hr:7", "deviceDataType": "UInt16"}],
    })


@pytest.mark.usefixtures("engine")
@pytest.mark.parametrize(("dtu_id", "keys", "packet", "heartbeat"), [
    ("DTU-HB-7", {"registration": "text", "heartbeat": "HB"}, b"HBDTU-HB-7", b"HB"),
    ("0100A3", {"registration": "hex", "heartbeatHex": "00"}, bytes.fromhex("000100A3"),
     b"\x00"),
    ("DTU-HB-7", {"registration": "regex", "heartbeat": "HB",
                  "registrationPattern": r"ID:([\w-]+)\r\n"}, b"HBID:DTU-HB-7\r\n", b"HB"),
], ids=["text", "hex", "regex"])
def test_an_id_containing_its_heartbeat_registers_on_each_engine(
        dtu_id: str, keys: dict[str, Any], packet: bytes, heartbeat: bytes) -> None:
    port = free_port()
    cfg = _device(port, dtu_id, **keys)
    drv = em.DriverModbusRtu()
    with Simulator([1]) as sim:
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        try:
            client = sim.dial("127.0.0.1", port, registration=packet, heartbeat=heartbeat,
                              heartbeat_interval=0.05)
            item = cfg.address_list[0]
            wait_for(lambda: item.value == default_register(1, 7), timeout=30,
                     what=f"{dtu_id} registered and polled")
            wait_for(lambda: drv.stats()["line"].get("heartbeats", 0) >= 3, timeout=30,
                     what="heartbeats discarded between the replies")
            requests = drv.stats()["responses"]
            wait_for(lambda: drv.stats()["responses"] > requests + 2, timeout=30,
                     what="polling goes on")
            assert not client.closed
        finally:
            drv.stop_device()
