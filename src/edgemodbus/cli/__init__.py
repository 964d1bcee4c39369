"""The ``edgemodbus`` command: demo, run, read, write, plan, simulate, descriptor, action,
scan, templates, import.

Errors are one line per problem on stderr.  Exit codes, the same in every command: 0 ok,
1 a runtime failure (a device that never answered, a line that could not be opened, tag
rows refused), 2 a usage or configuration error, 130 interrupted (Ctrl-C).  Values print
so that they read back exactly: a float as its shortest round-trip form (``repr``;
``nan``, ``inf`` and ``-inf`` in text, ``null`` in JSON, which has no such numbers).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NoReturn, cast

from ..config import (
    ConfigError,
    DeviceAddressItem,
    DeviceConfig,
    DeviceOrganizationParameter,
    DriverModbusRtuParameter,
    load_device_config,
)
from ..datatypes import Area, ItemStatus
from ..descriptor import driver_descriptor
from ..driver import DriverModbusRtu
from ..gateway.run import add_arguments as add_service_arguments
from ..line.endpoint import endpoint_for
from ..logs import configure_logging
from ..poll.poller import build_plan
from ..poll.schedule import entity_numbers_notice
from ..sim.cli import DESCRIPTION as SIMULATOR
from ..sim.cli import add_arguments as add_simulator_arguments
from ..sim.cli import slave_ids
from . import action as action_command
from . import import_tags as import_command
from . import scan as scan_command
from . import templates as templates_command
from .exits import FAILED, INTERRUPTED, OK, USAGE, CommandFailed
from .oneitem import add_line_options, entity_notice_line, framing_hint, start_one_item
from .output import CliError, emit, json_line, one_line, print_json, problem_lines, value_text

DEMO_FILE = Path(__file__).resolve().parent.parent / "demo-device.json"  # examples/ links here

_JSON_HELP = (
    "JSON lines on stdout instead of text: one object per item update "
    '{"device", "name", "value", "status", "updateTs", "errorReason"}, then, when polling '
    'stops, one {"device", "summary": {counters}} per device; nothing else goes to stdout. Floats '
    "are exact (shortest round-trip form); NaN and infinities are null"
)

class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (the usage is one ``-h`` away)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {one_line(message)} (see {self.prog} -h)\n")


def _version() -> str:
    """The installed distribution's version (pyproject.toml), else the package's."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("edgemodbus")
    except PackageNotFoundError:
        import edgemodbus

        return str(getattr(edgemodbus, "__version__", "unknown"))


