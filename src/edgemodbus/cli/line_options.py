"""``read`` and ``write``'s options (the line, the item, the address prefix) and what
needs no device file to say about them (the entity-number notice): nothing here imports
the config models, so the one-shot read (oneshot.py) starts without pydantic."""

from __future__ import annotations

import argparse

from ..protocol.address import PREFIXES, entity_lookalike, entity_notice, parse_address
from .arg_types import host_name, serial_device, word

__all__ = [
    "HOST_TRANSPORTS",
    "SERIAL_DEFAULTS",
    "add_line_options",
    "add_transport_options",
    "entity_notice_line",
    "host_transport",
    "other_framing_hint",
    "serial_options_given",
]

HOST_TRANSPORTS = ("tcp", "rtu-over-tcp")
_OTHER = {"tcp": "rtu-over-tcp", "rtu-over-tcp": "tcp"}
_HINT = {
    "rtu-over-tcp": "the device answered raw RTU frames over TCP (a serial server, a DTU, "
                    "edgemodbus simulate): add --rtu-over-tcp",
    "tcp": "the device answered Modbus TCP: leave out --rtu-over-tcp (--host speaks Modbus "
           "TCP)",
}


def add_transport_options(p: argparse.ArgumentParser, *, several: bool = False) -> None:
    """``--transport`` and its short form ``--rtu-over-tcp`` (one dest)."""
    if several:
        p.add_argument("--transport", default="tcp",
                       help="with --host: tcp (Modbus TCP, the default), rtu-over-tcp (raw "
                       "RTU frames: a serial server, a DTU), or both: tcp,rtu-over-tcp")
    else:
        p.add_argument("--transport", choices=HOST_TRANSPORTS, default=None,
                       help="with --host: tcp (Modbus TCP, the default) or rtu-over-tcp "
                       "(raw RTU frames over TCP: a serial server, a DTU, edgemodbus "
                       "simulate)")
    p.add_argument("--rtu-over-tcp", dest="transport", action="store_const",
                   const="rtu-over-tcp", help="the same as --transport rtu-over-tcp")


def add_line_options(p: argparse.ArgumentParser) -> None:
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--host", type=host_name, help="TCP host (with --port): Modbus TCP unless "
                       "--rtu-over-tcp")
    where.add_argument("--serial", type=serial_device, metavar="DEVICE",
                       help="serial port, e.g. /dev/ttyUSB0")
    p.add_argument("--port", type=int, default=502, help="TCP port (502)")
    add_transport_options(p)
    p.add_argument("--baud", type=int, default=None, help="with --serial (9600)")
    p.add_argument("--parity", type=word, default=None, help="with --serial: N, E or O (N)")
    p.add_argument("--data-bits", type=int, default=None, help="with --serial (8)")
    p.add_argument("--stop-bits", type=int, default=None, help="with --serial (1)")
    p.add_argument("--slave", type=int, default=1, help="slave / unit id (1)")
    p.add_argument("--type", type=word, default=None,
                   help="data type (Boolean for coils, discrete inputs and register bits such "
                   "as hr:7.3, else UInt16)")
    p.add_argument("--format", type=word, default="ABCD", help="byte and word order of "
                   "values of 2 or more registers: ABCD, BADC, CDAB or DCBA")
    p.add_argument("--byte-swap16", action="store_true",
                   help="swap the two bytes of a one-register value (and of a bit's register)")
    p.add_argument("--format64", type=word, default=None, help="order of 64-bit values (ABCDEFGH, "
                   "EFGHABCD = first DWord low, ...); default: what --format means for them")
    p.add_argument("--quantity", type=int, default=None, help="registers (String/Binary)")
    p.add_argument("--multiplier", type=float, default=1.0)
    p.add_argument("--timeout", type=int, default=1000, help="response timeout in ms (1000)")
    p.add_argument("--address-prefix", choices=PREFIXES, default="function-code",
                   help="how a bare number reads: function-code (40001 = holding register "
                   "40001, the default), modicon, or entity (40001 = holding register 0)")


SERIAL_DEFAULTS = {"baud": 9600, "parity": "N", "data_bits": 8, "stop_bits": 1}
"""The serial options (dest: default), given only with --serial."""


def serial_options_given(args: argparse.Namespace) -> list[str]:
    """The serial options given on a --host line, as ``--baud 9600`` (they were ignored,
    and a bad value went unnoticed: exit code 1 for the refused connection instead of 2)."""
    if not args.host:
        return []
    return [f"--{dest.replace('_', '-')} {getattr(args, dest)}" for dest in SERIAL_DEFAULTS
            if getattr(args, dest) is not None]


def host_transport(args: argparse.Namespace) -> str:
    """The framing ``--host`` uses: Modbus TCP unless told otherwise."""
    return str(args.transport or "tcp")


def entity_notice_line(args: argparse.Namespace) -> str | None:
    """The notice for an address that looks like a Modicon entity number (40001) but is
    read as an offset, with the option that switches; None otherwise."""
    entity = entity_lookalike(args.address, args.address_prefix)
    if entity is None:
        return None
    read_as = parse_address(args.address.strip(), args.address_prefix)
    return (f"notice: {entity_notice(args.address.strip(), read_as, entity)}; for Modicon "
            "numbering use --address-prefix entity")


def other_framing_hint(args: argparse.Namespace) -> str | None:
    """After a read or write over ``--host`` whose link was up but got nothing
    well-formed back: read the item's address once with the other framing; if that
    answers, the hint that names the flag (None otherwise)."""
    from ..commission.scan import SettingDone, scan_line  # only after a failure
    from ..errors import ModbusConnectionError
    from ..line.endpoint import TcpEndpoint

    other = _OTHER[host_transport(args)]
    try:
        addr = parse_address(args.address.strip(), args.address_prefix)
        events = scan_line([TcpEndpoint(args.host, args.port, other)], [args.slave],
                           functions=[addr.area.read_function], address=addr.offset,
                           timeout=min(max(args.timeout, 50), 2000) / 1000,
                           garbage_limit=0)
        done = [e for e in events if isinstance(e, SettingDone)]
    except (ValueError, ModbusConnectionError):
        return None  # e.g. a unit id only Modbus TCP has: no other framing to try
    return _HINT[other] if done and done[0].replies else None
