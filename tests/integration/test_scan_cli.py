"""``edgemodbus scan`` as a user runs it: a subprocess against pymodbus and the simulator
over TCP; the JSON document, the tables, Ctrl-C, bad options, the progress bar on a
terminal."""

from __future__ import annotations

import json
import os
import pty
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from edgemodbus.sim import Simulator
from tests.peers import ExceptionRange, PymodbusSlave

BASE = [sys.executable, "-m", "edgemodbus.cli", "scan"]


def cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*BASE, *args], capture_output=True, text=True, timeout=timeout,
                          check=False)


@pytest.fixture
def sim() -> Iterator[Simulator]:
    s = Simulator(slaves=[1, 5])
    yield s
    s.stop()


SETTING_KEYS = {"setting": str, "transport": str, "baudrate": (int, type(None)),
                "parity": (str, type(None)), "dataBits": (int, type(None)),
                "stopBits": (int, type(None))}
ANSWER_RESULTS = {"ok", "exception", "timeout", "garbage", "closed"}


def check_schema(doc: dict[str, Any]) -> None:
    """The document of --json (cli/scan.py JSON_HELP, docs/command-line.md), key by key."""
    assert set(doc) == {"line", "complete", "interrupted", "error", "slaveIds", "settings",
                        "found"}
    assert isinstance(doc["line"], str) and isinstance(doc["slaveIds"], int)
    assert isinstance(doc["complete"], bool) and isinstance(doc["interrupted"], bool)
    assert doc["error"] is None or isinstance(doc["error"], str)
    counts = {"probes", "replies", "garbage", "timeouts", "closed", "idsProbed"}
    for s in doc["settings"]:
        assert set(s) == set(SETTING_KEYS) | counts | {"stoppedEarly"}
        for key, kind in SETTING_KEYS.items():
            assert isinstance(s[key], kind), (key, s[key])
        assert all(isinstance(s[k], int) and s[k] >= 0 for k in counts)
        assert s["stoppedEarly"] is None or isinstance(s["stoppedEarly"], str)
    for f in doc["found"]:
        assert set(f) == set(SETTING_KEYS) | {"slaveId", "answers"}
        assert isinstance(f["slaveId"], int) and f["answers"]
        for a in f["answers"]:
            assert a["result"] in ANSWER_RESULTS and a["function"] in (1, 2, 3, 4)
            if a["result"] == "exception":
                assert set(a) == {"function", "result", "exceptionCode", "exception"}
                assert isinstance(a["exceptionCode"], int) and isinstance(a["exception"], str)
            else:
                assert set(a) <= {"function", "result", "detail"}


def test_json_document_pymodbus_tcp(slave_factory: Callable[..., PymodbusSlave]) -> None:
    slave = slave_factory("tcp", units=(2, 7),
                          exception_ranges=[ExceptionRange(0, 1, code=2, area="hr", unit=7)])
    r = cli("--host", "127.0.0.1", "--port", str(slave.port), "--transport", "tcp",
            "--ids", "1-3,7", "--timeout", "300", "--json")
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""  # no progress bar: stderr is not a terminal
    doc = json.loads(r.stdout)
    check_schema(doc)
    assert doc["complete"] is True and doc["slaveIds"] == 4
    assert [(s["setting"], s["idsProbed"], s["replies"]) for s in doc["settings"]] == [
        ("tcp", 4, 3)]
    assert [(f["slaveId"], f["answers"]) for f in doc["found"]] == [
        (2, [{"function": 3, "result": "ok"}]),
        (7, [{"function": 3, "result": "exception", "exceptionCode": 2,
              "exception": "illegal data address"},
             {"function": 4, "result": "ok"}]),
    ]


def test_tables_simulator_rtu_over_tcp(sim: Simulator) -> None:
    sim.slave(5).faults.refused_functions = frozenset({3})
    port = sim.serve_tcp("127.0.0.1", 0)
    r = cli("--host", "127.0.0.1", "--port", str(port), "--rtu-over-tcp", "--slaves", "1-6",
            "--timeout", "200")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0] == f"scan of 127.0.0.1:{port}: 6 slave id(s) per setting"
    assert lines[2:5] == [
        "setting       slave  answered",
        "rtu-over-tcp      1  FC03 ok",
        "rtu-over-tcp      5  FC03 exception 01 (illegal function), FC04 ok",
    ]
    assert lines[6:] == [
        "setting       ids  probes  replies  garbage  timeouts  note",
        "rtu-over-tcp    6       7        3        0         4",
    ]


