"""The ``edgemodbus`` command as a person uses it: one process per call."""

from __future__ import annotations

import json
import math
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.cli import json_line, value_text
from edgemodbus.codec import Float32, float32_short, float32_text
from tests.peers import PtyPair, PymodbusSlave, default_bit, default_register

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
    assert lines[0] == "14 items, 2 requests per cycle (slave 2 on rtu-over-tcp://127.0.0.1:1502)"
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
        base = ["--host", "127.0.0.1", "--port", str(slave.port), "--slave", "2",
                "--rtu-over-tcp"]
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
                  "--rtu-over-tcp", "--timeout", "200", "hr:1")
    assert out.returncode == 1  # a runtime failure: the device never answered
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


# -- read/write: the type follows the address; messages name the options -------------------
def test_bit_addresses_default_to_boolean() -> None:
    """coil:N, di:N and hr:N.b need no --type (docs/command-line.md's `write ... coil:5 true`)."""
    with PymodbusSlave("rtu-over-tcp", units=(3,)) as slave:
        base = ["--host", "127.0.0.1", "--port", str(slave.port), "--slave", "3",
                "--transport", "rtu-over-tcp"]
        slave.set_bits(3, "co", 5, [False])
        out = cli("write", *base, "coil:5", "true")
        assert (out.returncode, out.stdout.strip()) == (0, "ok"), out.stderr
        assert slave.bits(3, "co", 5, 1) == [True]
        out = cli("read", *base, "coil:5")
        assert (out.returncode, out.stdout.strip()) == (0, "True"), out.stderr
        for offset in (6, 7):  # one of each value (the discrete input pattern has period 4)
            out = cli("read", *base, f"di:{offset}")
            assert out.returncode == 0, out.stderr
            assert out.stdout.strip() == str(default_bit(3, "di", offset))
        slave.set_registers(3, "hr", 7, [0b1000])
        for bit, expected in ((3, "True"), (2, "False")):
            out = cli("read", *base, f"hr:7.{bit}")
            assert (out.returncode, out.stdout.strip()) == (0, expected), out.stderr
        out = cli("read", *base, "hr:7")  # a whole register is still UInt16
        assert (out.returncode, out.stdout.strip()) == (0, "8"), out.stderr


def test_option_errors_name_the_option() -> None:
    """A bad option value is reported as the option and the value typed, one line."""
    cases = [
        (["--type", "Float", "coil:5"], "--type Float: a coil holds one bit: use Boolean"),
        (["--type", "Int32", "hr:7.3"], "--type Int32: a bit address (.N) reads one bit"),
        (["--type", "Foo", "hr:1"], "--type Foo: unknown data type 'Foo'"),
        (["--format", "XYZ", "hr:1"], "--format XYZ: unknown data format 'XYZ'"),
        (["--slave", "300", "hr:1"], "--slave 300: must be 0..255"),
        (["--timeout", "0", "hr:1"], "--timeout 0: must be 1..86400000"),
        (["--quantity", "3", "--type", "Timestamp", "hr:1"],
         "--quantity 3: Timestamp allows quantity 2 or 4"),
        (["hr:99999"], "hr:99999: offset 99999 out of range 0..65535"),
    ]
    for args, message in cases:
        out = cli("read", "--host", "127.0.0.1", *args)
        assert out.returncode == 2, (args, out.stderr)
        assert len(out.stderr.splitlines()) == 1, out.stderr
        assert out.stderr.startswith(f"edgemodbus read: {message}"), (args, out.stderr)
        assert "addressList" not in out.stderr and "communication." not in out.stderr
    serial = ["--serial", "/dev/null-edgemodbus-test"]
    for args, message in [
        (["--parity", "X"], "--parity X: use None|Odd|Even"),
        (["--baud", "300"], "--baud 300: must be 1200..921600"),
        (["--data-bits", "9"], "--data-bits 9: must be 5..8"),
        (["--transport", "tcp"], "--transport tcp: applies to --host"),
    ]:
        out = cli("read", *serial, *args, "hr:1")
        assert out.returncode == 2, (args, out.stderr)
        assert len(out.stderr.splitlines()) == 1, out.stderr
        assert out.stderr.startswith(f"edgemodbus read: {message}"), (args, out.stderr)


# -- values print exactly ------------------------------------------------------------------
def _f32_registers(value: float, fmt: str = "ABCD") -> list[int]:
    hi, lo = struct.unpack(">HH", struct.pack(">f", value))
    return [lo, hi] if fmt == "CDAB" else [hi, lo]


def _f32(value: float) -> float:
    """The float32 nearest ``value``, as the Python float a Float item holds."""
    result: float = struct.unpack(">f", struct.pack(">f", value))[0]
    return result


def _same(a: float | None, b: float) -> bool:
    return a is not None and (a == b or (math.isnan(a) and math.isnan(b)))


