"""Issue 24, "First use that never misleads": the command line as a newcomer meets it, one
process per call, against pymodbus (Modbus TCP) and our simulator (RTU over TCP)."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.sim import Simulator, default_register
from tests.peers import PymodbusSlave, free_port

CLI = [sys.executable, "-m", "edgemodbus.cli"]
NOTICE = "for Modicon numbering set addressPrefix: entity"
READY = 20.0  # s for a started process to print its first line on a loaded machine


def cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout,
                          check=False)


@pytest.fixture
def sim() -> Iterator[tuple[Simulator, int]]:
    """Slave 1, every address readable (40001 too), RTU frames over TCP."""
    with Simulator([1], 0x10000) as s:
        yield s, s.serve_tcp("127.0.0.1", 0)


def device(path: Path, comm: dict[str, Any], items: list[dict[str, Any]] | None = None,
           code: str = "Dev") -> Path:
    path.write_text(json.dumps({
        "organization": {"deviceCode": code},
        "communication": {"readCycle": 200, "readTimeout": 300, **comm},
        "addressList": items or [{"name": "r", "address": "hr:7", "deviceDataType": "UInt16"}],
    }))
    return path


def one_line(out: subprocess.CompletedProcess[str]) -> str:
    lines = out.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr
    return lines[0]


# -- --host speaks Modbus TCP; the wrong framing is named --------------------------------
def test_host_speaks_modbus_tcp() -> None:
    """The `read --host H --port 502 hr:0` of docs/command-line.md against a Modbus TCP
    slave (it framed RTU over TCP and failed)."""
    with PymodbusSlave("tcp", units=(1,)) as slave:
        out = cli("read", "--host", "127.0.0.1", "--port", str(slave.port), "hr:0")
    assert (out.returncode, out.stdout.strip()) == (0, str(1000)), out.stderr  # unit*1000+0


def test_a_reply_in_the_other_framing_names_the_flag(sim: tuple[Simulator, int]) -> None:
    _, port = sim
    where = ["--host", "127.0.0.1", "--port", str(port), "--timeout", "300"]
    out = cli("read", *where, "hr:7")  # Modbus TCP to an RTU-over-TCP slave
    assert out.returncode == 1
    line = one_line(out)
    assert line.startswith("edgemodbus read: hr:7: device not responding"), line
    assert line.endswith("the device answered raw RTU frames over TCP (a serial server, a "
                         "DTU, edgemodbus simulate): add --rtu-over-tcp"), line
    out = cli("write", *where, "hr:7", "5")
    assert out.returncode == 1 and one_line(out).endswith("add --rtu-over-tcp"), out.stderr
    out = cli("read", *where, "--rtu-over-tcp", "hr:7")
    assert (out.returncode, out.stdout.strip()) == (0, str(default_register(1, 7))), out.stderr
    out = cli("read", *where, "--rtu-over-tcp", "--slave", "9", "hr:7")  # nobody at 9
    assert out.returncode == 1
    assert "add --rtu-over-tcp" not in out.stderr and "leave out" not in out.stderr
    with PymodbusSlave("tcp", units=(1,)) as slave:
        out = cli("read", "--host", "127.0.0.1", "--port", str(slave.port), "--timeout", "300",
                  "--rtu-over-tcp", "hr:7")
    assert out.returncode == 1
    assert one_line(out).endswith("the device answered Modbus TCP: leave out --rtu-over-tcp "
                                  "(--host speaks Modbus TCP)"), out.stderr


# -- device files: the transport the keys name; exit 1 for a device that never answered ----
def test_tcp_keys_alone_poll_the_tcp_endpoint(tmp_path: Path,
                                              sim: tuple[Simulator, int]) -> None:
    _, port = sim
    path = device(tmp_path / "dtu.json", {"tcpHost": "127.0.0.1", "tcpPort": port})
    out = cli("plan", str(path))
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0] == \
        f"1 items, 1 requests per cycle (slave 1 on rtu-over-tcp://127.0.0.1:{port})"
    out = cli("run", "--json", "--seconds", "1.5", str(path))
    assert out.returncode == 0, out.stderr
    values = [json.loads(line) for line in out.stdout.splitlines()]
    assert values[0]["value"] == default_register(1, 7), values
    both = device(tmp_path / "both.json",
                  {"comPort": "COM1", "tcpHost": "127.0.0.1", "tcpPort": port})
    out = cli("run", "--seconds", "1", str(both))
    assert out.returncode == 2
    line = one_line(out)
    assert line.startswith(f"edgemodbus run: {both}: communication.transport: missing: "
                           "comPort 'COM1' and tcpHost '127.0.0.1' and tcpPort"), line


def test_run_exits_1_naming_a_device_that_never_answered(
        tmp_path: Path, sim: tuple[Simulator, int]) -> None:
    _, port = sim
    good = device(tmp_path / "good.json", {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                                           "tcpPort": port}, code="Good")
    silent = device(tmp_path / "silent.json", {"transport": "rtu-over-tcp", "slaveId": 9,
                                               "tcpHost": "127.0.0.1", "tcpPort": port},
                    code="Silent")
    out = cli("run", "--seconds", "1.5", str(good), str(silent))
    assert out.returncode == 1, out.stderr
    mine = [line for line in out.stderr.splitlines() if line.startswith("edgemodbus run:")]
    assert mine == [  # (a loaded machine may also log the silent device going Offline)
        f"edgemodbus run: {silent}: device Silent never answered (device not responding: "
        "slave 9 FC03 @7+1: no response (timeout))"], out.stderr
    out = cli("run", "--seconds", "1.5", str(good))
    assert (out.returncode, out.stderr) == (0, "")
    closed = device(tmp_path / "closed.json", {"tcpHost": "127.0.0.1", "tcpPort": free_port()},
                    code="Closed")
    out = cli("run", "--seconds", "3", str(closed))  # room for a loaded machine
    assert out.returncode == 1  # after the line's own warning (logged: run's default level)
    assert out.stderr.splitlines()[-1].startswith(
        f"edgemodbus run: {closed}: device Closed never answered (link down: "), out.stderr


# -- 40001 without addressPrefix entity: valid, with a notice ------------------------------
def test_entity_lookalikes_get_one_notice(tmp_path: Path, sim: tuple[Simulator, int]) -> None:
    _, port = sim
    items = [{"name": f"e{a}", "address": str(a), "deviceDataType": "UInt16"}
             for a in (40001, 40002, 30005)]
    path = device(tmp_path / "sunspec.json", {"transport": "rtu-over-tcp",
                                              "tcpHost": "127.0.0.1", "tcpPort": port}, items)
    out = cli("plan", str(path))
    assert out.returncode == 0, out.stderr
    assert one_line(out) == (
        f"edgemodbus plan: notice: {path}: item 'e40001': address '40001' is read as holding "
        "register 40001 (hr:40001); as a Modicon entity number it would be holding register "
        f"0 (hr:0) (and 2 more such addresses); {NOTICE}")
    assert "  FC03 hr:40001-40002 (2): e40001, e40002" in out.stdout  # offsets, as before
    out = cli("run", "--json", "--seconds", "1.5", str(path))
    assert out.returncode == 0, out.stderr
    assert sum(NOTICE in line for line in out.stderr.splitlines()) == 1, out.stderr
    values = {r["name"]: r["value"] for r in map(json.loads, out.stdout.splitlines())
              if "name" in r}
    assert values["e40001"] == default_register(1, 40001)
    entity = device(tmp_path / "entity.json", {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                                               "tcpPort": port, "addressPrefix": "entity"}, items)
    out = cli("plan", str(entity))
    assert (out.returncode, out.stderr) == (0, ""), out.stderr


def test_read_takes_the_address_prefix(sim: tuple[Simulator, int]) -> None:
    _, port = sim
    where = ["--host", "127.0.0.1", "--port", str(port), "--rtu-over-tcp"]
    out = cli("read", *where, "--address-prefix", "entity", "40008")
    assert (out.returncode, out.stdout.strip(), out.stderr) == (
        0, str(default_register(1, 7)), "")
    out = cli("read", *where, "40008")
    assert (out.returncode, out.stdout.strip()) == (0, str(default_register(1, 40008)))
    assert one_line(out) == (
        "edgemodbus read: notice: address '40008' is read as holding register 40008 "
        "(hr:40008); as a Modicon entity number it would be holding register 7 (hr:7); for "
        "Modicon numbering use --address-prefix entity")


def test_import_notices_entity_lookalikes(tmp_path: Path) -> None:
    csv = tmp_path / "tags.csv"
    csv.write_text("name,address,type\nLevel,40001,UInt16\nFlow,40003,Float\nPump,coil:3,"
                   "Boolean\n", encoding="utf-8")
    out = cli("import", str(csv))
    assert out.returncode == 0, out.stderr
    assert out.stderr.splitlines()[0] == (
        f"edgemodbus import: notice: {csv}: row 2: address '40001' is read as holding register "
        "40001 (hr:40001); as a Modicon entity number it would be holding register 0 (hr:0) "
        "(and 1 more such rows); for Modicon numbering use --address-prefix entity")
    out = cli("import", "--address-prefix", "entity", str(csv))
    assert out.returncode == 0 and "import: notice:" not in out.stderr, out.stderr
    assert [i["address"] for i in json.loads(out.stdout)["addressList"]] == \
        ["hr:0", "hr:2", "coil:3"]


# -- one line instead of a traceback, exit code 2 ------------------------------------------
@pytest.mark.parametrize(("args", "start"), [
    (["--slaves", "1-300"], "edgemodbus simulate: argument --slaves: '1-300' is outside "
                            "1..247 or reversed"),
    (["--slaves", "abc"], "edgemodbus simulate: argument --slaves: 'abc' is not a number "
                          "or range (allowed: ids 1..247"),
    (["--size", "0"], "edgemodbus: --size 0: must be 1..65536"),
])
def test_simulate_option_errors_are_one_line(args: list[str], start: str) -> None:
    out = cli("simulate", "--port", "0", *args)
    assert out.returncode == 2
    assert one_line(out).startswith(start), out.stderr


def test_simulate_port_in_use_and_refused_dial_name_the_option() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        out = cli("simulate", "--port", str(port))
    assert out.returncode == 2
    assert one_line(out) == (f"edgemodbus simulate: --host 127.0.0.1 --port {port}: cannot "
                             f"listen on 127.0.0.1:{port}: Address already in use")
    closed = free_port()
    out = cli("simulate", "--dial", f"127.0.0.1:{closed}")
    assert out.returncode == 2
    assert one_line(out) == (f"edgemodbus simulate: --dial 127.0.0.1:{closed}: cannot "
                             "connect: Connection refused")


@pytest.mark.parametrize(("argv", "signum", "code"), [
    (["simulate", "--port", "0"], signal.SIGINT, 130),
    (["simulate", "--port", "0"], signal.SIGTERM, 0),
])
def test_simulate_exit_codes_of_signals(argv: list[str], signum: int, code: int) -> None:
    proc = subprocess.Popen([*CLI, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("tcp 127.0.0.1:")  # serving
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=READY)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == code, err
    assert "Traceback" not in err


def test_run_interrupted_exits_130(tmp_path: Path, sim: tuple[Simulator, int]) -> None:
    _, port = sim
    path = device(tmp_path / "d.json", {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                                        "tcpPort": port}, code="Int")
    proc = subprocess.Popen([*CLI, "run", str(path)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert " Int " in proc.stdout.readline()  # polling: the first update
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=READY)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert out.splitlines()[-1].startswith("Int: Stopped, ")  # the summary still printed


@pytest.mark.parametrize(("section", "blocked", "extra"), [
    ({"mqtt": {"host": "127.0.0.1", "port": 1}}, "paho", "mqtt"),
    ({"mqtt": {"host": "127.0.0.1", "port": 1, "mode": "sparkplug",
               "sparkplug": {"groupId": "plant1"}}}, "paho", "sparkplug"),
    ({"metrics": {"host": "127.0.0.1", "port": 0}}, "prometheus_client", "metrics"),
])
def test_gateway_without_an_optional_package(tmp_path: Path, section: dict[str, Any],
                                             blocked: str, extra: str) -> None:
    """The gateway file asks for MQTT (or metrics) and the package is not installed: one
    line naming the section and the extra, exit code 2 (it was a traceback)."""
    (tmp_path / "gateway.json").write_text(json.dumps({"gatewayId": "gw", **section}))
    code = (f"import sys; sys.modules[{blocked!r}] = None; from edgemodbus.cli import main; "
            f"sys.exit(main(['run', '--config-dir', {str(tmp_path)!r}, '--seconds', '5']))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=False)
    assert out.returncode == 2, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if "edgemodbus service:" in ln]
    assert "Traceback" not in out.stderr and len(lines) == 1, out.stderr
    name = next(iter(section))
    assert lines[0].startswith(f"edgemodbus service: {name}: needs the optional packages of "
                               f"edgemodbus[{extra}], not installed"), lines
    assert f"pip install 'edgemodbus[{extra}]'" in lines[0]


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 0)])
def test_service_exit_codes_of_signals(tmp_path: Path, signum: int, code: int) -> None:
    """``run --config-dir``: Ctrl-C is 130 as in every command, SIGTERM a clean stop."""
    proc = subprocess.Popen([*CLI, "run", "--config-dir", str(tmp_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        assert "gateway" in line and "running" in line, line  # the signals are handled
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=READY)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == code, err
    assert "Traceback" not in err


@pytest.mark.parametrize(("section", "what"), [
    (lambda port: {"serve": {"listen": f"127.0.0.1:{port}"}}, "Modbus TCP server"),
    (lambda port: {"metrics": {"host": "127.0.0.1", "port": port}}, "metrics"),
])
def test_service_port_in_use_names_the_port(tmp_path: Path, section: Any, what: str) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        (tmp_path / "gateway.json").write_text(json.dumps({"gatewayId": "gw",
                                                           **section(port)}))
        out = cli("run", "--config-dir", str(tmp_path), "--seconds", "5")
    assert out.returncode == 2
    assert one_line(out) == (f"edgemodbus service: {what}: cannot listen on 127.0.0.1:{port}: "
                             "Address already in use")


def test_a_modbus_tcp_server_that_resets_rtu_frames_gets_the_hint(
        sim: tuple[Simulator, int]) -> None:
    """The issue's case: RTU frames to a Modbus TCP port; this server (the gateway's,
    serve/server.py) closes a connection whose MBAP protocol id is not 0.  The error
    says the device answered Modbus TCP; without the flag the read works."""
    import edgemodbus as em
    from edgemodbus.serve.server import ModbusTcpServer

    _, port = sim
    cfg = em.load_device_config({
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": port, "readCycle": 1000, "readTimeout": 500},
        "addressList": [{"name": "r", "address": "hr:7", "deviceDataType": "UInt16"}]})
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    server = ModbusTcpServer("127.0.0.1", 0)
    try:
        server.forward_device(1, drv, timeout=2.0)
        server.start()
        where = ["--host", "127.0.0.1", "--port", str(server.port), "--timeout", "500"]
        out = cli("read", *where, "--rtu-over-tcp", "hr:7")
        assert out.returncode == 1
        line = one_line(out)
        assert line.startswith("edgemodbus read: hr:7: link down: "), line
        assert line.endswith("; the device answered Modbus TCP: leave out --rtu-over-tcp "
                             "(--host speaks Modbus TCP)"), line
        out = cli("read", *where, "hr:7")
        assert (out.returncode, out.stdout.strip()) == (0, str(default_register(1, 7))), \
            out.stderr
    finally:
        server.stop()
        drv.stop_device()


def test_a_deeply_nested_file_is_one_line(tmp_path: Path) -> None:
    """Past the parser's recursion limit: one line, exit 2, for any command that reads
    the file (config/ may bound the depth earlier, with its own message)."""
    path = tmp_path / "deep.json"
    path.write_text('{"communication": ' + "[" * 100_000 + "]" * 100_000 + "}")
    for command in ("plan", "run", "action"):
        out = cli(command, str(path))
        assert out.returncode == 2, (command, out.stderr)
        line = one_line(out)
        assert line.startswith(f"edgemodbus {command}: "), line
        if command != "action":
            assert line.startswith(f"edgemodbus {command}: {path}: "), line


# -- byte order on the command line: the device file's keys, as options ------------------
def test_read_and_write_take_the_byte_order_keys() -> None:
    """--format orders values of two or more registers only, --byte-swap16 swaps a
    one-register value, --format64 orders 64-bit values apart (docs/device-files.md "Byte
    order")."""
    with PymodbusSlave("tcp", units=(1,)) as slave:
        where = ["--host", "127.0.0.1", "--port", str(slave.port)]
        slave.set_registers(1, "hr", 0, [0x1234])
        out = cli("read", *where, "--format", "DCBA", "hr:0")
        assert (out.returncode, out.stdout.strip()) == (0, str(0x1234)), out.stderr
        out = cli("read", *where, "--byte-swap16", "hr:0")
        assert (out.returncode, out.stdout.strip()) == (0, str(0x3412)), out.stderr
        value = 0x0102030405060708
        out = cli("write", *where, "--type", "UInt64", "--format64", "EFGHABCD", "hr:10",
                  str(value))
        assert out.returncode == 0, out.stderr
        assert slave.registers(1, "hr", 10, 4) == [0x0506, 0x0708, 0x0102, 0x0304]
        out = cli("read", *where, "--type", "UInt64", "--format64", "EFGHABCD", "hr:10")
        assert (out.returncode, out.stdout.strip()) == (0, str(value)), out.stderr
        out = cli("read", *where, "--format64", "XYZ", "hr:10")
        assert out.returncode == 2 and one_line(out).startswith("edgemodbus read: --format64"), \
            out.stderr
