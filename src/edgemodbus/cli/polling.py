"""The commands behind ``edgemodbus demo/run/read/write/plan``: poll devices, print what
they report (cli/__init__.py parses the options and calls these)."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import cast

from ..config import (
    ConfigError,
    DeviceAddressItem,
    DeviceConfig,
    DeviceOrganizationParameter,
    DriverModbusRtuParameter,
    load_device_config,
)
from ..datatypes import Area, ItemStatus
from ..driver import DriverModbusRtu
from ..line.endpoint import endpoint_for
from ..poll.poller import build_plan
from ..poll.schedule import entity_numbers_notice
from .arg_types import MAX_SECONDS
from .exits import FAILED, INTERRUPTED, OK, CommandFailed
from .line_options import entity_notice_line
from .oneitem import framing_hint, start_one_item
from .output import (
    CliError,
    config_warnings,
    emit,
    in_file,
    json_line,
    problem_lines,
    stdout_closed,
    stop_when_stdout_closes,
    value_text,
)

__all__ = ["DEMO_FILE", "demo", "load_file", "plan", "read", "run", "write"]

DEMO_FILE = Path(__file__).resolve().parent.parent / "demo-device.json"  # examples/ links here



def demo(args: argparse.Namespace) -> int:
    from ..sim import Simulator, add_demo_movers

    slaves: list[int] = args.slaves
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
        print(f"simulator: slaves {','.join(map(str, slaves))} on rtu-over-tcp://127.0.0.1:"
              f"{port}; polling {DEMO_FILE.name} every "
              f"{cfg.effective_parameters().read_cycle} ms")
        drivers = []
        for slave_id in slaves:
            comm = cfg.communication.model_copy(update={"tcp_port": port, "slave_id": slave_id})
            org = cfg.organization.model_copy(
                update={"device_code": f"{cfg.organization.device_code}-{slave_id}"}
            )
            items = [it.model_copy(deep=True) for it in cfg.address_list]
            drivers.append(_start(org, comm, items, json_lines=False))
        interrupted = _poll_until_done(drivers, args.seconds, json_lines=False)
    return INTERRUPTED if interrupted else _done()


def run(args: argparse.Namespace) -> int:
    if args.config_dir is not None:
        if args.files:
            raise CliError("give device files or --config-dir, not both")
        from ..gateway import run_service

        return run_service(args.config_dir, args.gateway, seconds=args.seconds)
    if not args.files:
        raise CliError("give device files, or --config-dir DIR")
    if args.gateway is not None:
        raise CliError(f"--gateway {args.gateway}: applies to --config-dir (a gateway file "
                       "configures the service)")
    if not 0 <= args.seconds <= MAX_SECONDS:  # -5 ran until Ctrl-C, 1e20 overflowed
        raise CliError(f"--seconds {args.seconds}: must be >= 0 and at most "
                       f"{MAX_SECONDS:,} (0: run until Ctrl-C)")
    drivers: list[tuple[Path, DriverModbusRtu]] = []
    try:
        for file in args.files:
            cfg = load_file(file, "run")
            try:
                drv = _start(cfg.organization, cfg.communication, cfg.address_list, args.json)
            except (ValueError, OSError) as exc:  # e.g. a serial port opened with other settings
                raise CliError(*(in_file(file, line) for line in problem_lines(exc))) from None
            if not drv.is_enable:
                print(f"{file}: device is disabled (isEnable false), not polled",
                      file=sys.stderr)
            drivers.append((file, drv))
    except BaseException:
        for _, drv in drivers:
            drv.stop_device()
        raise
    interrupted = _poll_until_done([drv for _, drv in drivers], args.seconds, args.json)
    if interrupted:
        return INTERRUPTED
    if stdout_closed():
        return _done()
    silent = [_never_answered(file, drv) for file, drv in drivers
              if drv.is_enable and not drv.stats().get("responses")]
    if silent:
        raise CommandFailed(*silent)
    return OK


def _never_answered(file: Path, drv: DriverModbusRtu) -> str:
    """``FILE: device D never answered (the reason its items gave)``."""
    reasons = {it.error_reason for it in drv.address_items if it.error_reason}
    why = f" ({sorted(reasons)[0]})" if reasons else ""
    return f"{file}: device {drv.snapshot()['deviceCode']} never answered{why}"


def read(args: argparse.Namespace, notice: bool = True) -> int:
    """Read the item through a one-item device (oneshot.py's read when that could not:
    it printed the notice already)."""
    if notice:
        _notice(args)
    got = threading.Event()
    drv, item = start_one_item(args, lambda it: got.set())
    try:
        if not got.wait(args.timeout / 1000 * 4 + 5):
            raise CommandFailed(f"{item.address}: no answer")
    finally:
        drv.stop_device()
    if item.status is not ItemStatus.OK:
        raise CommandFailed(_with_hint(f"{item.address}: {item.error_reason}", args, drv))
    print(value_text(item.value))
    return OK


def write(args: argparse.Namespace) -> int:
    _notice(args)
    drv, _ = start_one_item(args)
    try:
        ok, err = drv.write_address("value", args.value)
    finally:
        drv.stop_device()
    if not ok:
        if not drv.stats().get("writes"):  # refused before a request went out: the value
            raise CliError(str(err))
        raise CommandFailed(_with_hint(str(err), args, drv))
    print("ok")
    return OK


def _notice(args: argparse.Namespace) -> None:
    line = entity_notice_line(args)
    if line is not None:
        print(f"edgemodbus {args.command}: {line}", file=sys.stderr)


def _with_hint(message: str, args: argparse.Namespace, drv: DriverModbusRtu) -> str:
    hint = framing_hint(args, drv)
    return message if hint is None else f"{message}; {hint}"


def plan(args: argparse.Namespace) -> int:
    cfg = load_file(args.file, "plan")
    params = cfg.effective_parameters()
    parsed = cfg.parsed_items()
    blocks = build_plan(parsed, params)
    notice = entity_numbers_notice(parsed, params)
    if notice is not None:
        print(f"edgemodbus plan: notice: {in_file(args.file, notice)}", file=sys.stderr)
    print(f"{len(parsed)} items, {len(blocks)} requests per cycle (slave {params.slave_id} "
          f"on {endpoint_for(params).describe()})")
    for block in blocks:
        names = [parsed[cast(int, p.key)].name for p in block.pieces]
        end = block.start + block.count - 1
        rate = "" if block.rate == params.read_cycle else f" every {block.rate} ms"
        print(f"  FC{block.area.read_function:02d} {block.area.short_name}:{block.start}-{end} "
              f"({block.count}){rate}: {', '.join(names)}")
    return 0


# -- helpers -----------------------------------------------------------------------------
def load_file(file: Path, command: str) -> DeviceConfig:
    """Load a device file; every problem (and every warning, e.g. an unknown key) is one
    line that names the file."""
    warnings: list[str] = []
    try:
        with config_warnings(warnings):
            return load_device_config(file)
    except ConfigError as exc:
        raise CliError(*(in_file(file, str(p)) for p in exc.problems)) from None
    except OSError as exc:
        raise CliError(f"{file}: {exc.strerror or exc}") from None
    except RecursionError:  # a backstop: config/ bounds the depth it reads
        raise CliError(f"{file}: JSON nested too deeply to read") from None
    finally:
        for message in warnings:
            print(f"edgemodbus {command}: warning: {in_file(file, message)}", file=sys.stderr)


def _start(org: DeviceOrganizationParameter, comm: DriverModbusRtuParameter,
           items: Sequence[DeviceAddressItem], json_lines: bool) -> DriverModbusRtu:
    drv = DriverModbusRtu()
    code = org.device_code or f"slave{comm.slave_id}"
    if json_lines:
        drv.address_updated_callback = lambda it: emit(json_line({
            "device": code, "name": it.name, "value": it.value, "status": it.status.value,
            "updateTs": it.update_ts, "errorReason": it.error_reason}))
    else:
        drv.address_updated_callback = lambda it: emit(_line(code, it))
    drv.start_device(org, comm, items)
    return drv


def _poll_until_done(drivers: list[DriverModbusRtu], seconds: float, json_lines: bool) -> bool:
    """Let the drivers poll for ``seconds`` (0: until Ctrl-C or SIGTERM), stop them,
    then print one summary line each.  True when Ctrl-C stopped them."""
    try:
        interrupted = _wait(seconds)
    finally:
        for drv in drivers:
            drv.stop_device()
    for drv in drivers:
        _summary(drv, json_lines)
    return interrupted


def _done() -> int:
    """OK, or FAILED when stdout's reader went away before the end (the exit code
    Python's own EPIPE handling gives)."""
    return FAILED if stdout_closed() else OK


