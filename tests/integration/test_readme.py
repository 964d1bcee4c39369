"""Every command shown in README.md and in docs/**/*.md runs as written, against peers
this test starts; so does the README's library quick start (its Python block).

The commands are the lines of the pages' fenced ``sh`` blocks (every line) and of the
README's unlabelled fenced blocks (lines that start with a command word such as
``edgemodbus``; in docs/ an unlabelled block is a diagram or output, never run);
a trailing ``\\`` continues a line and ``#`` starts a comment.  Each command is either run,
or on the small SKIP list with a reason; a command that is neither fails
``test_readme_command``, so a new command on any page fails until it is covered.

A command is rewritten only where it names the outside world: ``--host``/``--port``,
``--serial``, ``--dial``, ``--config-dir``, device file paths (``*.json``) point at a
simulator (or a listening driver) on 127.0.0.1 with an ephemeral port or at a pty, and
``--seconds`` is short; ``--config-dir`` of one of the example folders is a copy of it
with the broker and the slave started here.  Every other word runs as the page shows it.
"""

from __future__ import annotations

import json
import re
import select
import shlex
import shutil
import signal
import struct
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import Area
from edgemodbus.sim import Simulator, default_register
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave, free_port
from tests.uart_line import UartLine, UartSettings
from tests.waiting import wait_for

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
#: The pages whose commands are run: the README, then every page under docs/.
PAGES = (README, *sorted((ROOT / "docs").rglob("*.md")))
SHELL_BLOCKS = frozenset({"sh", "shell", "bash", "console"})
#: In an unlabelled block, a line starting with one of these is a command, not output.
COMMAND_WORDS = frozenset({"edgemodbus", "make", "python", "python3", "pip", "pip3"})

#: Commands not run here (exact words), with the reason.
SKIP: dict[tuple[str, ...], str] = {
    ("make", "demo"): "sets the machine up (apt-get, pip) and then runs `edgemodbus demo`, "
                      "whose README line is run here",
    ("make", "test"): "runs the whole test suite, this test included",
    ("make", "build"): "sets the machine up (apt-get, pip): the environment this test runs in",
    ("make", "bench"): "runs every benchmark (minutes; `make bench-quick` is CI's)",
    ("make", "bench-quick"): "runs every benchmark (CI runs it apart from the tests)",
    (".venv/bin/python", "-m", "pytest", "bench/test_bench_codec.py", "--benchmark-only"):
        "a benchmark: run by `make bench`",
    ("sudo", "apt-get", "install", "libmodbus-dev", "pkg-config", "python3-venv", "python3-dev",
     "gcc"): "installs Debian packages (as `make build` does)",
    ("python3", "-m", "venv", "/opt/edgemodbus/venv"): "makes a venv in /opt: the install of a "
                                                      "machine, not of a test",
    ("/opt/edgemodbus/venv/bin/pip", "install", ".[mqtt,metrics]"): "installs the package into "
        "that venv; the test environment has the package and its extras",
    ("pip", "install", ".[mqtt,metrics]"): "installs the package; the test environment has the "
                                           "package and its extras",
    # docs/links.md's TLS broker for an MQTT DTU: tests/integration/test_mqtt_dtu_tls.py
    # makes the same certificate and broker (and polls through it)
    ("openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
     "-nodes", "-keyout", "key.pem", "-out", "cert.pem", "-days", "365", "-subj",
     "/CN=localhost", "-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost"):
        "writes a key and certificate into the current folder; test_mqtt_dtu_tls.py does it",
    ("printf", "listener 8883 127.0.0.1\\ncertfile cert.pem\\nkeyfile key.pem\\n"
     "allow_anonymous true\\n", ">", "tls.conf"):
        "writes a broker config into the current folder; test_mqtt_dtu_tls.py does it",
    ("mosquitto", "-c", "tls.conf"): "a TLS broker that runs until stopped, on a fixed port; "
                                     "test_mqtt_dtu_tls.py runs one on an ephemeral port",
    ("mosquitto_sub", "-h", "127.0.0.1", "-t", "plant1/#", "-v"): "a subscriber that runs "
        "until Ctrl-C; what it shows is checked by the runner of `run --config-dir examples/...`",
}