@pytest.mark.parametrize("mode", ["text", "json"])
def test_ctrl_c_prints_what_was_found_and_exits_130(sim: Simulator, mode: str) -> None:
    port = sim.serve_tcp("127.0.0.1", 0)
    extra = ["--json"] if mode == "json" else []
    proc = subprocess.Popen([*BASE, "--host", "127.0.0.1", "--port", str(port), "--ids",
                             "1-247", "--transport", "rtu-over-tcp", "--timeout", "200",
                             *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        # slave 1 answered and the probe of id 3 went out: id 1 is in the report
        while sim.stats()["line"]["unknown_slave"] < 2:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the scan did not get to id 3"
            time.sleep(0.02)  # poll: until id 3 (deadline above)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)  # quick: the line closes at once
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    if mode == "json":
        doc = json.loads(out)
        check_schema(doc)
        assert (doc["complete"], doc["interrupted"]) == (False, True)
        assert [f["slaveId"] for f in doc["found"]] == [1]
        assert doc["settings"] == []  # the setting did not end
    else:
        assert out.splitlines()[0].endswith("(interrupted)")
        assert "rtu-over-tcp      1  FC03 ok" in out
    # the link was closed: the simulator sees no connection left
    deadline = time.monotonic() + 5
    while sim.clients():
        assert time.monotonic() < deadline, "the scan left its connection open"
        time.sleep(0.02)  # poll: until closed (deadline above)


@pytest.mark.parametrize(("args", "message"), [
    (["--serial", "/dev/null", "--baud", "9600,fast"],
     "--baud '9600,fast': not a comma-separated list of numbers (allowed: e.g. 9600,19200)"),
    (["--serial", "/dev/null", "--baud", "10"], "--baud '10': 10 is not a baud rate"),
    (["--serial", "/dev/null", "--parity", "N,X"], "--parity 'N,X': 'X' is not N, E or O"),
    (["--serial", "/dev/null", "--stop-bits", "3"], "--stop-bits '3': must be 1, 2 or 1,2"),
    (["--serial", "/dev/null", "--ids", "1-300"],
     "--ids '1-300' is outside 1..247 or reversed"),
    (["--serial", "/dev/null", "--ids", "a"], "--ids 'a' is not a number or range"),
    (["--serial", "/dev/null", "--slaves", "1,a"], "--slaves '1,a': 'a' is not a number"),
    (["--serial", "/dev/null", "--slaves", "1", "--ids", "2"],
     "--slaves '1' and --ids '2': give one"),
    (["--serial", "/dev/null", "--timeout", "0"], "--timeout '0': must be 1..60000 ms"),
    (["--serial", "/dev/null", "--functions", "3,6"],
     "--functions '3,6': a probe reads with 1, 2, 3 or 4"),
    (["--serial", "/dev/null", "--garbage-limit", "-1"],
     "--garbage-limit '-1': one number, 0 or more"),
    (["--serial", "/dev/null", "--rs485", "auto"], "--rs485 'auto': must be one of none"),
    (["--host", "127.0.0.1", "--transport", "udp"], "--transport 'udp': 'udp' is not one of"),
    (["--host", "127.0.0.1", "--ids", "256"], "--ids '256' is outside 0..255"),
    (["--host", "127.0.0.1", "--rtu-over-tcp", "--slaves", "0"],
     "--slaves '0' is outside 1..247"),
])
def test_bad_options_named(args: list[str], message: str) -> None:
    r = cli(*args)
    assert r.returncode == 2
    assert r.stdout == ""
    assert r.stderr.startswith(f"edgemodbus scan: {message}"), r.stderr


def test_missing_serial_port_is_an_error_with_the_report() -> None:
    r = cli("--serial", "/dev/edgemodbus-no-such-port", "--baud", "9600", "--parity", "N",
            "--ids", "1-2")
    assert r.returncode == 1
    assert "(failed)" in r.stdout.splitlines()[0]
    assert "serial port /dev/edgemodbus-no-such-port: does not exist" in r.stderr


def test_progress_bar_on_a_terminal(sim: Simulator) -> None:
    port = sim.serve_tcp("127.0.0.1", 0)
    master, slave = pty.openpty()
    try:
        proc = subprocess.Popen([*BASE, "--host", "127.0.0.1", "--port", str(port),
                                 "--rtu-over-tcp", "--slaves", "1-3", "--timeout", "200"],
                                stdout=subprocess.PIPE, stderr=slave, text=True,
                                env={**os.environ, "COLUMNS": "100", "TERM": "xterm"})
        os.close(slave)
        slave = -1
        seen = b""
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 0.2)
            if ready:
                try:
                    chunk = os.read(master, 4096)
                except OSError:  # EIO: the process closed the terminal
                    break
                if not chunk:
                    break
                seen += chunk
            elif proc.poll() is not None:
                break
        out, _ = proc.communicate(timeout=10)
    finally:
        os.close(master)
        if slave != -1:
            os.close(slave)
    assert proc.returncode == 0
    text = seen.decode(errors="replace")
    assert "rtu-over-tcp (1/1)" in text  # the bar's description
    assert "slave 1: FC03 ok" in text  # found devices are shown as they come
    assert "rtu-over-tcp      1  FC03 ok" in out  # the table still goes to stdout


def test_a_scan_in_the_wrong_framing_names_the_flag() -> None:
    """``scan --host`` speaks Modbus TCP (as read does); against a slave that answers raw
    RTU frames (pymodbus's RTU framer over TCP) nothing answers, and stderr says which
    flag scans the other framing; with both framings the slave is found, no hint."""
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        where = ["--host", "127.0.0.1", "--port", str(slave.port), "--slaves", "1",
                 "--timeout", "300"]
        out = cli(*where)
        assert out.returncode == 0, out.stderr
        assert "nothing answered" in out.stdout
        assert out.stderr.splitlines() == [
            "edgemodbus scan: nothing answered Modbus TCP; a serial server or a DTU speaks "
            "raw RTU frames: scan with --transport tcp,rtu-over-tcp"]
        out = cli(*where, "--transport", "tcp,rtu-over-tcp", "--json")
        assert out.returncode == 0 and out.stderr == "", out.stderr
        found = json.loads(out.stdout)["found"]
        assert [(f["transport"], f["slaveId"]) for f in found] == [("rtu-over-tcp", 1)]
