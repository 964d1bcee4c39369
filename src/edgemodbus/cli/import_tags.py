"""``edgemodbus import FILE.csv [-o device.json]``: a tag list exported from another tool
(Kepware's CSV export, or a generic ``name,address,type[,scanRate,scale]`` list, with the
engineering units columns of docs/engineering-units.md) as our device file
(docs/command-line.md, "Importing a tag list").

Every row that cannot be converted is one line on stderr (row, column, value, what is
allowed).  Exit code 0 when every row was converted; 1 when rows were refused, and then
nothing is written unless ``--partial`` (which writes the converted rows and exits 0).
"""

from __future__ import annotations

import argparse
import codecs
import sys

from ..codec import json_text
from ..commission.tag_import import import_tags
from ..config import ConfigError, load_device_config
from ..protocol.address import PREFIXES
from ..protocol.limits import MAX_UNIT_ID
from .arg_types import input_file, output_file
from .output import CliError, one_line

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=input_file, help="the CSV tag list")
    p.add_argument("-o", "--output", type=output_file, default=None,
                   help="the device file to write (default and -: stdout)")
    p.add_argument("--partial", action="store_true",
                   help="write the rows that converted even if others were refused (exit 0)")
    p.add_argument("--address-prefix", choices=PREFIXES, default="function-code",
                   help="how the generic form's addresses are read (Kepware's are entity "
                   "numbers)")
    p.add_argument("--slave", type=_slave_id, default=None,
                   help=f"slaveId of the device file (0..{MAX_UNIT_ID})")
    p.add_argument("--device-code", default=None, help="organization.deviceCode")
    p.add_argument("--encoding", type=_encoding, default="utf-8-sig",
                   help="the file's text encoding (utf-8-sig, cp1252, gbk, ...)")


def _slave_id(text: str) -> int:
    """A slaveId the device file can hold (config/ checks it against its transport)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_UNIT_ID:
        raise argparse.ArgumentTypeError(f"{text!r}: not a slave id (0..{MAX_UNIT_ID})")
    return value


def _encoding(text: str) -> str:
    """A text encoding Python knows (codecs.lookup), named as given."""
    try:
        codecs.lookup(text)
    except LookupError:
        raise argparse.ArgumentTypeError(f"{text!r}: not a known text encoding (e.g. "
                                         "utf-8-sig, cp1252, gbk)") from None
    return text


_OPTION_OF_FIELD = {"organization.deviceCode": "--device-code",
                    "communication.slaveId": "--slave"}


def _option_problem(text: str, path: str) -> str:
    """A problem of the device file made, told as the option that gave the field."""
    option = _OPTION_OF_FIELD.get(path)
    return one_line(text if option is None else f"{option}: {text}")


def run(args: argparse.Namespace) -> int:
    try:
        text = args.file.read_text(encoding=args.encoding)
    except (OSError, LookupError, UnicodeDecodeError) as exc:
        raise CliError(f"{args.file}: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        result = import_tags(text, args.address_prefix)
    except ValueError as exc:
        raise CliError(f"{args.file}: {exc}") from None
    for refusal in result.refused:
        print(f"edgemodbus import: {args.file}: {refusal}", file=sys.stderr)
    if result.notice is not None:
        more = (f" (and {result.entity_lookalikes - 1} more such rows)"
                if result.entity_lookalikes > 1 else "")
        print(f"edgemodbus import: notice: {args.file}: {result.notice}{more}; for Modicon "
              "numbering use --address-prefix entity", file=sys.stderr)
    comm = {} if args.slave is None else {"slaveId": args.slave}
    org = {} if args.device_code is None else {"deviceCode": args.device_code}
    device = result.device(comm, org)
    try:
        load_device_config(device)  # what we write must load
    except ConfigError as exc:
        raise CliError(*(_option_problem(str(p), p.path) for p in exc.problems)) from None
    print(f"edgemodbus import: {args.file}: {result.form} form, {len(result.items)} rows "
          f"converted, {len(result.refused)} refused", file=sys.stderr)
    if result.refused and not args.partial:
        print("edgemodbus import: nothing written (--partial writes the converted rows)",
              file=sys.stderr)
        return 1
    out = json_text(device, indent=True) + "\n"
    if args.output is None:
        sys.stdout.write(out)
    else:
        args.output.write_text(out, encoding="utf-8")
    return 0
