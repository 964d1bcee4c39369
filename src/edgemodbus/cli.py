"""The ``edgemodbus`` command: demo, run, read, write, plan, simulate, descriptor.

Errors are one clear line on stderr and a non-zero exit code.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

from .config import (
    DeviceAddressItem,
    DeviceConfig,
    DeviceOrganizationParameter,
    DriverModbusRtuParameter,
    ItemStatus,
    load_device_config,
)
from .datatypes import Area
from .descriptor import driver_descriptor
from .device import build_plan
from .driver import DriverModbusRtu

DEMO_FILE = Path(__file__).resolve().with_name("demo-device.json")  # examples/ links here


class CliError(Exception):
    """A user error: printed as one line, exit code 2."""


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    command_at = next((i for i, a in enumerate(argv) if not a.startswith("-")), len(argv))
    if argv[command_at:command_at + 1] == ["simulate"]:
        # the simulator parses its own options (argparse.REMAINDER would not take options
        # such as --port that follow a sub-command)
        args = parser.parse_args([*argv[:command_at], "simulate"])
        _configure_logging(args.verbose)
        from .simulator import main as simulate

        return simulate(argv[command_at + 1:])
    args = parser.parse_args(argv)
    _configure_logging(args.verbose)
    try:
        result: int = args.func(args)
        return result
    except (CliError, ValueError, OSError) as exc:
        print(f"edgemodbus {args.command}: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


def _configure_logging(verbose: int) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose > 1 else logging.INFO if verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="edgemodbus", description=__doc__)
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more (-vv: frame trace)")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="poll a simulated line of slaves, print live values")
    demo.add_argument("--seconds", type=float, default=10.0, help="how long (10; 0 = until ^C)")
    demo.add_argument("--slaves", default="1,2,3", help="slave ids on the line (1,2,3)")
    demo.set_defaults(func=_demo)

    run = sub.add_parser("run", help="poll devices from device files, print updates; or run "
                         "the gateway service with --config-dir")
    run.add_argument("files", nargs="*", type=Path)
    run.add_argument("--config-dir", type=Path, default=None,
                     help="gateway service: every device file in DIR; MQTT/metrics from "
                     "DIR/gateway.json or --gateway; SIGHUP reloads, SIGTERM stops")
    run.add_argument("--gateway", type=Path, default=None, help="gateway file (with --config-dir)")
    run.add_argument("--json", action="store_true", help="JSON lines instead of text")
    run.add_argument("--seconds", type=float, default=0.0, help="stop after N s (0 = ^C)")
    run.set_defaults(func=_run)

    for name, helptext in (("read", "read one value"), ("write", "write one value")):
        p = sub.add_parser(name, help=helptext)
        _line_options(p)
        p.add_argument("address", help="e.g. hr:100, 3:00005, coil:5, hr:7.3")
        if name == "write":
            p.add_argument("value", help="value to write (number, true/false, text)")
            p.set_defaults(func=_write)
        else:
            p.set_defaults(func=_read)

    plan = sub.add_parser("plan", help="show the read plan of a device file")
    plan.add_argument("file", type=Path)
    plan.set_defaults(func=_plan)

    sub.add_parser("simulate", help="serve simulated RTU slaves (see simulate -h)",
                   add_help=False)

    desc = sub.add_parser("descriptor", help="print the driver descriptor JSON")
    desc.add_argument("--prefix", choices=["function-code", "modicon"], default="function-code")
    desc.set_defaults(func=lambda a: _print_json(driver_descriptor(a.prefix)))
    return parser


def _line_options(p: argparse.ArgumentParser) -> None:
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--host", help="TCP host (with --port)")
    where.add_argument("--serial", metavar="DEVICE", help="serial port, e.g. /dev/ttyUSB0")
    p.add_argument("--port", type=int, default=502, help="TCP port (502)")
    p.add_argument("--transport", choices=["rtu-over-tcp", "tcp"], default="rtu-over-tcp",
                   help="with --host: raw RTU frames (default) or Modbus TCP")
    p.add_argument("--baud", type=int, default=9600)
    p.add_argument("--parity", default="N", help="N, E or O")
    p.add_argument("--data-bits", type=int, default=8)
    p.add_argument("--stop-bits", type=int, default=1)
    p.add_argument("--slave", type=int, default=1, help="slave / unit id (1)")
    p.add_argument("--type", default="UInt16", help="data type (UInt16)")
    p.add_argument("--format", default="ABCD", help="ABCD, BADC, CDAB or DCBA")
    p.add_argument("--quantity", type=int, default=None, help="registers (String/Binary)")
    p.add_argument("--multiplier", type=float, default=1.0)
    p.add_argument("--timeout", type=int, default=1000, help="response timeout in ms (1000)")


# -- commands ----------------------------------------------------------------------------
def _demo(args: argparse.Namespace) -> int:
    from .simulator import Simulator, add_demo_movers

    slaves = [int(s) for s in args.slaves.split(",") if s.strip()]
    cfg = load_device_config(DEMO_FILE)
    with Simulator(slaves) as sim:
        hr = Area.HOLDING_REGISTER
        for slave in sim.slaves:
            add_demo_movers(slave)
            sid = slave.slave_id
            slave.set_registers(hr, 10, [sid % 2])  # Running bit
            slave.set_registers(hr, 12, [sid * 1000, 0])  # Energy, UInt32 CDAB (low word first)
            slave.set_registers(hr, 20, _text_registers(f"PUMP-{sid:02d}", 4))  # Model
        port = sim.serve_tcp("127.0.0.1", 0)
        print(f"simulator: slaves {args.slaves} on rtu-over-tcp://127.0.0.1:{port}; "
              f"polling {DEMO_FILE.name} every {cfg.effective_parameters().read_cycle} ms")
        drivers = []
        for slave_id in slaves:
            comm = cfg.communication.model_copy(update={"tcp_port": port, "slave_id": slave_id})
            org = cfg.organization.model_copy(
                update={"device_code": f"{cfg.organization.device_code}-{slave_id}"}
            )
            items = [it.model_copy(deep=True) for it in cfg.address_list]
            drivers.append(_start(org, comm, items, json_lines=False))
        _poll_until_done(drivers, args.seconds)
    return 0


def _run(args: argparse.Namespace) -> int:
    if args.config_dir is not None:
        if args.files:
            raise CliError("give device files or --config-dir, not both")
        from .service import run_service

        logging.getLogger("edgemodbus").setLevel(logging.DEBUG if args.verbose > 1 else
                                                 logging.INFO)
        return run_service(args.config_dir, args.gateway, seconds=args.seconds)
    if not args.files:
        raise CliError("give device files, or --config-dir DIR")
    drivers = []
    try:
        for file in args.files:
            cfg = load_device_config(file)
            drv = _start(cfg.organization, cfg.communication, cfg.address_list, args.json)
            if not drv.is_enable:
                print(f"{file}: device is disabled (isEnable false), not polled",
                      file=sys.stderr)
            drivers.append(drv)
    except BaseException:
        for drv in drivers:
            drv.stop_device()
        raise
    _poll_until_done(drivers, args.seconds)
    return 0


def _read(args: argparse.Namespace) -> int:
    drv, item = _one_item(args)
    got = threading.Event()
    drv.address_updated_callback = lambda it: got.set()
    try:
        if not got.wait(args.timeout / 1000 * 4 + 5):
            raise CliError("no answer")
    finally:
        drv.stop_device()
    if item.status is not ItemStatus.OK:
        raise CliError(f"{item.address}: {item.error_reason}")
    print(_show(item.value))
    return 0


def _write(args: argparse.Namespace) -> int:
    drv, _ = _one_item(args)
    try:
        ok, err = drv.write_address("value", args.value)
    finally:
        drv.stop_device()
    if not ok:
        raise CliError(str(err))
    print("ok")
    return 0


def _plan(args: argparse.Namespace) -> int:
    cfg = load_device_config(args.file)
    params = cfg.effective_parameters()
    parsed = cfg.parsed_items()
    blocks = build_plan(parsed, params)
    print(f"{len(parsed)} items, {len(blocks)} requests per cycle (slave {params.slave_id})")
    for block in blocks:
        names = [parsed[cast(int, p.key)].name for p in block.pieces]
        end = block.start + block.count - 1
        print(f"  FC{block.area.read_function:02d} {block.area.short_name}:{block.start}-{end} "
              f"({block.count}): {', '.join(names)}")
    return 0


# -- helpers -----------------------------------------------------------------------------
def _start(org: DeviceOrganizationParameter, comm: DriverModbusRtuParameter,
           items: Sequence[DeviceAddressItem], json_lines: bool) -> DriverModbusRtu:
    drv = DriverModbusRtu()
    code = org.device_code or f"slave{comm.slave_id}"
    if json_lines:
        drv.address_updated_callback = lambda it: print(json.dumps(
            {"device": code, "name": it.name, "value": _show(it.value), "status":
             it.status.value, "updateTs": it.update_ts.isoformat() if it.update_ts else None,
             "errorReason": it.error_reason}, ensure_ascii=False), flush=True)
    else:
        drv.address_updated_callback = lambda it: print(_line(code, it), flush=True)
    drv.start_device(org, comm, items)
    return drv


def _one_item(args: argparse.Namespace) -> tuple[DriverModbusRtu, DeviceAddressItem]:
    comm: dict[str, Any] = {
        "slaveId": args.slave, "readTimeout": args.timeout, "readCycle": 1000,
        "dataFormat": args.format, "retries": 0, "offlineAfterFailedCycles": 1000,
    }
    if args.host:
        comm.update(transport=args.transport, tcpHost=args.host, tcpPort=args.port)
    else:
        comm.update(transport="rtu", comPort=args.serial, baudRate=args.baud,
                    parity=args.parity, dataBits=args.data_bits, stopBits=args.stop_bits)
    item: dict[str, Any] = {"name": "value", "address": args.address,
                            "deviceDataType": args.type, "dataMultiplier": args.multiplier}
    if args.quantity is not None:
        item["quantity"] = args.quantity
    cfg: DeviceConfig = load_device_config({"communication": comm, "addressList": [item]})
    drv = DriverModbusRtu()
    drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    return drv, cfg.address_list[0]


def _poll_until_done(drivers: list[DriverModbusRtu], seconds: float) -> None:
    """Let the drivers poll for ``seconds`` (0: until Ctrl-C or SIGTERM), stop them,
    then print one summary line each."""
    try:
        _wait(seconds)
    finally:
        for drv in drivers:
            drv.stop_device()
    for drv in drivers:
        _summary(drv)


def _wait(seconds: float) -> None:
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with contextlib.suppress(KeyboardInterrupt):
        stop.wait(seconds if seconds > 0 else None)


def _line(code: str, item: DeviceAddressItem) -> str:
    stamp = item.update_ts.strftime("%H:%M:%S.%f")[:-3] if item.update_ts else "--"
    if item.status is ItemStatus.OK:
        text = f"{_show(item.value)} {item.unit}".rstrip()
    else:
        text = f"{item.status.value}: {item.error_reason}"
    return f"{stamp} {code:<12} {item.name:<12} {text}"


def _summary(drv: DriverModbusRtu) -> None:
    s = drv.stats()
    snap = drv.snapshot()
    print(f"{snap['deviceCode']}: {snap['deviceDriverStatus']}, {s.get('cycles', 0)} cycles, "
          f"{s.get('requests', 0)} requests, {s.get('timeouts', 0)} timeouts, "
          f"{s.get('crcErrors', 0)} CRC errors, avg cycle "
          f"{s.get('avgCycleTime', 0.0) * 1000:.1f} ms, avg round trip "
          f"{s.get('avgRoundTrip', 0.0) * 1000:.2f} ms, {s.get('valuesChanged', 0)} updates")


def _show(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, 6)
    if isinstance(value, bytes):
        return value.hex()
    if hasattr(value, "isoformat"):
        return value.isoformat()
    return value


def _text_registers(text: str, registers: int) -> list[int]:
    raw = text.encode().ljust(2 * registers, b"\0")[: 2 * registers]
    return [raw[i] << 8 | raw[i + 1] for i in range(0, len(raw), 2)]


def _print_json(data: Any) -> int:
    print(json.dumps(data, indent=2, ensure_ascii=False))
    return 0


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


if __name__ == "__main__":
    sys.exit(main())