def test_floats_print_so_that_they_read_back_exactly(tmp_path: Path) -> None:
    """`read` and `run --json` used to round to 6 decimals: 2.89e-37 and 1.5e-7 read 0.0;
    then they wrote the widened double (69.74495697021484): a Float is now the shortest
    decimal that reads back to the same float32 (69.74496), NaN and infinities in JSON
    the strings "NaN", "Infinity", "-Infinity"."""
    values = {100: 2.89e-37, 102: 1.5e-7, 104: -3.4028234663852886e38, 106: 1e-45,
              108: 123.456, 110: math.inf, 112: math.nan, 114: 69.74495697021484,
              116: -math.inf}
    initial = {2: {"hr": {a + i: r for a, v in values.items()
                          for i, r in enumerate(_f32_registers(v, "CDAB"))}}}
    with PymodbusSlave("rtu-over-tcp", units=(2,), initial=initial) as slave:
        base = ["--host", "127.0.0.1", "--port", str(slave.port), "--slave", "2",
                "--rtu-over-tcp", "--type", "Float", "--format", "CDAB",
                "--timeout", "5000"]  # a loaded CI
        for address, value in values.items():
            out = cli("read", *base, f"hr:{address}")
            assert out.returncode == 0, out.stderr
            assert _same(_f32(float(out.stdout)), _f32(value)), (value, out.stdout)
            assert out.stdout.strip() == float32_text(value), (value, out.stdout)
        out = cli("read", *base, "hr:110")
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == "inf"
        device = tmp_path / "floats.json"
        device.write_text(json.dumps({
            "organization": {"deviceCode": "F"},
            "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": slave.port, "slaveId": 2, "readCycle": 200,
                              "dataFormat": "CDAB"},
            "addressList": [{"name": f"f{a}", "address": f"hr:{a}", "deviceDataType": "Float"}
                            for a in values],
        }))
        out = cli("run", "--json", "--seconds", "1.5", str(device))
    assert out.returncode == 0, out.stderr
    got = {}
    for line in out.stdout.splitlines():
        record = json.loads(line, parse_constant=lambda c: pytest.fail(f"not JSON: {c}"))
        if "name" in record:
            assert record["status"] == "Ok", record
            got[record["name"]] = record["value"]
    assert got["f114"] == 69.74496 and got["f108"] == 123.456
    for address, value in values.items():
        expected = _f32(value)
        if math.isfinite(expected):
            assert got[f"f{address}"] == float32_short(expected), (value, got)
        else:  # strict JSON has no NaN or infinity: their names, not null ("no value")
            assert got[f"f{address}"] == {math.inf: "Infinity", -math.inf: "-Infinity"}.get(
                expected, "NaN"), (value, got)


@settings(max_examples=3000, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 2**64 - 1))
def test_float_formatting_round_trips(bits32: int, bits64: int) -> None:
    """Every float32 and float64 bit pattern: text reads back to the same float (the
    same float32 too), JSON to the same number or the name of NaN or the infinity; a
    Float item's value (Float32) reads back to the same float32, as its shortest text."""
    for value in (struct.unpack(">f", bits32.to_bytes(4, "big"))[0],
                  struct.unpack(">d", bits64.to_bytes(8, "big"))[0]):
        text = value_text(value)
        assert _same(float(text), value), (value, text)
        assert text == text.strip() and " " not in text
        decoded = json.loads(json_line({"value": value}), parse_constant=lambda c: "invalid")
        if math.isfinite(value):
            assert decoded["value"] == value and type(decoded["value"]) is float
        else:
            assert decoded["value"] in ("NaN", "Infinity", "-Infinity")
    f32 = struct.unpack(">f", bits32.to_bytes(4, "big"))[0]
    if math.isfinite(f32):
        assert struct.pack(">f", float(value_text(f32))) == bits32.to_bytes(4, "big")
        text = value_text(Float32(f32))
        assert text == float32_text(f32)
        assert struct.pack(">f", float(text)) == bits32.to_bytes(4, "big")
        line = json.loads(json_line({"value": Float32(f32)}), parse_constant=lambda c: "bad")
        assert struct.pack(">f", line["value"]) == bits32.to_bytes(4, "big")