def _wait(seconds: float) -> bool:
    """Wait ``seconds`` (0: forever), until SIGTERM or until stdout's reader went away;
    True when Ctrl-C ended it."""
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        with stop_when_stdout_closes(stop):
            stop.wait(seconds if seconds > 0 else None)
    except KeyboardInterrupt:
        return True
    return False


def _line(code: str, item: DeviceAddressItem) -> str:
    stamp = item.update_ts.strftime("%H:%M:%S.%f")[:-3] if item.update_ts else "--"
    if item.status is ItemStatus.OK:
        text = f"{value_text(item.value)} {item.unit}".rstrip()
    else:
        text = f"{item.status.value}: {item.error_reason}"
    return f"{stamp} {code:<12} {item.name:<12} {text}"


def _summary(drv: DriverModbusRtu, json_lines: bool) -> None:
    s = drv.stats()
    code = drv.snapshot()["deviceCode"]
    if json_lines:
        emit(json_line({"device": code, "summary": s}))
        return
    emit(f"{code}: {s['deviceDriverStatus']}, {s.get('cycles', 0)} cycles, "
          f"{s.get('requests', 0)} requests, {s.get('timeouts', 0)} timeouts, "
          f"{s.get('crcErrors', 0)} CRC errors, avg cycle "
          f"{s.get('avgCycleTime', 0.0) * 1000:.1f} ms, avg round trip "
          f"{s.get('avgRoundTrip', 0.0) * 1000:.2f} ms, {s.get('valuesChanged', 0)} updates")


def _text_registers(text: str, registers: int) -> list[int]:
    raw = text.encode().ljust(2 * registers, b"\0")[: 2 * registers]
    return [raw[i] << 8 | raw[i + 1] for i in range(0, len(raw), 2)]
