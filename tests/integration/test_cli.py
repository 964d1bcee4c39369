"""The ``edgemodbus`` command as a person uses it: one process per call."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tests.peers import PymodbusSlave, default_register

DATA = Path(__file__).resolve().parents[1] / "data"


def cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "edgemodbus.cli", *args],
        capture_output=True, text=True, timeout=timeout, check=False,
    )


def test_plan_of_the_seed_file() -> None:
    out = cli("plan", str(DATA / "seed-device.json"))
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "14 items, 2 requests per cycle (slave 2)"
    assert lines[1].startswith("  FC03 hr:1-12 (12): tag1, tag2, tag3, tag4, pooled, tag5")
    assert lines[2] == "  FC03 hr:99-99 (1): tag99"


def test_descriptor_is_json() -> None:
    out = cli("descriptor")
    assert out.returncode == 0
    desc = json.loads(out.stdout)
    assert desc["driverType"] == "DriverModbusRtu"
    assert "Double" in desc["supportedDataTypes"]


def test_read_and_write_one_value() -> None:
    with PymodbusSlave("rtu-over-tcp", units=(2,)) as slave:
        base = ["--host", "127.0.0.1", "--port", str(slave.port), "--slave", "2"]
        out = cli("read", *base, "hr:10")
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == str(default_register(2, "hr", 10))
        out = cli("write", *base, "--type", "Int32", "--format", "CDAB", "hr:20", "-123456")
        assert (out.returncode, out.stdout.strip()) == (0, "ok"), out.stderr
        assert slave.registers(2, "hr", 20, 2) == [0x1DC0, 0xFFFE]  # -123456 low word first
        out = cli("read", *base, "--type", "Int32", "--format", "CDAB", "hr:20")
        assert out.stdout.strip() == "-123456"


def test_errors_are_one_line_and_non_zero(tmp_path: Path) -> None:
    with PymodbusSlave("rtu-over-tcp", units=(2,)) as slave:
        out = cli("read", "--host", "127.0.0.1", "--port", str(slave.port), "--slave", "9",
                  "--timeout", "200", "hr:1")
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1 and "not responding" in out.stderr
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"communication": {"baudRate": 300}, "addressList": []}))
    out = cli("plan", str(bad))
    assert out.returncode == 2
    assert "baudRate" in out.stderr and "300" in out.stderr and "1200..921600" in out.stderr
    out = cli("read", "--host", "127.0.0.1", "hr:99999")
    assert out.returncode == 2 and "99999" in out.stderr and "0..65535" in out.stderr


def test_demo_runs_and_summarises() -> None:
    out = cli("demo", "--seconds", "2.5", "--slaves", "1,2")
    assert out.returncode == 0, out.stderr
    text = out.stdout
    assert "simulator: slaves 1,2 on rtu-over-tcp://127.0.0.1:" in text
    assert "Model        PUMP-01" in text and "Model        PUMP-02" in text
    assert "Energy       2000 kWh" in text  # UInt32 CDAB, low word first
    summary = [line for line in text.splitlines() if line.startswith("Demo001-")]
    assert len(summary) == 2 and all("0 timeouts" in line for line in summary)
    assert all(" 0 cycles" not in line for line in summary)


def test_simulate_dials_a_listening_driver() -> None:
    """`edgemodbus simulate --dial` plays a DTU that dials in to a listen-mode driver."""
    import edgemodbus as em
    from tests.peers import free_port
    from tests.waiting import wait_for

    port = free_port()
    cfg = em.load_device_config({
        "communication": {"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "registration": "text", "dtuId": "DTU-7",
                          "slaveId": 3, "readCycle": 200, "readTimeout": 500},
        "addressList": [{"name": "r", "address": "hr:42", "deviceDataType": "UInt16"}],
    })
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    proc = subprocess.Popen(
        [sys.executable, "-m", "edgemodbus.cli", "simulate", "--dial", f"127.0.0.1:{port}",
         "--registration", "DTU-7", "--slaves", "3"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        item = cfg.address_list[0]
        wait_for(lambda: item.status is em.ItemStatus.OK, timeout=15, what="a value via the DTU")
        assert item.value == (3 * 1000 + 42)  # the simulator's address-derived value
        assert drv.device_driver_status is em.DeviceDriverStatus.RUNNING
    finally:
        proc.terminate()
        proc.communicate(timeout=10)
        drv.stop_device()
    out = cli("simulate", "--dial", "nowhere")
    assert out.returncode == 2 and "HOST:PORT" in out.stderr