SHORT_SECONDS = "1.5"
SLAVE_READY = 15.0  # s for a started process to poll, dial or listen


@dataclass(frozen=True)
class Command:
    """One command of a page: where it is, its text and its words (comment removed)."""

    line: int
    text: str
    argv: tuple[str, ...]
    page: str = "README.md"

    def __str__(self) -> str:
        return f"{self.page}:{self.line}: {self.text}"


def readme_commands(text: str, page: str = "README.md") -> list[Command]:
    """The commands of the fenced blocks of a page's text (see the module doc)."""
    commands: list[Command] = []
    fence: str | None = None
    pending: tuple[int, str] | None = None  # a line continued with a backslash
    for number, raw in enumerate(text.splitlines(), start=1):
        stripped = raw.strip()
        if stripped.startswith("```"):
            fence = None if fence is not None else stripped[3:].strip().lower()
            pending = None
            continue
        if fence is None or (fence and fence not in SHELL_BLOCKS):
            continue
        start, line = (pending[0], f"{pending[1]} {stripped}") if pending else (number, stripped)
        if line.endswith("\\"):
            pending = (start, line[:-1].rstrip())
            continue
        pending = None
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        if not fence and (page != "README.md" or words[0] not in COMMAND_WORDS):
            continue  # output or a diagram in an unlabelled block
        argv = tuple(shlex.split(line, comments=True))
        commands.append(Command(start, " ".join(shlex.quote(w) for w in argv), argv, page))
    return commands


COMMANDS = [command for page in PAGES
            for command in readme_commands(page.read_text(encoding="utf-8"),
                                           str(page.relative_to(ROOT)))]


# -- running processes ---------------------------------------------------------------------
def executable(argv: tuple[str, ...]) -> list[str]:
    """The installed ``edgemodbus`` script, or this interpreter for ``python``."""
    if argv[0] == "edgemodbus":
        script = Path(sys.executable).with_name("edgemodbus")
        assert script.exists(), f"{script}: the package's console script is not installed"
        return [str(script), *argv[1:]]
    if argv[0] in ("python", "python3"):
        return [sys.executable, *argv[1:]]
    raise AssertionError(f"no executable for {argv[0]!r}")