def test_run_json_writes_only_json_lines(tmp_path: Path) -> None:
    """stdout of `run --json` is JSON lines only: the per-device summary is a JSON object
    line too (it was a plain-text line)."""
    with PymodbusSlave("rtu-over-tcp", units=(1, 2)) as slave:
        files = []
        for unit in (1, 2):
            files.append(tmp_path / f"d{unit}.json")
            files[-1].write_text(json.dumps({
                "organization": {"deviceCode": f"D{unit}"},
                "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                                  "tcpPort": slave.port, "slaveId": unit, "readCycle": 100},
                "addressList": [{"name": f"r{a}", "address": f"hr:{a}",
                                 "deviceDataType": "UInt16", "unit": "m"} for a in range(5)],
            }))
        out = cli("run", "--json", "--seconds", "1", *map(str, files))
    assert out.returncode == 0, out.stderr
    records = [json.loads(line, parse_constant=lambda c: pytest.fail(f"not JSON: {c}"))
               for line in out.stdout.splitlines()]
    assert all(isinstance(r, dict) for r in records)
    items = [r for r in records if "summary" not in r]
    summaries = [r for r in records if "summary" in r]
    assert records[-2:] == summaries  # after every update
    assert [s["device"] for s in summaries] == ["D1", "D2"]
    assert all(s["summary"]["cycles"] > 0 and s["summary"]["timeouts"] == 0 for s in summaries)
    assert {(r["device"], r["name"], r["value"]) for r in items} == {
        (f"D{u}", f"r{a}", default_register(u, "hr", a)) for u in (1, 2) for a in range(5)}


# -- one line per problem on stderr ----------------------------------------------------------
def test_one_line_per_problem(tmp_path: Path) -> None:
    """No log line beside the error that says the same; every problem on a line of its own
    naming where it is; argparse's errors without the usage dump."""
    from tests.peers import free_port

    port = free_port()
    out = cli("read", "--host", "127.0.0.1", "--port", str(port), "hr:1")
    assert out.returncode == 1  # a runtime failure, one line, no framing hint (no link)
    assert out.stderr.splitlines() == [
        f"edgemodbus read: hr:1: link down: tcp://127.0.0.1:{port}: "
        "connect failed: Connection refused"]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"communication": {"baudRate": 300, "parity": "X"},
                               "addressList": []}))
    out = cli("run", str(bad))
    assert out.returncode == 2
    assert out.stderr.splitlines() == [
        f"edgemodbus run: {bad}: communication.baudRate 300: must be 1200..921600",
        f"edgemodbus run: {bad}: communication.parity 'X': use None|Odd|Even, 0|1|2 or N|O|E",
    ]
    out = cli("run", str(tmp_path / "missing.json"))
    assert out.stderr.splitlines() == [
        f"edgemodbus run: {tmp_path / 'missing.json'}: No such file or directory"]
    out = cli("run", "--seconds", "x", str(bad))
    assert out.returncode == 2
    assert out.stderr.splitlines() == [
        "edgemodbus run: argument --seconds: invalid float value: 'x' (see edgemodbus run -h)"]
    out = cli("demo", "--slaves", "1,x")
    assert out.returncode == 2 and len(out.stderr.splitlines()) == 1
    assert out.stderr.startswith("edgemodbus demo: argument --slaves: '1,x': 'x' is not a "
                                 "number or range (allowed: ids 1..247")


def test_device_file_warning_names_the_file(tmp_path: Path) -> None:
    """A warning while a device file loads (an unknown key) is one line naming the file."""
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        device = tmp_path / "odd.json"
        device.write_text(json.dumps({
            "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": slave.port, "colour": "red"},
            "addressList": [{"name": "r", "address": "hr:1", "deviceDataType": "UInt16"}],
        }))
        out = cli("run", "--seconds", "1.5", str(device))  # it must answer (else exit 1)
    assert out.returncode == 0, out.stderr
    assert out.stderr.splitlines() == [
        f"edgemodbus run: warning: {device}: communication: unknown key 'colour' ignored"]


def test_a_device_that_cannot_start_is_named_by_its_file(tmp_path: Path,
                                                          pty_pair: PtyPair) -> None:
    """Two device files that open one serial port with different settings: one line naming
    the second file and both settings."""
    files = []
    for baud in (9600, 19200):
        files.append(tmp_path / f"at{baud}.json")
        files[-1].write_text(json.dumps({
            "communication": {"transport": "rtu", "comPort": pty_pair.a, "baudRate": baud},
            "addressList": [{"name": "r", "address": "hr:1", "deviceDataType": "UInt16"}],
        }))
    out = cli("run", "--seconds", "0.5", *map(str, files))
    assert out.returncode == 2
    lines = out.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"edgemodbus run: {files[1]}: line "), lines
    assert "9600" in lines[0] and "19200" in lines[0]


def test_plan_shows_the_rate_of_blocks_that_have_their_own(tmp_path: Path) -> None:
    device = tmp_path / "rated.json"
    device.write_text(json.dumps({
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": 5020, "slaveId": 3, "readCycle": 1000},
        "addressList": [
            {"name": "fast", "address": "hr:0", "deviceDataType": "UInt16", "readCycle": 100},
            {"name": "slow", "address": "hr:1", "deviceDataType": "UInt16"},
        ],
    }))
    out = cli("plan", str(device))
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        "2 items, 2 requests per cycle (slave 3 on rtu-over-tcp://127.0.0.1:5020)",
        "  FC03 hr:0-0 (1) every 100 ms: fast",
        "  FC03 hr:1-1 (1): slow",
    ]
