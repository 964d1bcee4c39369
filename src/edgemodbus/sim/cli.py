"""``edgemodbus simulate``: serve simulated slaves from the command line until stopped."""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any

from ..logs import configure_logging
from ..protocol.hosts import check_host
from ..protocol.rtu import MAX_SLAVE_ID, parse_slave_ids
from .fleet import FLEET_SIZE, DtuFleet
from .movers import add_demo_movers
from .server import Simulator
from .slave import DEFAULT_SIZE


def slave_ids(text: str) -> list[int]:
    """``--slaves 1,2,5-8`` -> [1, 2, 5, 6, 7, 8]; a bad part is an ArgumentTypeError
    naming it and what is allowed (argparse prints it as one line)."""
    try:
        return parse_slave_ids(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _host(text: str) -> str:
    """A listen address by the one host rule (protocol/hosts.py); not empty (it listened
    on every interface, or with --no-tcp nowhere, without a word)."""
    try:
        if not text.strip():
            raise ValueError("empty (give an address, e.g. 127.0.0.1)")
        return check_host(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text[:60]!r}: {exc}") from None


def _number(low: float, high: float, *, whole: bool = False,
            above_low: bool = False) -> Callable[[str], float]:
    """An argparse type: a number in ``low..high`` (a whole one when ``whole``; NaN and
    infinities never), named with the range (``--heartbeat-interval -5`` was taken and
    ignored without --dial)."""
    what = "a whole number" if whole else "a number"
    bounds = f"more than {low:g} and at most {high:g}" if above_low else f"{low:g}..{high:g}"

    def parse(text: str) -> float:
        try:
            value = int(text) if whole else float(text)
        except ValueError:
            value = math.nan
        if not (low < value if above_low else low <= value) or not value <= high:
            raise argparse.ArgumentTypeError(f"{text[:60]!r}: not {what} in {bounds}")
        return value
    return parse


_DAY = 86400.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``edgemodbus simulate`` (also ``python -m edgemodbus.sim``)."""
    parser.add_argument("--host", type=_host, default="127.0.0.1",
                        help="listen address (127.0.0.1)")
    parser.add_argument("--port", type=int, default=5020, help="TCP port, 0 = any (5020)")
    parser.add_argument("--slaves", type=slave_ids, default=[1],
                        help=f"ids 1..{MAX_SLAVE_ID}, e.g. 1,2,5-8 (1)")
    parser.add_argument("--size", type=int, default=None,
                        help=f"points per area ({DEFAULT_SIZE}; with --dtus {FLEET_SIZE})")
    parser.add_argument("--pty", action="store_true", help="also serve a pty")
    parser.add_argument("--no-tcp", action="store_true", help="do not listen on TCP")
    parser.add_argument("--movers", action="store_true", help="add the demo's moving values")
    parser.add_argument("--seed", type=int, default=None, help="seed of random faults")
    parser.add_argument("--dial", metavar="HOST:PORT", default=None,
                        help="DTU-client mode: connect to a master listening there "
                        "(rtu-over-tcp-server) instead of listening")
    parser.add_argument("--registration", default=None,
                        help="with --dial: registration packet sent first (text); with --dtus "
                        "a template of the DTU's number {n} (DTU{n:05d})")
    parser.add_argument("--heartbeat", default="", help="with --dial: heartbeat packet (text)")
    parser.add_argument("--heartbeat-interval", type=_number(0, _DAY), default=0.0,
                        help="with --dial: seconds between heartbeats (0: none)")
    parser.add_argument("--wrapped", action="store_true",
                        help="speak the edge MCU's wrapped report frames")
    parser.add_argument("--dtus", type=_number(1, 1_000_000, whole=True), default=None,
                        metavar="N",
                        help="with --dial: play N DTUs from this one process (asyncio), each "
                        "with its own --slaves, registering as --registration")
    parser.add_argument("--first-dtu", type=_number(0, 10**12, whole=True), default=0,
                        metavar="N",
                        help="with --dtus: the number {n} of the first DTU (0)")
    parser.add_argument("--dial-rate", type=_number(0, 1e6), default=0.0,
                        help="with --dtus: new connections per second (0: no limit)")
    parser.add_argument("--reconnect", type=_number(0, _DAY, above_low=True), default=1.0,
                        help="with --dtus: seconds before a dropped DTU dials again, doubling "
                        "up to 30 while its connections end before any request (1)")


DESCRIPTION = "Multi-slave Modbus RTU simulator (raw RTU frames over TCP, or a pty)."


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m edgemodbus.sim``: the same as ``edgemodbus simulate``."""
    parser = argparse.ArgumentParser(prog="python -m edgemodbus.sim", description=DESCRIPTION)
    add_arguments(parser)
    parser.add_argument("-v", "--verbose", action="count", default=0, help="log more")
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    return run(args, parser)


def run(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """Serve slaves until SIGINT/SIGTERM.

    Prints one line per endpoint (``tcp HOST:PORT``, ``pty PATH``) on stdout, flushed,
    so that a script can read where to connect.  Exit codes (docs/command-line.md, "Exit codes"):
    0 after SIGTERM, 130 after SIGINT (Ctrl-C), 2 for a bad option, a port in use or a
    refused ``--dial`` (one line naming the option), 1 for another OSError (e.g. too few
    open files for ``--dtus``).
    """
    dial: tuple[str, int] | None = None
    if args.dial is not None:
        host, _, port_text = args.dial.rpartition(":")
        if not host or not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
            parser.error(f"--dial {args.dial!r}: use HOST:PORT with a port of 1..65535")
        dial = (host, int(port_text))
    if not 0 <= args.port <= 65535:
        parser.error(f"--port {args.port}: must be 0..65535 (0: any free port)")
    if args.size is not None and not 1 <= args.size <= 0x10000:
        parser.error(f"--size {args.size}: must be 1..65536 points per area")

    if args.dtus is not None and (dial is None or args.dtus < 1 or args.wrapped or args.pty):
        parser.error("--dtus N: needs --dial HOST:PORT and N >= 1; not with --wrapped or --pty")
    stop = threading.Event()
    interrupted = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        if signum == signal.SIGINT:
            interrupted.set()
        stop.set()

    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, on_signal)
    try:
        if args.dtus is not None:
            assert dial is not None
            _run_fleet(args, parser, dial, stop)
        else:
            _serve(args, dial, stop)
    except _OptionFailed as exc:
        print(f"edgemodbus simulate: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the machine's limits (open files): a runtime failure
        print(f"edgemodbus simulate: {exc}", file=sys.stderr)
        return 1
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return 130 if interrupted.is_set() else 0


class _OptionFailed(Exception):
    """What an option asked for failed (a port in use, a refused dial): one line."""


def _serve(args: argparse.Namespace, dial: tuple[str, int] | None,
           stop: threading.Event) -> None:
    size = DEFAULT_SIZE if args.size is None else args.size
    with Simulator(args.slaves, size, seed=args.seed) as sim:
        if args.movers:
            for slave in sim.slaves:
                add_demo_movers(slave)
        if dial is not None:
            try:
                sim.dial(dial[0], dial[1], registration=(args.registration or "").encode(),
                         heartbeat=args.heartbeat.encode(),
                         heartbeat_interval=args.heartbeat_interval, wrapped=args.wrapped)
            except OSError as exc:
                raise _OptionFailed(f"--dial {args.dial}: cannot connect: "
                                    f"{exc.strerror or exc}") from None
            print(f"dialled {dial[0]}:{dial[1]}", flush=True)
        elif not args.no_tcp:
            try:
                port = sim.serve_tcp(args.host, args.port, wrapped=args.wrapped)
            except OSError as exc:
                raise _OptionFailed(f"--host {args.host} --port {args.port}: cannot listen "
                                    f"on {args.host}:{args.port}: {exc.strerror or exc}"
                                    ) from None
            print(f"tcp {args.host}:{port}", flush=True)
        if args.pty:
            try:
                print(f"pty {sim.serve_pty()}", flush=True)
            except OSError as exc:
                raise _OptionFailed(f"--pty: {exc.strerror or exc}") from None
        ids = ",".join(str(s) for s in args.slaves)
        print(f"serving slaves {ids}; Ctrl-C to stop", file=sys.stderr, flush=True)
        while not stop.wait(1.0):
            pass


def _run_fleet(args: argparse.Namespace, parser: argparse.ArgumentParser,
               dial: tuple[str, int], stop: threading.Event) -> None:
    """``--dial HOST:PORT --dtus N``: a :class:`DtuFleet` until stopped; a status line on
    stderr every 5 s while it changes."""
    try:
        fleet = DtuFleet(dial[0], dial[1], args.dtus, first=args.first_dtu,
                         registration=args.registration or "DTU{n:05d}", slaves=args.slaves,
                         size=FLEET_SIZE if args.size is None else args.size,
                         heartbeat=args.heartbeat.encode(),
                         heartbeat_interval=args.heartbeat_interval, dial_rate=args.dial_rate,
                         reconnect=args.reconnect, reconnect_max=max(30.0, args.reconnect),
                         seed=args.seed)
    except ValueError as exc:
        parser.error(str(exc))
    if args.movers:
        for dtu in fleet.dtus:
            for slave in dtu.slaves.values():
                add_demo_movers(slave)
    first, last = (d.registration.decode(errors="backslashreplace")
                   for d in (fleet.dtus[0], fleet.dtus[-1]))
    with fleet:
        print(f"dialling {dial[0]}:{dial[1]} with {len(fleet)} DTUs ({first}..{last})",
              flush=True)
        shown = ""
        while not stop.wait(5.0):
            s = fleet.stats()
            line = (f"{s['connected']}/{s['dtus']} DTUs connected, {s['requests']} requests, "
                    f"{s['dial_failures']} failed dials, {s['reconnects']} reconnects")
            if line != shown:
                print(line, file=sys.stderr, flush=True)
                shown = line
