"""``edgemodbus scan``: find what answers on a line (edgemodbus.commission.scan).

Text output: a table of the devices found (setting, slave id, what answered) and one of
the settings tried (probes, replies, garbage, timeouts, early stop), on stdout; a
progress bar on stderr when stderr is a terminal.  ``--json``: one JSON document on
stdout instead (see JSON_HELP).  Ctrl-C stops the scan (the line is closed), prints
what was found so far and exits with 130.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..commission.scan import (
    DEFAULT_GARBAGE_LIMIT,
    DEFAULT_PROBES,
    Found,
    Progress,
    ScanEndpoint,
    ScanEvent,
    SettingDone,
    SettingStarted,
    scan_line,
    serial_settings,
    setting_text,
)
from ..errors import ModbusConnectionError
from ..line.endpoint import SerialPort, TcpEndpoint
from ..protocol.rtu import MAX_SLAVE_ID, parse_slave_ids
from .arg_types import host_name, serial_device
from .line_options import add_transport_options
from .output import CliError, print_json

DEFAULT_BAUDS = "9600,19200,38400,57600,115200"
TRANSPORTS = ("tcp", "rtu-over-tcp")
RS485_MODES = ("none", "kernel", "rts-up", "rts-down")

JSON_HELP = (
    "one JSON document on stdout instead of the tables: {\"line\", \"complete\" (false when "
    "interrupted or the line failed), \"interrupted\", \"error\" (text or null), \"slaveIds\" "
    "(count), \"settings\": [{\"setting\", \"transport\", \"baudrate\", \"parity\", "
    "\"dataBits\", \"stopBits\" (null on TCP), \"probes\", \"replies\", \"garbage\", "
    "\"timeouts\", \"closed\", \"idsProbed\", \"stoppedEarly\" (reason or null)}], \"found\": "
    "[{\"setting\", \"transport\", \"baudrate\", \"parity\", \"dataBits\", \"stopBits\", "
    "\"slaveId\", \"answers\": [{\"function\", \"result\": ok|exception|timeout|garbage|"
    "closed, \"exceptionCode\", \"exception\" (exceptions only), \"detail\" (garbage, "
    "closed)}]}]}"
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--serial", type=serial_device, metavar="DEVICE",
                       help="serial port, e.g. /dev/ttyUSB0")
    where.add_argument("--host", type=host_name, help="TCP host (with --port)")
    p.add_argument("--port", type=int, default=502, help="TCP port (502)")
    add_transport_options(p, several=True)
    p.add_argument("--baud", default=DEFAULT_BAUDS,
                   help=f"baud rates to try, in order ({DEFAULT_BAUDS})")
    p.add_argument("--parity", default="N,E,O", help="parities to try: N, E, O (N,E,O)")
    p.add_argument("--stop-bits", default="1", help="stop bits to try: 1, 2 or 1,2 (1)")
    p.add_argument("--rs485", default="none", help=f"RS-485 mode: {', '.join(RS485_MODES)}")
    p.add_argument("--echo", action="store_true",
                   help="the adapter echoes requests (2-wire, no echo suppression)")
    p.add_argument("--slaves", default=None, metavar="IDS",
                   help=f"slave ids: numbers and ranges, e.g. 1-10,17,100-110 (1-{MAX_SLAVE_ID}"
                   "; 0..255 with --transport tcp)")
    p.add_argument("--ids", default=None, help="the same as --slaves")
    p.add_argument("--functions", default=",".join(map(str, DEFAULT_PROBES)),
                   help="read functions to probe with, in order (3,4,1: FC04 and FC01 only "
                   "after an exception reply)")
    p.add_argument("--timeout", default=None, metavar="MS",
                   help="per probe, in ms (100 at 9600 baud and above, scaled up below it; "
                   "500 on TCP)")
    p.add_argument("--garbage-limit", default=str(DEFAULT_GARBAGE_LIMIT), metavar="N",
                   help="skip the rest of a setting after N garbled replies and no "
                   f"well-formed one ({DEFAULT_GARBAGE_LIMIT}; 0: never)")
    p.add_argument("--interval", default="0", metavar="MS",
                   help="extra silence between requests, in ms (0)")
    p.add_argument("--json", action="store_true", help=JSON_HELP)
    p.set_defaults(func=run)


# -- options -------------------------------------------------------------------------
def _ints(option: str, text: str, allowed: str) -> list[int]:
    try:
        values = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise CliError(f"{option} {text!r}: not a comma-separated list of numbers "
                       f"(allowed: {allowed})") from None
    if not values:
        raise CliError(f"{option} {text!r}: empty (allowed: {allowed})")
    return values


def parse_ids(option: str, text: str, low: int = 1, high: int = MAX_SLAVE_ID) -> list[int]:
    """"1-10,17" -> [1..10, 17]; a bad part raises CliError naming ``option``."""
    try:
        return parse_slave_ids(text, low, high)
    except ValueError as exc:
        raise CliError(f"{option} {exc}") from None


def _ms(option: str, text: str | None, low: float, high: float) -> float | None:
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        raise CliError(f"{option} {text!r}: not a number of milliseconds "
                       f"(allowed: {low:g}..{high:g})") from None
    if not low <= value <= high:
        raise CliError(f"{option} {text!r}: must be {low:g}..{high:g} ms")
    return value / 1000


def endpoints_of(args: argparse.Namespace) -> list[ScanEndpoint]:
    """The settings to sweep, from the options; CliError names a bad one.  Every option is
    checked, also the serial ones of a TCP scan (``--host H --baud abc`` scanned and
    failed to connect, exit code 1, with the bad option never named)."""
    bauds = _ints("--baud", args.baud, "e.g. 9600,19200")
    for baud in bauds:
        if not 50 <= baud <= 4_000_000:
            raise CliError(f"--baud {args.baud!r}: {baud} is not a baud rate (50..4000000)")
    parities = [p.strip().upper() for p in args.parity.split(",") if p.strip()]
    bad_parity = [p for p in parities if p not in ("N", "E", "O")] or ([] if parities else [""])
    if bad_parity:
        raise CliError(f"--parity {args.parity!r}: {bad_parity[0]!r} is not N, E or O "
                       "(a comma-separated list)")
    stops = _ints("--stop-bits", args.stop_bits, "1, 2 or 1,2")
    if any(s not in (1, 2) for s in stops):
        raise CliError(f"--stop-bits {args.stop_bits!r}: must be 1, 2 or 1,2")
    if args.rs485 not in RS485_MODES:
        raise CliError(f"--rs485 {args.rs485!r}: must be one of {', '.join(RS485_MODES)}")
    transports = [t.strip() for t in args.transport.split(",") if t.strip()]
    bad = [t for t in transports if t not in TRANSPORTS] or ([] if transports else [""])
    if bad:
        raise CliError(f"--transport {args.transport!r}: {bad[0]!r} is not one of "
                       f"{', '.join(TRANSPORTS)} (a comma-separated list)")
    if not 1 <= args.port <= 65535:
        raise CliError(f"--port {args.port}: must be 1..65535")
    if args.host is not None:
        return [TcpEndpoint(args.host, args.port, t) for t in dict.fromkeys(transports)]
    return list(serial_settings(args.serial, bauds, parities, stops, rs485=args.rs485,
                                echo=args.echo))


# -- the report ------------------------------------------------------------------------
@dataclass
class Report:
    """What the scan found and did so far."""

    line: str
    slave_ids: int
    found: list[Found] = field(default_factory=list)
    settings: list[SettingDone] = field(default_factory=list)
    interrupted: bool = False
    error: str | None = None

    def take(self, event: ScanEvent) -> None:
        if isinstance(event, Found):
            self.found.append(event)
        elif isinstance(event, SettingDone):
            self.settings.append(event)

    def as_json(self) -> dict[str, Any]:
        return {
            "line": self.line,
            "complete": not self.interrupted and self.error is None,
            "interrupted": self.interrupted,
            "error": self.error,
            "slaveIds": self.slave_ids,
            "settings": [{**_setting_json(s.endpoint), "probes": s.probes,
                          "replies": s.replies, "garbage": s.garbage, "timeouts": s.timeouts,
                          "closed": s.closed, "idsProbed": s.ids_probed,
                          "stoppedEarly": s.stopped_early}
                         for s in self.settings],
            "found": [{**_setting_json(f.endpoint), "slaveId": f.slave_id,
                       "answers": [a.as_dict() for a in f.answers]} for f in self.found],
        }

    def text_lines(self) -> list[str]:
        state = " (interrupted)" if self.interrupted else (" (failed)" if self.error else "")
        out = [f"scan of {self.line}: {self.slave_ids} slave id(s) per setting{state}", ""]
        rows: list[tuple[str, ...]]
        if self.found:
            rows = [("setting", "slave", "answered")]
            rows += [(setting_text(f.endpoint), str(f.slave_id), f.summary) for f in self.found]
            out += _table(rows, right={1})
        else:
            out.append("nothing answered")
        out.append("")
        rows = [("setting", "ids", "probes", "replies", "garbage", "timeouts", "note")]
        for s in self.settings:
            notes = [f"stopped early: {s.stopped_early}"] if s.stopped_early else []
            if s.closed:
                notes.append(f"the peer closed the connection {s.closed} time(s)")
            note = "; ".join(notes)
            rows.append((setting_text(s.endpoint), str(s.ids_probed), str(s.probes),
                         str(s.replies), str(s.garbage), str(s.timeouts), note))
        out += _table(rows, right={1, 2, 3, 4, 5})
        return out


def _setting_json(ep: ScanEndpoint) -> dict[str, Any]:
    return {
        "setting": setting_text(ep),
        "transport": ep.transport if isinstance(ep, TcpEndpoint) else "rtu",
        "baudrate": ep.baudrate if isinstance(ep, SerialPort) else None,
        "parity": ep.parity if isinstance(ep, SerialPort) else None,
        "dataBits": ep.data_bits if isinstance(ep, SerialPort) else None,
        "stopBits": ep.stop_bits if isinstance(ep, SerialPort) else None,
    }


def _table(rows: Sequence[tuple[str, ...]], right: set[int]) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return [
        "  ".join(cell.rjust(widths[i]) if i in right else cell.ljust(widths[i])
                  for i, cell in enumerate(row)).rstrip()
        for row in rows
    ]


# -- the command -----------------------------------------------------------------------
def run(args: argparse.Namespace) -> int:
    endpoints = endpoints_of(args)
    tcp_unit = args.host is not None and all(
        isinstance(e, TcpEndpoint) and e.transport == "tcp" for e in endpoints)
    if args.slaves is not None and args.ids is not None:
        raise CliError(f"--slaves {args.slaves!r} and --ids {args.ids!r}: give one (--ids is "
                       "the old name of --slaves)")
    option, text = ("--ids", args.ids) if args.ids is not None else (
        "--slaves", f"1-{MAX_SLAVE_ID}" if args.slaves is None else args.slaves)
    ids = parse_ids(option, text, 0 if tcp_unit else 1, 255 if tcp_unit else MAX_SLAVE_ID)
    functions = _ints("--functions", args.functions, "1, 2, 3, 4, e.g. 3,4,1")
    if any(fc not in (1, 2, 3, 4) for fc in functions):
        raise CliError(f"--functions {args.functions!r}: a probe reads with 1, 2, 3 or 4")
    timeout = _ms("--timeout", args.timeout, 1, 60_000)
    interval = _ms("--interval", args.interval, 0, 10_000) or 0.0
    limit = _ints("--garbage-limit", args.garbage_limit, "0 or more")
    if len(limit) != 1 or limit[0] < 0:
        raise CliError(f"--garbage-limit {args.garbage_limit!r}: one number, 0 or more")
    line = args.serial if args.serial is not None else f"{args.host}:{args.port}"
    report = Report(line, len(ids))
    events = scan_line(endpoints, ids, functions=functions, timeout=timeout,
                       garbage_limit=limit[0], request_interval=interval)
    try:
        with _progress(sys.stderr.isatty()) as show:
            for event in events:
                report.take(event)
                show(event)
    except KeyboardInterrupt:
        report.interrupted = True
    except ModbusConnectionError as exc:
        report.error = str(exc)
    finally:
        events.close()  # closes the line if the scan stopped between two events
    if args.json:
        print_json(report.as_json())
    else:
        sys.stdout.write("\n".join(report.text_lines()) + "\n")
    sys.stdout.flush()
    if report.error is not None:
        print(f"edgemodbus scan: {report.error}", file=sys.stderr)
        return 1
    hint = _other_framing_hint(endpoints, report)
    if hint is not None:
        print(f"edgemodbus scan: {hint}", file=sys.stderr)
    return 130 if report.interrupted else 0


_OTHER_FRAMING = {
    "tcp": "nothing answered Modbus TCP; a serial server or a DTU speaks raw RTU frames: "
           "scan with --transport tcp,rtu-over-tcp",
    "rtu-over-tcp": "nothing answered raw RTU frames over TCP; a Modbus TCP device speaks "
                    "MBAP: scan with --transport tcp,rtu-over-tcp",
}


def _other_framing_hint(endpoints: Sequence[ScanEndpoint], report: Report) -> str | None:
    """After a complete TCP scan of one framing that found nothing, the flag of the other
    (the line layer's framing hint of read and write, for a whole scan: one probe in the
    other framing would not tell an empty id from the wrong framing)."""
    transports = {e.transport for e in endpoints if isinstance(e, TcpEndpoint)}
    if report.found or report.interrupted or len(transports) != 1 or \
            len(endpoints) != len(transports):
        return None
    return _OTHER_FRAMING.get(transports.pop())


@contextlib.contextmanager
def _progress(on: bool) -> Iterator[Any]:
    """A function taking each scan event: a rich progress bar on stderr, or nothing."""
    if not on:
        yield lambda event: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn
    from rich.progress import Progress as Bar

    with Bar(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("found {task.fields[found]}"),
                  console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("scan", total=None, found=0)
        found = 0

        def show(event: ScanEvent) -> None:
            nonlocal found
            if isinstance(event, SettingStarted):
                bar.update(task, description=f"{setting_text(event.endpoint)} "
                           f"({event.index + 1}/{event.count})")
            elif isinstance(event, Found):
                found += 1
                bar.update(task, found=found)
                bar.console.print(f"{setting_text(event.endpoint)}  slave {event.slave_id}: "
                                  f"{event.summary}", markup=False, highlight=False)
            elif isinstance(event, Progress):
                bar.update(task, completed=event.done, total=event.total)

        yield show
