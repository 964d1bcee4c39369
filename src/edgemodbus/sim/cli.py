"""``edgemodbus simulate``: serve simulated slaves from the command line until stopped."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence
from typing import Any

from ..logs import configure_logging
from .movers import add_demo_movers
from .server import Simulator
from .slave import DEFAULT_SIZE


def _parse_ids(text: str) -> list[int]:
    """'1,2,5-8' -> [1, 2, 5, 6, 7, 8]."""
    ids: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            lo, hi = (int(x) for x in part.split("-", 1))
            ids.extend(range(lo, hi + 1))
        else:
            ids.append(int(part))
    if not ids:
        raise argparse.ArgumentTypeError("no slave ids")
    return ids


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``edgemodbus simulate`` (also ``python -m edgemodbus.sim``)."""
    parser.add_argument("--host", default="127.0.0.1", help="listen address (127.0.0.1)")
    parser.add_argument("--port", type=int, default=5020, help="TCP port, 0 = any (5020)")
    parser.add_argument("--slaves", type=_parse_ids, default=[1], help="ids, e.g. 1,2,5-8")
    parser.add_argument("--size", type=int, default=DEFAULT_SIZE, help="points per area")
    parser.add_argument("--pty", action="store_true", help="also serve a pty")
    parser.add_argument("--no-tcp", action="store_true", help="do not listen on TCP")
    parser.add_argument("--movers", action="store_true", help="add the demo's moving values")
    parser.add_argument("--seed", type=int, default=None, help="seed of random faults")
    parser.add_argument("--dial", metavar="HOST:PORT", default=None,
                        help="DTU-client mode: connect to a master listening there "
                        "(rtu-over-tcp-server) instead of listening")
    parser.add_argument("--registration", default="",
                        help="with --dial: registration packet sent first (text)")
    parser.add_argument("--heartbeat", default="", help="with --dial: heartbeat packet (text)")
    parser.add_argument("--heartbeat-interval", type=float, default=0.0,
                        help="with --dial: seconds between heartbeats (0: none)")
    parser.add_argument("--wrapped", action="store_true",
                        help="speak the edge MCU's wrapped report frames")


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
    so that a script can read where to connect.
    """
    dial: tuple[str, int] | None = None
    if args.dial is not None:
        host, _, port_text = args.dial.rpartition(":")
        if not host or not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
            parser.error(f"--dial {args.dial!r}: use HOST:PORT with a port of 1..65535")
        dial = (host, int(port_text))

    stop = threading.Event()
    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, lambda *_: stop.set())
    try:
        with Simulator(args.slaves, args.size, seed=args.seed) as sim:
            if args.movers:
                for slave in sim.slaves:
                    add_demo_movers(slave)
            if dial is not None:
                sim.dial(dial[0], dial[1], registration=args.registration.encode(),
                         heartbeat=args.heartbeat.encode(),
                         heartbeat_interval=args.heartbeat_interval, wrapped=args.wrapped)
                print(f"dialled {dial[0]}:{dial[1]}", flush=True)
            elif not args.no_tcp:
                port = sim.serve_tcp(args.host, args.port, wrapped=args.wrapped)
                print(f"tcp {args.host}:{port}", flush=True)
            if args.pty:
                print(f"pty {sim.serve_pty()}", flush=True)
            ids = ",".join(str(s) for s in args.slaves)
            print(f"serving slaves {ids}; Ctrl-C to stop", file=sys.stderr, flush=True)
            while not stop.wait(1.0):
                pass
    except OSError as e:
        print(f"edgemodbus simulate: {e}", file=sys.stderr)
        return 1
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return 0