def run(argv: list[str], timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(executable(tuple(argv)), capture_output=True, text=True,
                          timeout=timeout, check=False, cwd=ROOT)


@contextmanager
def started(argv: list[str]) -> Iterator[subprocess.Popen[str]]:
    """A long-running command; on exit it gets SIGTERM and must have exited with 0."""
    proc = subprocess.Popen(executable(tuple(argv)), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT)
    failure: Exception | None = None
    try:
        yield proc
    except Exception as exc:  # reported below with the process' output
        failure = exc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            out, err = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
    detail = f"{shlex.join(argv)}: exit {proc.returncode}\nstdout:\n{out}\nstderr:\n{err}"
    if failure is not None:
        raise AssertionError(f"{failure}\n{detail}") from failure
    assert proc.returncode == 0, detail


def read_line(proc: subprocess.Popen[str], timeout: float = SLAVE_READY) -> str:
    """One line of the process' stdout, without blocking past ``timeout``."""
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    assert ready, f"no output in {timeout} s"
    return proc.stdout.readline()


# -- rewriting -----------------------------------------------------------------------------
def rewrite(argv: tuple[str, ...], **where: str) -> list[str]:
    """``argv`` with the values of the outside-world options replaced by ``where``
    (keys: host, port, serial, dial, config_dir, file, seconds); ``seconds`` is added
    when missing; every other word stays."""
    options = {"--host": "host", "--port": "port", "--serial": "serial", "--dial": "dial",
               "--config-dir": "config_dir", "--seconds": "seconds"}
    out: list[str] = []
    words = iter(argv)
    for word in words:
        out.append(word)
        if word in options:
            value = next(words)
            out.append(where.get(options[word], value))
        elif word.endswith(".json") and "file" in where:
            out[-1] = where["file"]
    if "seconds" in where and "--seconds" not in out:
        out += ["--seconds", where["seconds"]]
    for key in where:
        assert key in (*options.values(), "file"), key
    return out


def device_file(path: Path, port: int, slave: int, code: str, **comm: Any) -> Path:
    path.write_text(json.dumps({
        "organization": {"deviceCode": code},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": port, "slaveId": slave, "readCycle": 200, **comm},
        "addressList": [
            {"name": "Counter", "address": "hr:0", "deviceDataType": "UInt16"},
            {"name": "Level", "address": "hr:1", "deviceDataType": "UInt16", "unit": "cm"},
            {"name": "Running", "address": "hr:10.0", "deviceDataType": "Boolean"},
            {"name": "Pump", "address": "coil:3", "deviceDataType": "Boolean"},
        ],
    }))
    return path


# -- one runner per kind of command -------------------------------------------------------
def run_demo(argv: tuple[str, ...], tmp: Path) -> None:
    out = run(rewrite(argv, seconds="2"))
    assert out.returncode == 0, out.stderr
    slaves = argv[argv.index("--slaves") + 1].split(",") if "--slaves" in argv else ["1"]
    assert f"simulator: slaves {','.join(slaves)} on rtu-over-tcp://127.0.0.1:" in out.stdout
    summaries = [ln for ln in out.stdout.splitlines() if ln.startswith("Demo001-")]
    assert len(summaries) == len(slaves) and all("0 timeouts" in ln for ln in summaries)


def run_run(argv: tuple[str, ...], tmp: Path) -> None:
    if "--config-dir" in argv:
        run_service(argv, tmp)
        return
    with Simulator([4]) as sim:
        port = sim.serve_tcp("127.0.0.1", 0)
        sim.slave(4).set_registers(Area.HOLDING_REGISTER, 10, [1])
        path = device_file(tmp / "device.json", port, 4, "Pump4")
        out = run(rewrite(argv, file=str(path), seconds=SHORT_SECONDS))
    assert out.returncode == 0, out.stderr
    expected = {"Counter": default_register(4, 0), "Level": default_register(4, 1),
                "Running": True, "Pump": False}
    if "--json" in argv:
        records = [json.loads(ln, parse_constant=lambda c: pytest.fail(f"not JSON: {c}"))
                   for ln in out.stdout.splitlines()]
        assert records[-1]["device"] == "Pump4" and records[-1]["summary"]["cycles"] > 0
        assert {r["name"]: r["value"] for r in records[:-1]} == expected
    else:
        for name, value in expected.items():
            assert re.search(rf" Pump4 +{name} +{value}\b", out.stdout), (name, out.stdout)
        assert out.stdout.splitlines()[-1].startswith("Pump4: Stopped, ")


def run_read(argv: tuple[str, ...], tmp: Path) -> None:
    """``read --host``: a pymodbus Modbus TCP slave (what --host speaks), or with
    ``--rtu-over-tcp`` our simulator (raw RTU frames over TCP)."""
    assert "--host" in argv, "a README read that is not over TCP needs its own runner"
    slave = int(argv[argv.index("--slave") + 1]) if "--slave" in argv else 1
    if "--type" not in argv:  # one UInt16 register of the simulator (raw RTU over TCP)
        assert "--rtu-over-tcp" in argv and argv[-1].startswith("hr:"), \
            "a README read without --type of another kind needs its check here"
        with Simulator([slave]) as sim:
            port = sim.serve_tcp("127.0.0.1", 0)
            out = run(rewrite(argv, host="127.0.0.1", port=str(port)))
        expected = default_register(slave, int(argv[-1].partition(":")[2]))
        assert (out.returncode, out.stdout.strip()) == (0, str(expected)), out.stderr
        return
    fmt = argv[argv.index("--format") + 1] if "--format" in argv else "ABCD"
    assert "--type" in argv and argv[argv.index("--type") + 1] == "Float" \
        and argv[-1].startswith("hr:") and fmt in ("ABCD", "CDAB"), \
        "a README read of another type, area or format needs its check here"
    value = struct.unpack(">f", struct.pack(">f", -2.89e-37))[0]  # rounded, it was -0.0
    hi, lo = struct.unpack(">HH", struct.pack(">f", value))
    address = int(argv[-1].partition(":")[2])
    registers = [lo, hi] if fmt == "CDAB" else [hi, lo]
    rtu = "--rtu-over-tcp" in argv or ("--transport" in argv and
                                       argv[argv.index("--transport") + 1] == "rtu-over-tcp")
    if rtu:
        with Simulator([slave]) as sim:
            port = sim.serve_tcp("127.0.0.1", 0)
            sim.slave(slave).set_registers(Area.HOLDING_REGISTER, address, registers)
            out = run(rewrite(argv, host="127.0.0.1", port=str(port)))
    else:
        initial = {slave: {"hr": {address: registers[0], address + 1: registers[1]}}}
        with PymodbusSlave("tcp", units=(slave,), initial=initial) as peer:
            out = run(rewrite(argv, host="127.0.0.1", port=str(peer.port)))
    assert out.returncode == 0, out.stderr
    # the shortest text that reads back to the same float32 (README "Values as text and
    # JSON"): -2.89e-37, not the widened -2.8900000617130274e-37
    assert out.stdout.strip() == "-2.89e-37", out.stdout
    assert struct.pack(">f", float(out.stdout)) == struct.pack(">f", value), out.stdout


def run_write(argv: tuple[str, ...], tmp: Path) -> None:
    slave = int(argv[argv.index("--slave") + 1]) if "--slave" in argv else 1
    baud = int(argv[argv.index("--baud") + 1]) if "--baud" in argv else 9600
    target = argv[-2]
    assert target.startswith("coil:") and argv[-1] in ("true", "false"), \
        "a README write of something other than a coil needs its check here"
    coil = int(target.partition(":")[2])
    with Simulator([slave]) as sim:
        sim.slave(slave).set_bits(Area.COIL, coil, [argv[-1] != "true"])
        if "--serial" in argv:
            where = {"serial": sim.serve_pty(baudrate=baud)}
        else:
            where = {"host": "127.0.0.1", "port": str(sim.serve_tcp("127.0.0.1", 0))}
        out = run(rewrite(argv, **where))
        assert (out.returncode, out.stdout.strip()) == (0, "ok"), out.stderr
        assert sim.slave(slave).get_bits(Area.COIL, coil) == [argv[-1] == "true"]


def run_plan(argv: tuple[str, ...], tmp: Path) -> None:
    path = device_file(tmp / "device.json", 5020, 7, "Planned")
    out = run(rewrite(argv, file=str(path)))
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        "4 items, 2 requests per cycle (slave 7 on rtu-over-tcp://127.0.0.1:5020)",
        "  FC01 coil:3-3 (1): Pump",
        "  FC03 hr:0-10 (11): Counter, Level, Running",
    ]


