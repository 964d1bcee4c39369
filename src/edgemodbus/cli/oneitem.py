"""``read`` and ``write``'s one-item device (the polled way; their options are in
line_options.py, the one-shot read in oneshot.py) and what a failure adds to its message
(the framing hint).

``--host`` speaks Modbus TCP (MBAP), as mbpoll and most tools do; ``--rtu-over-tcp`` (or
``--transport rtu-over-tcp``) sends raw RTU frames over TCP instead (a serial server, a
DTU, ``edgemodbus simulate``).  A read that got no well-formed reply over TCP is tried once
more with the other framing (one read of the same address, nothing written): when that
answers, the error names the flag that fits.
"""

from __future__ import annotations

import argparse
import shlex
from collections.abc import Callable
from typing import Any

from ..config import ConfigError, DeviceAddressItem, DeviceConfig, load_device_config
from ..driver import DriverModbusRtu
from ..protocol.address import parse_address
from .line_options import (
    SERIAL_DEFAULTS,
    host_transport,
    other_framing_hint,
    serial_options_given,
)
from .output import CliError, one_line

__all__ = [
    "framing_hint",
    "one_item_config",
    "start_one_item",
]

#: The option (argparse dest) behind each field of the generated configuration, so that a
#: message names what the user typed (``--type Float: ...``).
_OPTION_OF_FIELD = {
    "communication.slaveId": "slave",
    "communication.readTimeout": "timeout",
    "communication.dataFormat": "format",
    "communication.byteSwap16": "byte_swap16",
    "communication.dataFormat64": "format64",
    "communication.tcpHost": "host",
    "communication.tcpPort": "port",
    "communication.comPort": "serial",
    "communication.baudRate": "baud",
    "communication.parity": "parity",
    "communication.dataBits": "data_bits",
    "communication.stopBits": "stop_bits",
    "addressList[0].address": "address",
    "addressList[0].deviceDataType": "type",
    "addressList[0].quantity": "quantity",
    "addressList[0].dataMultiplier": "multiplier",
}


def start_one_item(args: argparse.Namespace,
                   updated: Callable[[DeviceAddressItem], None] | None = None
                   ) -> tuple[DriverModbusRtu, DeviceAddressItem]:
    """A driver polling the one item ``args`` name (its config checked first: a problem
    is a CliError naming the option), ``updated`` its item callback from the start (a
    line already down tells the item at once, before start_device returns)."""
    cfg = one_item_config(args)
    drv = DriverModbusRtu()
    drv.address_updated_callback = updated
    drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    return drv, cfg.address_list[0]


def one_item_config(args: argparse.Namespace) -> DeviceConfig:
    """The checked device configuration of the one item ``args`` name (a problem is a
    CliError naming the option); sets ``args.type`` when it was left out."""
    comm: dict[str, Any] = {
        "slaveId": args.slave, "readTimeout": args.timeout, "readCycle": 1000,
        "dataFormat": args.format, "byteSwap16": args.byte_swap16, "retries": 0,
        "offlineAfterFailedCycles": 1000,
        "addressPrefix": args.address_prefix,
    }
    if args.format64 is not None:
        comm["dataFormat64"] = args.format64
    if serial_options_given(args):
        raise CliError(f"{serial_options_given(args)[0]}: applies to --serial (--host is "
                       "a TCP line)")
    if args.host:
        comm.update(transport=host_transport(args), tcpHost=args.host, tcpPort=args.port)
    elif args.transport is not None:
        raise CliError(f"--transport {args.transport}: applies to --host (a --serial line "
                       "speaks RTU)")
    else:
        serial = {dest: default if getattr(args, dest) is None else getattr(args, dest)
                  for dest, default in SERIAL_DEFAULTS.items()}
        comm.update(transport="rtu", comPort=args.serial, baudRate=serial["baud"],
                    parity=serial["parity"], dataBits=serial["data_bits"],
                    stopBits=serial["stop_bits"])
    if args.type is None:
        args.type = _default_type(args.address, args.address_prefix)
    item: dict[str, Any] = {"name": "value", "address": args.address,
                            "deviceDataType": args.type, "dataMultiplier": args.multiplier}
    if args.quantity is not None:
        item["quantity"] = args.quantity
    try:
        cfg: DeviceConfig = load_device_config({"communication": comm, "addressList": [item]})
    except ConfigError as exc:
        raise CliError(*(_option_problem(args, p.path, p.message) for p in exc.problems)) \
            from None
    return cfg


def framing_hint(args: argparse.Namespace, drv: DriverModbusRtu) -> str | None:
    """After a failed read or write over ``--host``: when the link was up but nothing
    well-formed came back, read the item's address once with the other framing; if that
    answers, the hint that names the flag (None otherwise, and for serial lines)."""
    if not args.host:
        return None
    stats = drv.stats()
    if stats.get("responses", 0) or stats.get("exceptions") or \
            not stats.get("line", {}).get("connects", 0):
        return None  # the framing was understood, or the link never came up
    return other_framing_hint(args)


def _default_type(address: str, prefix: str) -> str:
    """Boolean for a coil, a discrete input or a register bit (hr:7.3), else UInt16."""
    try:
        addr = parse_address(address, prefix)
    except ValueError:
        return "UInt16"  # the address itself is reported by the configuration check
    return "Boolean" if addr.area.is_bit or addr.bit is not None else "UInt16"


def _option_problem(args: argparse.Namespace, path: str, message: str) -> str:
    """A problem of the generated configuration, told as the option the user typed."""
    dest = _OPTION_OF_FIELD.get(path)
    if dest is None:
        return one_line(f"{path}: {message}")
    value = shlex.quote(str(getattr(args, dest)))
    if dest == "address":
        return one_line(f"{value}: {message}")
    return one_line(f"--{dest.replace('_', '-')} {value}: {message}")
