"""An imported Kepware tag list polls what Kepware would read: the device file that
``edgemodbus import`` writes, polled against pymodbus (own process)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest

import edgemodbus as em
from edgemodbus.cli import main
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

CSV = (
    '"Tag Name","Address","Data Type","Respect Data Type","Client Access","Scan Rate",'
    '"Scaling","Raw Low","Raw High","Scaled Low","Scaled High","Scaled Data Type",'
    '"Clamp Low","Clamp High","Eng Units","Description"\n'
    '"Flow","400001","Float",1,R/W,200,"None",,,,,,0,0,"m3/h","Flow rate"\n'
    '"Level","40003","Word",1,RO,200,"Linear",0,1000,0,100,"Float",0,0,"%","Tank level"\n'
    '"Temp","300002","Short",1,RO,200,,,,,,,0,0,"degC",\n'
    '"Alarm","400005.3","Boolean",1,RO,200,,,,,,,0,0,,\n'
    '"Run","000017","Boolean",1,R/W,200,,,,,,,0,0,,\n'
    '"Door","100008","Default",1,RO,200,,,,,,,0,0,,\n'
)


def test_imported_kepware_tags_poll_their_values(tmp_path: Path) -> None:
    src, out = tmp_path / "tags.csv", tmp_path / "device.json"
    src.write_text(CSV, encoding="utf-8")
    assert main(["import", str(src), "-o", str(out), "--device-code", "Tank"]) == 0
    flow = struct.unpack(">2H", struct.pack(">f", 12.75))
    initial = {1: {"hr": {0: flow[0], 1: flow[1], 2: 437, 4: 0b1000},
                   "ir": {1: (-52) & 0xFFFF}, "co": {16: True}, "di": {7: True}}}
    with PymodbusSlave("tcp", units=(1,), fill="zero", initial=initial) as peer:
        device = json.loads(out.read_text(encoding="utf-8"))
        device["communication"].update({"transport": "tcp", "tcpHost": "127.0.0.1",
                                        "tcpPort": peer.port, "slaveId": 1})
        cfg = em.load_device_config(device)
        drv = em.DriverModbusRtu()
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        try:
            wait_for(lambda: all(i.status is em.ItemStatus.OK for i in cfg.address_list),
                     timeout=15, what="every imported tag read")
        finally:
            drv.stop_device()
    got = {i.name: i.value for i in cfg.address_list}
    assert got == {"Flow": 12.75, "Level": pytest.approx(43.7), "Temp": -52,
                   "Alarm": True, "Run": True, "Door": True}