def run_action(argv: tuple[str, ...], tmp: Path) -> None:
    """The README's action example: a pump whose action ``start`` sets a Float speed and
    a UInt16 mode (default 1) in one FC16 request."""
    assert argv[3:] == ("start", "speed=42.5"), "adapt this runner to the README's action"
    with Simulator([1]) as sim:
        port = sim.serve_tcp("127.0.0.1", 0)
        path = tmp / "pump.json"
        path.write_text(json.dumps({
            "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": port, "readTimeout": 500},
            "addressList": [
                {"name": "PumpSpeed", "address": "hr:100", "deviceDataType": "Float"},
                {"name": "Mode", "address": "hr:102", "deviceDataType": "UInt16"}],
            "actions": [{"name": "start", "functionCode": 16, "parameters": [
                {"name": "speed", "item": "PumpSpeed", "type": "Float32", "minValue": 0,
                 "maxValue": 100},
                {"name": "mode", "item": "Mode", "type": "UInt16", "default": 1}]}],
        }))
        out = run(rewrite(argv, file=str(path)))
        assert (out.returncode, out.stdout.strip()) == (0, "ok"), out.stderr
        assert sim.slave(1).get_registers(Area.HOLDING_REGISTER, 100, 3) == [
            *struct.unpack(">2H", struct.pack(">f", 42.5)), 1]