class _SubParser(_Parser):
    """A command's parser: also takes ``-v``/``-vv`` after the command's name (it
    leaves the value given before it when absent)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                          help="log more (-vv: frame trace)")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _logging(args)
    if args.command == "simulate":
        from ..sim.cli import run as simulate

        return simulate(args, parser)
    try:
        result: int = args.func(args)
        return result
    except (CliError, ValueError, OSError) as exc:
        for line in problem_lines(exc):
            print(f"edgemodbus {args.command}: {line}", file=sys.stderr)
        return USAGE
    except CommandFailed as exc:
        for line in exc.lines:
            print(f"edgemodbus {args.command}: {line}", file=sys.stderr)
        return FAILED
    except RecursionError:  # a backstop: config/ bounds the JSON depth it reads
        print(f"edgemodbus {args.command}: input nested too deeply to read", file=sys.stderr)
        return USAGE
    except KeyboardInterrupt:
        return INTERRUPTED


def _logging(args: argparse.Namespace) -> None:
    """Warnings by default, the service (``run --config-dir``) info; each -v one step more
    (logs.py).  read and write report their outcome in their own line, so without -v
    they show the library's errors only: a refused connection is one line, not a warning
    and then the same error."""
    service = args.command == "run" and args.config_dir is not None
    configure_logging(args.verbose, default=logging.INFO if service else logging.WARNING,
                      quiet=getattr(args, "quiet", False))
    if not args.verbose and args.command in ("read", "write"):
        logging.getLogger("edgemodbus").setLevel(logging.ERROR)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="edgemodbus", description=__doc__,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"edgemodbus {_version()}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more (-vv: frame trace); also after the command")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_SubParser)

    demo = sub.add_parser("demo", help="poll a simulated line of slaves, print live values")
    demo.add_argument("--seconds", type=float, default=10.0, help="how long (10; 0 = until ^C)")
    demo.add_argument("--slaves", type=slave_ids, default=[1, 2, 3],
                      help="slave ids on the line (1,2,3)")
    demo.set_defaults(func=_demo)

    run = sub.add_parser("run", help="poll devices from device files, print updates; or run "
                         "the gateway service with --config-dir")
    run.add_argument("files", nargs="*", type=Path)
    add_service_arguments(run, config_dir_required=False)
    run.add_argument("--json", action="store_true", help=_JSON_HELP)
    run.set_defaults(func=_run)

    for name, helptext in (("read", "read one value"), ("write", "write one value")):
        p = sub.add_parser(name, help=helptext)
        add_line_options(p)
        p.add_argument("address", help="e.g. hr:100, 3:00005, coil:5, hr:7.3")
        if name == "write":
            p.add_argument("value", help="value to write (number, true/false, text)")
            p.set_defaults(func=_write)
        else:
            p.set_defaults(func=_read)

    plan = sub.add_parser("plan", help="show the read plan of a device file")
    plan.add_argument("file", type=Path)
    plan.set_defaults(func=_plan)

    simulate = sub.add_parser("simulate", help="serve simulated RTU slaves",
                              description=SIMULATOR)
    add_simulator_arguments(simulate)

    act = sub.add_parser("action", help="run an action of a device file (NAME param=value "
                         "...), or list its actions", description=action_command.__doc__)
    action_command.add_arguments(act)
    act.set_defaults(func=action_command.run)

    desc = sub.add_parser("descriptor", help="print the driver descriptor JSON")
    desc.add_argument("--prefix", choices=["function-code", "modicon", "entity"],
                      default="function-code")
    desc.set_defaults(func=lambda a: print_json(driver_descriptor(a.prefix)))

    scan = sub.add_parser("scan", help="find what answers on a line (settings, slave ids)",
                          description=scan_command.__doc__,
                          formatter_class=argparse.RawDescriptionHelpFormatter)
    scan_command.add_arguments(scan)

    tpl = sub.add_parser("templates", help="list the device templates (or show one)",
                         description=templates_command.__doc__,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    templates_command.add_arguments(tpl)
    tpl.set_defaults(func=templates_command.run)

    imp = sub.add_parser("import", help="turn a tag list (Kepware CSV export, or generic "
                         "CSV) into a device file", description=import_command.__doc__,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    import_command.add_arguments(imp)
    imp.set_defaults(func=import_command.run)
    return parser


# -- commands ----------------------------------------------------------------------------
def _demo(args: argparse.Namespace) -> int:
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
    return INTERRUPTED if interrupted else OK


def _run(args: argparse.Namespace) -> int:
    if args.config_dir is not None:
        if args.files:
            raise CliError("give device files or --config-dir, not both")
        from ..gateway import run_service

        return run_service(args.config_dir, args.gateway, seconds=args.seconds)
    if not args.files:
        raise CliError("give device files, or --config-dir DIR")
    drivers: list[tuple[Path, DriverModbusRtu]] = []
    try:
        for file in args.files:
            cfg = _load_file(file, "run")
            try:
                drv = _start(cfg.organization, cfg.communication, cfg.address_list, args.json)
            except (ValueError, OSError) as exc:  # e.g. a serial port opened with other settings
                raise CliError(*(_in_file(file, line) for line in problem_lines(exc))) from None
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


def _read(args: argparse.Namespace) -> int:
    _notice(args)
    drv, item = start_one_item(args)
    got = threading.Event()
    drv.address_updated_callback = lambda it: got.set()
    try:
        if not got.wait(args.timeout / 1000 * 4 + 5):
            raise CommandFailed(f"{item.address}: no answer")
    finally:
        drv.stop_device()
    if item.status is not ItemStatus.OK:
        raise CommandFailed(_with_hint(f"{item.address}: {item.error_reason}", args, drv))
    print(value_text(item.value))
    return OK


def _write(args: argparse.Namespace) -> int:
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


def _plan(args: argparse.Namespace) -> int:
    cfg = _load_file(args.file, "plan")
    params = cfg.effective_parameters()
    parsed = cfg.parsed_items()
    blocks = build_plan(parsed, params)
    notice = entity_numbers_notice(parsed, params)
    if notice is not None:
        print(f"edgemodbus plan: notice: {_in_file(args.file, notice)}", file=sys.stderr)
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
def _load_file(file: Path, command: str) -> DeviceConfig:
    """Load a device file; every problem (and every warning, e.g. an unknown key) is one
    line that names the file."""
    with _config_warnings(file, command):
        try:
            return load_device_config(file)
        except ConfigError as exc:
            raise CliError(*(_in_file(file, str(p)) for p in exc.problems)) from None
        except OSError as exc:
            raise CliError(f"{file}: {exc.strerror or exc}") from None
        except RecursionError:  # a backstop: config/ bounds the depth it reads
            raise CliError(f"{file}: JSON nested too deeply to read") from None


def _in_file(file: Path, message: str) -> str:
    message = one_line(message)
    return message if message.startswith(f"{file}:") else f"{file}: {message}"


@contextlib.contextmanager
def _config_warnings(file: Path, command: str) -> Iterator[None]:
    """Print what edgemodbus.config logs while ``file`` loads as ``edgemodbus CMD:
    warning: FILE: ...`` lines (the log line would not say which file)."""
    collector = _Collector(logging.WARNING)
    config_log = logging.getLogger("edgemodbus.config")
    propagate = config_log.propagate
    config_log.addHandler(collector)
    config_log.propagate = False
    try:
        yield
    finally:
        config_log.removeHandler(collector)
        config_log.propagate = propagate
        for record in collector.records:
            print(f"edgemodbus {command}: warning: {_in_file(file, record.getMessage())}",
                  file=sys.stderr)


class _Collector(logging.Handler):
    def __init__(self, level: int) -> None:
        super().__init__(level)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


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


def _wait(seconds: float) -> bool:
    """Wait ``seconds`` (0: forever) or until SIGTERM; True when Ctrl-C ended it."""
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
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
