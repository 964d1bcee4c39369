"""Serial hardware flow control (flowControl rtscts, docs/links.md).  There is no
hardware here: the flag is checked on a pty (socat), where termios keeps c_cflag as
set, and a pymodbus slave on the pty's other end answers a device with rtscts."""

from __future__ import annotations

import os
import termios

import pytest

import edgemodbus as em
from edgemodbus.line.connect import open_link
from edgemodbus.line.endpoint import LineTiming, SerialPort
from edgemodbus.stats import LineStats
from tests.integration.test_driver import Running
from tests.peers import PtyPair, PymodbusSlave
from tests.waiting import wait_for


@pytest.mark.parametrize("flow", ["none", "rtscts"])
def test_crtscts_is_set_on_the_port_only_with_rtscts(pty_pair: PtyPair, flow: str) -> None:
    link = open_link(SerialPort(str(pty_pair.a), flow_control=flow), LineTiming(),
                     LineStats())
    try:  # termios belongs to the tty, not to the fd: read it through one of ours
        fd = os.open(pty_pair.a, os.O_RDWR | os.O_NOCTTY)
        try:
            cflag = termios.tcgetattr(fd)[2]
        finally:
            os.close(fd)
    finally:
        link.close()
    assert bool(cflag & termios.CRTSCTS) == (flow == "rtscts")


def test_a_device_with_rtscts_reads_a_pymodbus_slave(serial_slave: PymodbusSlave) -> None:
    cfg = em.load_device_config({
        "organization": {"deviceCode": "rtscts"},
        "communication": {"transport": "rtu", "comPort": serial_slave.master_path,
                          "baudRate": 19200, "slaveId": 1, "flowControl": "rtscts",
                          "readCycle": 100, "readTimeout": 500},
        "addressList": [{"name": "a", "address": "hr:0", "deviceDataType": "UInt16"}],
    })
    with Running(cfg) as drv:
        wait_for(lambda: drv.address_items[0].status == "Ok", 10, "a value read")