def run_simulate(argv: tuple[str, ...], tmp: Path) -> None:
    if "--dial" in argv:
        run_simulate_dial(argv)
        return
    slaves = argv[argv.index("--slaves") + 1] if "--slaves" in argv else "1"
    last = int(slaves.split(",")[-1].split("-")[-1])
    with started(rewrite(argv, port="0")) as proc:
        endpoint = read_line(proc).split()
        assert endpoint[0] == "tcp", endpoint
        port = endpoint[1].rpartition(":")[2]
        out = run(["edgemodbus", "read", "--host", "127.0.0.1", "--port", port,
                   "--rtu-over-tcp", "--slave", str(last), "hr:7"])
        assert (out.returncode, out.stdout.strip()) == (0, str(default_register(last, 7))), \
            out.stderr


def run_simulate_dial(argv: tuple[str, ...]) -> None:
    if "--dtus" in argv:
        run_simulate_fleet(argv)
        return
    registration = argv[argv.index("--registration") + 1] if "--registration" in argv else ""
    match = re.fullmatch(r"IMEI:(\d{15})", registration)
    assert match, "the README's DTU registers with IMEI:<15 digits>; adapt this runner"
    heartbeat = argv[argv.index("--heartbeat") + 1] if "--heartbeat" in argv else ""
    slave = int(argv[argv.index("--slaves") + 1]) if "--slaves" in argv else 1
    port = free_port()
    cfg = em.load_device_config({
        "communication": {"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "dtuId": match.group(1), "registration": "regex",
                          "registrationPattern": r"IMEI:(\d{15})", "heartbeat": heartbeat,
                          "slaveId": slave, "readCycle": 200, "readTimeout": 500},
        "addressList": [{"name": "r", "address": "hr:42", "deviceDataType": "UInt16"}],
    })
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        with started(rewrite(argv, dial=f"127.0.0.1:{port}")) as proc:
            assert read_line(proc).strip() == f"dialled 127.0.0.1:{port}"
            item = cfg.address_list[0]
            wait_for(lambda: item.status is em.ItemStatus.OK, timeout=SLAVE_READY,
                     what="a value through the dialled-in DTU")
            assert item.value == default_register(slave, 42)
    finally:
        drv.stop_device()


def item_ok(item: em.DeviceAddressItem) -> Callable[[], bool]:
    return lambda: item.status is em.ItemStatus.OK


def run_simulate_fleet(argv: tuple[str, ...]) -> None:
    """``simulate --dial ... --dtus N``: drivers listen for the first and the last DTU
    (the others register with ids nobody configured and are closed) and read a value
    through each."""
    def option(name: str, default: str) -> str:
        return argv[argv.index(name) + 1] if name in argv else default

    n, first = int(option("--dtus", "1")), int(option("--first-dtu", "0"))
    template, slave = option("--registration", "DTU{n:05d}"), int(option("--slaves", "1"))
    port = free_port()
    cfgs = [em.load_device_config({
        "communication": {"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "dtuId": template.format(n=k),
                          "registration": "text", "registrationTimeout": 1000,
                          "slaveId": slave, "readCycle": 200, "readTimeout": 500},
        "addressList": [{"name": "r", "address": "hr:42", "deviceDataType": "UInt16"}],
    }) for k in (first, first + n - 1)]
    drivers = [em.DriverModbusRtu() for _ in cfgs]
    try:
        for drv, cfg in zip(drivers, cfgs, strict=True):
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        with started(rewrite(argv, dial=f"127.0.0.1:{port}")) as proc:
            assert read_line(proc).startswith(f"dialling 127.0.0.1:{port} with {n} DTUs")
            for cfg in cfgs:
                wait_for(item_ok(cfg.address_list[0]), timeout=SLAVE_READY,
                         what=f"a value through DTU {cfg.communication.dtu_id}")
                assert cfg.address_list[0].value == default_register(slave, 42)
    finally:
        for drv in drivers:
            drv.stop_device()


def run_version(argv: tuple[str, ...], tmp: Path) -> None:
    out = run(list(argv))
    assert (out.returncode, out.stdout.strip()) == (0, f"edgemodbus {em.__version__}"), out


