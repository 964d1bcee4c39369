"""``edgemodbus read`` in one shot (docs/benchmarks.md "Start-up of the command
line"): over ``--host``, one request on a libmodbus context of its own (``_ffi``), decoded
with the codec's BlockDecoder, without the config models, pydantic, the driver or the
line worker, which cost ~110 ms of start-up before the 6-8 ms the read itself takes.

It takes the options it can check with the layers below the config models (the
address with protocol/address.py, the host with protocol/hosts.py, the slave id with
protocol/limits.py, the value spec with codec/spec.py's check_spec), and only values
that the device-file check accepts too (tests/unit/cli/test_oneshot.py compares both
over a set of options).  Everything else goes the polled way (polling.read: a one-item
device, config/ checks it): a serial line, --quantity, --format64, -v (the line's log,
-vv its frame trace), an option value it does not take, and every failure (a refused
connection, no or a bad reply, a value the codec refuses), which the polled read then
repeats, so its messages, the framing hint and the exit codes stay those of the
device's own path; but for a slave that did not answer at all (the most common failure:
the wrong framing, slave id or address), which is told in the polled read's words here
(tests/unit/cli/test_oneshot.py compares the two) rather than waited for twice.
"""

from __future__ import annotations

import argparse
import math
import socket
import sys

from .._ffi import Context
from ..codec import BlockDecoder, ValueSpec, check_spec
from ..datatypes import DataFormat, DataType
from ..errors import ModbusError, ModbusTimeoutError
from ..protocol.address import Address, parse_address
from ..protocol.hosts import check_host
from ..protocol.limits import MAX_ADDRESS, slave_id_problem
from .exits import OK, CommandFailed
from .line_options import (
    entity_notice_line,
    host_transport,
    other_framing_hint,
    serial_options_given,
)
from .output import value_text

__all__ = ["one_shot_item", "read", "read_once"]

CONNECT_TIMEOUT_S = 3.0
"""The connect timeout of a device file's default (communication.connectTimeout)."""
BYTE_TIMEOUT_S = 0.2
"""The timeout between two bytes of a reply, the device file's default (byteTimeout)."""
MAX_TIMEOUT_MS = 60_000
"""The longest --timeout the one-shot read takes (device files allow a day; longer
ones go the polled way, which checks them)."""


def read(args: argparse.Namespace) -> int:
    """``edgemodbus read``: the one-shot read when it can, else (and after any failure)
    the polled one."""
    notice = entity_notice_line(args)
    if notice is not None:
        print(f"edgemodbus {args.command}: {notice}", file=sys.stderr)
    value = read_once(args)
    if value is not None:
        print(value_text(value[0]))
        return OK
    from .polling import read as polled_read  # the config models, the driver

    return polled_read(args, notice=False)


def one_shot_item(args: argparse.Namespace) -> tuple[Address, ValueSpec] | None:
    """The address and value spec of the options, or None when the one-shot read does
    not take them (they go the polled way, which checks them and names the option)."""
    if not args.host or args.quantity is not None or args.format64 is not None:
        return None
    if serial_options_given(args):
        return None  # refused the polled way, naming the option
    if args.verbose:
        return None  # -v logs the line's life, -vv traces its frames: the polled way's
    if not args.host.strip():
        return None  # "a host is required"
    if not (1 <= args.port <= 65535 and 1 <= args.timeout <= MAX_TIMEOUT_MS):
        return None
    if slave_id_problem(args.slave, host_transport(args)) is not None:
        return None
    if not math.isfinite(args.multiplier) or args.multiplier == 0:
        return None
    if args.format not in {f.value for f in DataFormat}:
        return None
    try:
        check_host(args.host)
        addr = parse_address(args.address, args.address_prefix)
        bit_item = addr.area.is_bit or addr.bit is not None
        if args.type is None:
            data_type = DataType.BOOLEAN if bit_item else DataType.UINT16
        else:
            data_type = DataType.parse(args.type)
        if bit_item != (data_type is DataType.BOOLEAN):
            return None
        spec = ValueSpec(name="value", data_type=data_type,
                         data_format=DataFormat(args.format), byte_swap16=args.byte_swap16,
                         bit=addr.bit, multiplier=float(args.multiplier))
        check_spec(spec, addr.area)
    except ValueError:
        return None
    count = 1 if addr.area.is_bit else spec.registers
    if count < 1 or addr.offset + count - 1 > MAX_ADDRESS:
        return None
    return addr, spec


def read_once(args: argparse.Namespace) -> tuple[object] | None:
    """The value of one request (a 1-tuple: a value may be None), or None when the
    options are not the one-shot read's or anything else failed.  A slave that did not
    answer at all is CommandFailed, worded as the polled read words it (and with its
    framing hint), so that the user does not wait for a second timeout."""
    item = one_shot_item(args)
    if item is None:
        return None
    addr, spec = item
    count = 1 if addr.area.is_bit else spec.registers
    transport = host_transport(args)
    try:
        sock = socket.create_connection((args.host, args.port), timeout=CONNECT_TIMEOUT_S)
    except (OSError, UnicodeError):
        return None
    try:
        sock.settimeout(None)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        ctx = Context.on_socket(sock.fileno(), f"{transport}://{args.host}:{args.port}",
                                mbap=transport == "tcp")
        try:
            ctx.set_timeouts(args.timeout / 1000, BYTE_TIMEOUT_S)
            try:
                block = ctx.read(args.slave, addr.area.read_function, addr.offset, count)
            except ModbusTimeoutError as exc:
                if type(exc) is not ModbusTimeoutError:
                    raise  # a garbled or cut reply: the polled way words it
                raise CommandFailed(_silent(args, exc)) from None
            decoder = BlockDecoder(addr.area, count, [(0, spec)])
            values = decoder.decode_values(block)
            if decoder.errors():
                return None
            return (values[0],)
        finally:
            ctx.close()
    except (ModbusError, ValueError):
        return None
    finally:
        sock.close()


def _silent(args: argparse.Namespace, exc: ModbusTimeoutError) -> str:
    """The polled read's message for a slave that did not answer (its item's reason,
    poll/faults.py reason_of; the hint of cli/oneitem.py framing_hint: the link was up
    and nothing came back)."""
    message = f"{args.address}: device not responding: {exc}"
    hint = other_framing_hint(args)
    return message if hint is None else f"{message}; {hint}"
