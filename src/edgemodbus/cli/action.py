"""``edgemodbus action FILE [NAME [param=value ...]]``: run an action of a device file
(docs/device-files.md, "Actions"); without NAME, list the file's actions and their parameters.

Values are text and are read by the parameter's type (``12.5``, ``true``, ``"text"``);
everything is checked before a request is sent.  Prints ``ok`` once the slave confirmed
every request of the action; a failure is one line naming the action: exit code 2 for a
bad file, name or parameter (nothing sent), 1 when the slave did not confirm.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..config import ConfigError, DeviceConfig, load_device_config
from ..driver import DriverModbusRtu
from ..poll.actions import describe_parameter
from .arg_types import path_text
from .exits import CommandFailed
from .output import CliError, one_line

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=path_text, help="the device file (with its \"actions\")")
    p.add_argument("name", nargs="?", help="the action to run (none: list the actions)")
    p.add_argument("params", nargs="*", metavar="param=value",
                   help="parameter values; a parameter left out takes its default")


def parse_params(texts: list[str]) -> dict[str, Any]:
    """``["speed=12.5", "mode=auto"]`` -> ``{"speed": "12.5", "mode": "auto"}``."""
    params: dict[str, Any] = {}
    for text in texts:
        name, sep, value = text.partition("=")
        if not sep or not name.strip():
            raise CliError(f"{text!r}: give parameters as name=value (e.g. speed=12.5)")
        if name.strip() in params:
            raise CliError(f"{name.strip()!r}: given twice")
        params[name.strip()] = value
    return params


def _load(file: Path) -> DeviceConfig:
    try:
        return load_device_config(file)
    except ConfigError as exc:
        raise CliError(*(one_line(f"{file}: {p}") for p in exc.problems)) from None
    except OSError as exc:
        raise CliError(f"{file}: {exc.strerror or exc}") from None


def _listing(cfg: DeviceConfig) -> list[str]:
    lines = []
    for action in cfg.actions:
        lines.append(f"{action.name}: functionCode {action.function_code}"
                     + (f" ({action.description})" if action.description else ""))
        lines += [f"  {describe_parameter(action, p.name)}" for p in action.parameters]
    return lines or ["no actions in this file"]


def run(args: argparse.Namespace) -> int:
    cfg = _load(args.file)
    if args.name is None:
        if args.params:
            raise CliError("give the action's name before its parameters")
        print("\n".join(_listing(cfg)))
        return 0
    params = parse_params(args.params)
    drv = DriverModbusRtu()
    try:
        if not drv.start_device(cfg.organization, cfg.communication, cfg.address_list,
                                cfg.actions):
            raise CliError(f"{args.file}: device is disabled (isEnable false)")
        ok, err = drv.run_action(args.name, params)
    except ConfigError as exc:
        raise CliError(*(one_line(f"{args.file}: {p}") for p in exc.problems)) from None
    finally:
        drv.stop_device()
    if not ok:
        if drv.stats().get("writes", 0) or drv.stats().get("writeErrors", 0):
            raise CommandFailed(str(err))
        raise CliError(str(err))
    print("ok")
    return 0