def run_descriptor(argv: tuple[str, ...], tmp: Path) -> None:
    out = run(list(argv))
    assert out.returncode == 0, out.stderr
    desc = json.loads(out.stdout)
    assert desc["driverType"] == "DriverModbusRtu"
    modicon = "--prefix" in argv and argv[argv.index("--prefix") + 1] == "modicon"
    assert ('"holdingRegister": "4:00001"' in out.stdout) is modicon


def run_service(argv: tuple[str, ...], tmp: Path) -> None:
    """``run --config-dir`` / ``python -m edgemodbus.gateway``: polls every device file
    of the folder until SIGTERM, then exits 0."""
    given = argv[argv.index("--config-dir") + 1]
    if (ROOT / given).is_dir():
        run_example_service(argv, ROOT / given, tmp)
        return
    config_dir = tmp / "etc-edgemodbus"
    config_dir.mkdir()
    (config_dir / "gateway.json").write_text(json.dumps({"gatewayId": "readme"}))
    with Simulator([5, 6]) as sim:
        port = sim.serve_tcp("127.0.0.1", 0)
        for slave in (5, 6):
            device_file(config_dir / f"pump{slave}.json", port, slave, f"Pump{slave}")
        with started(rewrite(argv, config_dir=str(config_dir))):
            wait_for(lambda: all(s["requests"] >= 3 for s in sim.stats()["slaves"].values()),
                     timeout=SLAVE_READY, what="the service polling both devices")


def run_example_service(argv: tuple[str, ...], folder: Path, tmp: Path) -> None:
    """``run --config-dir examples/gateway-mqtt-per-item``: a copy of the example folder
    whose device files point at a simulator and whose gateway file points at a mosquitto
    started here (ports changed, nothing else); the items and the device's status arrive
    on the topics the README names."""
    config_dir = tmp / folder.name
    shutil.copytree(folder, config_dir, symlinks=False)
    gateway = json.loads((config_dir / "gateway.json").read_text())
    devices = {path: json.loads(path.read_text()) for path in config_dir.glob("*.json")
               if path.name != "gateway.json"}
    slaves = sorted({d["communication"]["slaveId"] for d in devices.values()})
    with Simulator(slaves) as sim, Mosquitto(tmp / "broker") as broker:
        port = sim.serve_tcp("127.0.0.1", 0)
        for path, device in devices.items():
            device["communication"]["tcpPort"] = port
            path.write_text(json.dumps(device))
        gateway["mqtt"]["port"] = broker.port
        (config_dir / "gateway.json").write_text(json.dumps(gateway))
        prefix = gateway["mqtt"]["topicPrefix"]
        with MqttProbe(broker.port) as probe, \
                started(rewrite(argv, config_dir=str(config_dir))):
            for device in devices.values():
                code = device["organization"]["deviceCode"]
                probe.wait_for(f"{prefix}/{code}/$status", timeout=SLAVE_READY,
                               match=lambda m: m.json()["status"] == "Running")
                for item in device["addressList"]:
                    probe.wait_for(f"{prefix}/{code}/{item['name']}", timeout=SLAVE_READY)
            counter = probe.wait_for(f"{prefix}/Pump1/Counter", timeout=SLAVE_READY)
            assert counter.json()["value"] == default_register(1, 0)


def run_scan(argv: tuple[str, ...], tmp: Path) -> None:
    """``scan --serial``: our simulator (slaves 1 and 3) behind a UART model at 19200 8E1
    (tests/uart_line.py), found there only; ``scan --host``: a pymodbus Modbus TCP slave
    (unit 1), in the JSON document."""
    if "--serial" in argv:
        with Simulator([1, 3]) as sim:
            sim.slave(3).faults.exception_ranges = [(Area.HOLDING_REGISTER, 0, 1, 2)]
            with UartLine(sim.serve_pty(baudrate=19200), UartSettings(19200, "E")) as line:
                out = run(rewrite(argv, serial=line.path))
        assert out.returncode == 0, out.stderr
        assert "19200 8E1      1  FC03 ok" in out.stdout
        assert "19200 8E1      3  FC03 exception 02 (illegal data address), FC04 ok" in out.stdout
        return
    with PymodbusSlave("tcp", units=(1,)) as slave:
        out = run(rewrite(argv, host="127.0.0.1", port=str(slave.port)))
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert [(f["setting"], f["slaveId"]) for f in doc["found"]] == [("tcp", 1)]


