"""The access keys of a listen-mode device reach the listener through the driver:
registrationKey, dtuAllowFrom and listenAllowFrom, as a device file gives them, decide
who may be the device's DTU (our simulator dials in as the DTUs)."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import ItemStatus
from edgemodbus.gateway import Gateway, GatewayConfig
from edgemodbus.line import dtu_registry
from edgemodbus.sim import Simulator, default_register
from tests.engines import with_engine
from tests.peers import free_port
from tests.waiting import wait_for

IMEI = "861234567890123"
KEY = "s3cretKey"


def keyed_device(port: int, **extra: Any) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": "keyed"},
        "communication": with_engine({
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
            "listenPort": port, "dtuId": IMEI, "registration": "regex",
            "registrationPattern": r"ID:(\d+);KEY:(?P<key>\w+)", "registrationKey": KEY,
            "registrationTimeout": 2000, "readTimeout": 300, "readCycle": 100,
            "byteTimeout": 50, **extra,
        }),
        "addressList": [{"name": "r0", "address": "3:0", "deviceDataType": "UInt16"}],
    })


def stats(port: int) -> dict[str, int]:
    return dtu_registry.stats()[f"127.0.0.1:{port}"]


@pytest.mark.usefixtures("engine")
def test_only_the_dtu_with_the_key_is_polled(caplog: pytest.LogCaptureFixture) -> None:
    port = free_port()
    cfg = keyed_device(port)
    drv = em.DriverModbusRtu()
    with Simulator(slaves=[1]) as sim:
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        try:
            impostor = sim.dial("127.0.0.1", port, registration=f"ID:{IMEI};KEY:guess\r\n"
                                .encode())
            wait_for(lambda: impostor.closed, what="the wrong key closed")
            assert stats(port)["badKey"] == 1 and stats(port)["registered"] == 0
            sim.dial("127.0.0.1", port, registration=f"ID:{IMEI};KEY:{KEY}\r\n".encode())
            wait_for(lambda: cfg.address_list[0].status is ItemStatus.OK, what="polled")
            assert cfg.address_list[0].value == default_register(1, 0)
            assert stats(port)["registered"] == 1
        finally:
            drv.stop_device()
    assert KEY not in caplog.text


@pytest.mark.parametrize(("key", "counter"), [("dtuAllowFrom", "refusedDtuNotAllowed"),
                                              ("listenAllowFrom", "refusedNotAllowed")])
def test_a_source_outside_the_allow_list_is_refused(key: str, counter: str) -> None:
    port = free_port()
    cfg = keyed_device(port, **{key: "192.0.2.0/24, 2001:db8::/32"})  # not 127.0.0.1
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        # a plain socket: listenAllowFrom resets the connection at accept, which may
        # come before the registration is sent, or even before connect() returned
        with contextlib.suppress(ConnectionResetError, BrokenPipeError), \
                socket.create_connection(("127.0.0.1", port), timeout=5) as client:
            client.sendall(f"ID:{IMEI};KEY:{KEY}\r\n".encode())
            while client.recv(64):
                pass  # until the listener closes it
        wait_for(lambda: stats(port)[counter] == 1, what="the refusal counted")
        assert stats(port)["registered"] == 0
    finally:
        drv.stop_device()


@pytest.mark.usefixtures("engine")
def test_a_changed_key_restarts_the_device_on_reload(tmp_path: Path,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    """to_dict() masks the key, so two keys look alike there: the reload compares the
    keys themselves and restarts the device with the new one."""
    port = free_port()
    path = tmp_path / "keyed.json"

    def write(key: str) -> None:
        data = keyed_device(port).to_dict(secrets=True)
        data["communication"]["registrationKey"] = key
        path.write_text(json.dumps(data), "utf-8")

    write(KEY)
    gateway = Gateway(tmp_path, GatewayConfig())
    caplog.set_level(logging.INFO, logger="edgemodbus")
    try:
        gateway.start()
        first = gateway.devices[path].driver
        write(KEY + "2")
        gateway.reload_devices()
        second = gateway.devices[path].driver
        assert second is not first and first.device_driver_status.value == "Stopped"
        assert gateway.devices[path].cfg.communication.registration_key.get_secret_value() \
            == KEY + "2"
    finally:
        gateway.stop()
    assert "keyed: restarted from keyed.json" in caplog.text
    assert KEY not in caplog.text
