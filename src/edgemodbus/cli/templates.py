"""``edgemodbus templates [NAME]``: list the device templates on the search path (name,
description, source document, file), or print one template's items (docs/device-files.md, "Device
templates").

The search path: ``--dir`` folders, then ``$EDGEMODBUS_TEMPLATE_PATH``, then the
templates shipped with the package.  A device file uses one with ``"template": NAME``.
"""

from __future__ import annotations

import argparse
from typing import Any

from ..config import ConfigError
from ..config.templates import TemplateInfo, find_templates, load_template, template_file
from .arg_types import folder
from .output import CliError, one_line, print_json

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", nargs="?", help="a template to show (none: list them)")
    p.add_argument("--dir", action="append", default=[], type=folder, metavar="DIR",
                   help="a folder searched first (repeatable)")
    p.add_argument("--json", action="store_true", help="JSON instead of text")


def source_text(source: dict[str, Any]) -> str:
    """``vendor, document, version`` of a template's source, as one line."""
    return ", ".join(str(source[k]) for k in ("vendor", "document", "version") if source.get(k))


def _listing(templates: list[TemplateInfo]) -> list[str]:
    lines = []
    for t in templates:
        lines += [f"{t.name}: {t.description}", f"  source: {source_text(t.source)}",
                  f"  file: {t.file}"]
    return lines or ["no templates on the search path"]


def _items(doc: dict[str, Any]) -> list[str]:
    defaults = doc.get("itemDefaults", {})
    lines = []
    for item in doc.get("addressList", []):
        item = {**defaults, **item}
        unit = f" [{item['unit']}]" if item.get("unit") else ""
        lines.append(f"  {item.get('name')}: {item.get('address')} "
                     f"{item.get('deviceDataType', '')}{unit}")
    return lines


def run(args: argparse.Namespace) -> int:
    dirs = [str(d) for d in args.dir]
    try:
        if args.name is None:
            templates = find_templates(dirs)
            if args.json:
                return print_json([{**t.summary(), "file": str(t.file)} for t in templates])
            print("\n".join(_listing(templates)))
            return 0
        file = template_file(args.name, dirs)
        doc = load_template(args.name, dirs)
    except ConfigError as exc:
        raise CliError(*(one_line(str(p)) for p in exc.problems)) from None
    if args.json:
        return print_json(doc)
    prefix = doc.get("communication", {}).get("addressPrefix", "function-code")
    print("\n".join([f"{args.name}: {doc.get('description', '')}",
                     f"  source: {source_text(doc.get('source', {}))}", f"  file: {file}",
                     f"  addresses written with addressPrefix {prefix}",
                     *_items(doc)]))
    return 0