def run_templates(argv: tuple[str, ...], tmp: Path) -> None:
    """``templates``: lists the shipped templates with their source documents."""
    out = run(list(argv))
    assert out.returncode == 0, out.stderr
    for name in ("eastron-sdm120", "eastron-sdm630", "xy-md02", "waveshare-relay-d-8ch"):
        assert f"\n{name}: " in f"\n{out.stdout}", (name, out.stdout)
    assert "  source: Eastron Electronic Co., Ltd., SDM120 Modbus protocol" in out.stdout


KEPWARE_CSV = (
    '"Tag Name","Address","Data Type","Respect Data Type","Client Access","Scan Rate",'
    '"Scaling","Raw Low","Raw High","Scaled Low","Scaled High","Scaled Data Type",'
    '"Clamp Low","Clamp High","Eng Units","Description"\n'
    '"Level","400001","Word",1,RO,1000,"Linear",0,1000,0,100,"Float",0,0,"%","Tank level"\n'
    '"Pump","000017","Boolean",1,R/W,250,"None",,,,,,0,0,,\n'
)


def run_import(argv: tuple[str, ...], tmp: Path) -> None:
    """``import tags.csv -o tank.json``: a Kepware export (written here) becomes a device
    file that loads back."""
    csv_file, out_file = tmp / "tags.csv", tmp / "tank.json"
    csv_file.write_text(KEPWARE_CSV, encoding="utf-8")
    words = [str(csv_file) if w.endswith(".csv") else str(out_file) if w.endswith(".json")
             else w for w in argv]
    out = run(words)
    assert out.returncode == 0, out.stderr
    assert "kepware form, 2 rows converted, 0 refused" in out.stderr
    cfg = em.load_device_config(out_file)
    assert [(i.name, i.address, i.data_multiplier, i.read_cycle) for i in cfg.address_list] \
        == [("Level", "hr:0", 0.1, 1000), ("Pump", "coil:16", 1.0, 250)]


Runner = Callable[[tuple[str, ...], Path], None]
RUNNERS: dict[tuple[str, ...], Runner] = {
    ("edgemodbus", "demo"): run_demo,
    ("edgemodbus", "run"): run_run,
    ("edgemodbus", "read"): run_read,
    ("edgemodbus", "write"): run_write,
    ("edgemodbus", "plan"): run_plan,
    ("edgemodbus", "simulate"): run_simulate,
    ("edgemodbus", "descriptor"): run_descriptor,
    ("edgemodbus", "action"): run_action,
    ("edgemodbus", "scan"): run_scan,
    ("edgemodbus", "templates"): run_templates,
    ("edgemodbus", "import"): run_import,
    ("edgemodbus", "--version"): run_version,
    ("python", "-m", "edgemodbus.gateway"): run_service,
}


def how_to_run(argv: tuple[str, ...]) -> Runner | str | None:
    """The runner of a command, its skip reason, or None: not covered."""
    if argv in SKIP:
        return SKIP[argv]
    for prefix, runner in RUNNERS.items():
        if argv[:len(prefix)] == prefix:
            return runner
    return None


# -- the tests -----------------------------------------------------------------------------
@pytest.mark.parametrize("command", COMMANDS,
                         ids=lambda c: f"{c.page}:L{c.line}:{' '.join(c.argv[:2])}")
def test_readme_command(command: Command, tmp_path: Path) -> None:
    how = how_to_run(command.argv)
    if how is None:
        pytest.fail(f"{command}: not run by this test and not on its SKIP list; add a runner "
                    "(or a skip with a reason) in tests/integration/test_readme.py")
    if isinstance(how, str):
        pytest.skip(f"{command.text}: {how}")
    how(command.argv, tmp_path)


def quick_start_code() -> str:
    """The Python block of the README's library quick start."""
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Library quick start"):]
    section = section[:section.index("\n## ", 1)]
    found = re.search(r"```python\n(.*?)```", section, re.S)
    assert found, "README: the library quick start has no Python block"
    return found.group(1)


def test_the_library_quick_start_runs(tmp_path: Path) -> None:
    """The quick start's code, as written, against the simulator the README starts
    (``simulate --port 5020 --slaves 1``; here on an ephemeral port: the device file is a
    copy of examples/rtu-over-tcp.json with its port changed): it prints the values and
    both writes reach the slave."""
    code = quick_start_code()
    example = "examples/rtu-over-tcp.json"
    assert f'load_device_config("{example}")' in code
    device = json.loads((ROOT / example).read_text())
    with Simulator([1]) as sim:
        device["communication"]["tcpPort"] = sim.serve_tcp("127.0.0.1", 0)
        copy = tmp_path / "rtu-over-tcp.json"
        copy.write_text(json.dumps(device))
        out = subprocess.run([sys.executable, "-c", code.replace(example, str(copy))],
                             capture_output=True, text=True, timeout=60, check=False, cwd=ROOT)
        assert out.returncode == 0, out.stderr
        assert sim.slave(1).get_registers(Area.HOLDING_REGISTER, 30, 1) == [42]
        assert sim.slave(1).get_bits(Area.COIL, 0, 1) == [True]
    lines = out.stdout.splitlines()
    assert f"Counter {default_register(1, 0)} Ok" in lines, out.stdout
    assert "write Setpoint: True None" in lines and "write PumpOn: True None" in lines, lines


def test_the_readme_commands_are_found() -> None:
    """The extraction sees the pages' command lines (joined continuation lines too)
    and every skip is still on a page."""
    argvs = [c.argv for c in COMMANDS]
    assert ("make", "demo") in argvs and ("make", "test") in argvs
    assert sum(a[0] == "edgemodbus" for a in argvs) >= 10
    dial = next(a for a in argvs if "--dial" in a)
    assert dial[-2:] == ("--heartbeat-interval", "30")  # the continued line
    assert all(skip in argvs for skip in SKIP), "a skipped command left the pages"
    assert all(how_to_run(a) is not None for a in argvs)


def test_extraction_rules_and_unknown_commands() -> None:
    """Shell blocks give every line, unlabelled blocks only command lines, other blocks
    nothing; a command without a runner or skip is reported, not passed over."""
    text = "\n".join([
        "edgemodbus demo  (prose, not a block)",
        "```sh",
        "# a comment",
        "edgemodbus frobnicate --now   # new sub-command",
        "./configure && make",
        "edgemodbus read --host h \\",
        "    hr:1",
        "```",
        "```",
        "config -> items -> plan",
        "reads  42011 requests",
        "make test    # comment",
        "```",
        "```python",
        "edgemodbus = 1",
        "```",
    ])
    found = readme_commands(text)
    assert [(c.line, c.argv) for c in found] == [
        (4, ("edgemodbus", "frobnicate", "--now")),
        (5, ("./configure", "&&", "make")),
        (6, ("edgemodbus", "read", "--host", "h", "hr:1")),
        (12, ("make", "test")),
    ]
    assert [how_to_run(c.argv) is None for c in found] == [True, True, False, False]


def test_rewrite_touches_only_the_outside_world() -> None:
    argv = ("edgemodbus", "read", "--host", "10.0.0.5", "--port", "502", "--slave", "2",
            "--type", "Float", "hr:100")
    assert rewrite(argv, host="127.0.0.1", port="4000") == [
        "edgemodbus", "read", "--host", "127.0.0.1", "--port", "4000", "--slave", "2",
        "--type", "Float", "hr:100"]
    assert rewrite(("edgemodbus", "run", "device.json"), file="/tmp/d.json", seconds="1") == [
        "edgemodbus", "run", "/tmp/d.json", "--seconds", "1"]
    with pytest.raises(AssertionError):
        rewrite(argv, slave="9")  # not an outside-world option
