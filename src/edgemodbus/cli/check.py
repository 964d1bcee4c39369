"""``edgemodbus check PATH ...``: check device files, a gateway file or a whole config
folder before they go on a gateway, the way the gateway would load them (docs/cli.md,
"check"); nothing connects and no port is opened.

A device file is loaded with its template applied, its items parsed against its
communication options and its read plan built; a gateway file (``gateway.json``, or any
file given with ``--gateway``) is loaded with its TLS, Sparkplug and spool paths checked;
a folder is its gateway file and every device file the gateway would start (its
``devicePattern``), and then two devices with one deviceCode and a ``serve`` unit that
names no device are problems too, as is a folder with neither; a name the pattern matches
that the gateway skips (a FIFO, a folder, a broken link, a symlink loop) is a warning.

Each problem is one line on stdout, ``PATH: field value: what is allowed``, and the exit
code is 2 when there is any; warnings (an unknown key) are ``PATH: warning: ...`` and
notices (``40001`` without ``addressPrefix: entity``, read as holding register 40001) are
``PATH: notice: ...``; neither fails.  With no problem the last line sums up what was
checked, exit code 0.
"""

from __future__ import annotations

import argparse
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

from ..config import ConfigError, DeviceConfig, load_device_config
from ..config.files import mode_kind
from ..gateway.bulk import file_id
from ..gateway.config import GATEWAY_FILE, GatewayConfig, load_gateway_config
from ..gateway.service import Gateway
from ..line.endpoint import endpoint_for
from ..poll.schedule import build_plan, entity_numbers_notice
from ..serve import unknown_devices
from .arg_types import path_text
from .exits import OK, USAGE
from .output import config_warnings, emit, in_file, one_line, shortened

__all__ = ["Report", "add_arguments", "check_path", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("paths", nargs="+", type=path_text, metavar="PATH",
                   help=f"a device file, a gateway file ({GATEWAY_FILE}) or a config folder")
    p.add_argument("--gateway", action="append", default=[], type=path_text, metavar="FILE",
                   help=f"a gateway file with a name other than {GATEWAY_FILE} (repeatable)")


@dataclass
class Report:
    """What a check found: problem and warning lines, and what was checked."""

    problems: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    notices: list[str] = field(default_factory=list)
    device_files: int = 0
    gateway_files: int = 0
    items: int = 0
    requests: int = 0

    def problem(self, path: Path, message: str) -> None:
        self.problems.append(in_file(path, message))

    def summary(self) -> str:
        files = f"{self.device_files} device file{'s' * (self.device_files != 1)}"
        gateways = f"{self.gateway_files} gateway file{'s' * (self.gateway_files != 1)}"
        warned = f", {len(self.warnings)} warnings" if self.warnings else ""
        warned += f", {len(self.notices)} notices" if self.notices else ""
        return (f"ok: {files} ({self.items} items, {self.requests} requests per cycle), "
                f"{gateways}{warned}")


def run(args: argparse.Namespace) -> int:
    report = Report()
    for path in args.gateway:
        _gateway_file(path, report)
    for path in args.paths:
        check_path(path, report)
    for line in report.notices + report.warnings + report.problems:
        emit(shortened(line))
    if report.problems:
        return USAGE
    emit(report.summary())
    return OK


def check_path(path: Path, report: Report) -> None:
    """Check what ``path`` is (a folder, a gateway file or a device file) into ``report``."""
    try:
        info = path.stat()
    except OSError as exc:  # missing, a broken link, a symlink loop, no permission
        report.problem(path, _os_words(exc))
        return
    if stat.S_ISDIR(info.st_mode):
        _folder(path, report)
    elif path.name == GATEWAY_FILE:
        _gateway_file(path, report)
    else:
        _device_file(path, report)


def _os_words(exc: OSError) -> str:
    """An OSError as the line of its path says it ("too many levels of symbolic links":
    a symlink loop was "no such file or directory" before)."""
    words = exc.strerror or str(exc)
    return words[:1].lower() + words[1:]


def _device_file(path: Path, report: Report) -> DeviceConfig | None:
    """Load, parse and plan one device file; None when it has a problem."""
    report.device_files += 1
    warnings: list[str] = []
    try:
        with config_warnings(warnings):
            cfg = load_device_config(path)
            params = cfg.effective_parameters()
            parsed = cfg.parsed_items()
            blocks = build_plan(parsed, params)
            endpoint_for(params)  # the line's settings hang together
            notice = entity_numbers_notice(parsed, params)
    except ConfigError as exc:
        for problem in exc.problems:
            report.problem(path, str(problem))
        return None
    except OSError as exc:
        report.problem(path, _os_words(exc))
        return None
    except ValueError as exc:
        report.problem(path, str(exc))
        return None
    except RecursionError:  # a backstop: config/ bounds the depth it reads
        report.problem(path, "JSON nested too deeply to read")
        return None
    finally:
        report.warnings += [in_file(path, f"warning: {one_line(w)}") for w in warnings]
    if notice is not None:  # as the gateway logs it, once per device (not a problem)
        report.notices.append(in_file(path, f"notice: {one_line(notice)}"))
    report.items += len(cfg.address_list)
    report.requests += len(blocks)
    return cfg


def _gateway_file(path: Path, report: Report) -> GatewayConfig | None:
    report.gateway_files += 1
    warnings: list[str] = []
    try:
        with config_warnings(warnings):
            return load_gateway_config(path)
    except ConfigError as exc:
        for problem in exc.problems:
            report.problem(path, str(problem))
    except OSError as exc:
        report.problem(path, _os_words(exc))
    except RecursionError:
        report.problem(path, "JSON nested too deeply to read")
    finally:
        report.warnings += [in_file(path, f"warning: {one_line(w)}") for w in warnings]
    return None


def _folder(folder: Path, report: Report) -> None:
    """The gateway's view of a config folder: its gateway file (when there is one), the
    device files it would start, their device codes and the serve units' targets."""
    gateway_file = folder / GATEWAY_FILE
    config = GatewayConfig()
    if os.path.lexists(gateway_file):  # a FIFO or a broken link: a problem, not "none"
        loaded = _gateway_file(gateway_file, report)
        if loaded is None:
            return  # without its devicePattern the device files are not known
        config = loaded
    codes: dict[str, Path] = {}
    failed = False
    files = Gateway(folder, config, gateway_file).device_files()
    _skipped(folder, config.device_pattern, files, gateway_file, report)
    if not files and not gateway_file.is_file():  # a wrong folder, not an empty gateway
        report.problem(folder, f"nothing to check: no {GATEWAY_FILE} and no device file "
                               f"(devicePattern {config.device_pattern!r})")
    for path in files:
        cfg = _device_file(path, report)
        if cfg is None:
            failed = True
            continue
        code = cfg.organization.device_code or path.stem  # as the gateway names it
        if code in codes:
            report.problem(path, f"organization.deviceCode {code!r}: already used by "
                                 f"{codes[code].name} (the gateway starts only one)")
        else:
            codes[code] = path
    if config.serve is not None and not failed:  # a unit may name a file that failed
        for problem in unknown_devices(config.serve, list(codes)):
            report.problem(gateway_file, str(problem))


def _skipped(folder: Path, pattern: str, files: list[Path], gateway_file: Path,
             report: Report) -> None:
    """A warning for each name the folder's ``devicePattern`` matches that the gateway
    does not start (it skips them without a word): a FIFO, a device, a folder, a broken
    link, a symlink loop.  One stat each, no open (a FIFO's open blocks)."""
    taken = set(files)
    gateway = file_id(gateway_file)
    for path in sorted(folder.glob(pattern)):
        if path in taken or path.name.startswith("."):
            continue
        try:
            info = path.stat()
        except OSError as exc:
            why = _os_words(exc)
        else:
            if (info.st_dev, info.st_ino) == gateway:
                continue
            why = f"is {mode_kind(info.st_mode) or 'a regular file'}"
        report.warnings.append(in_file(path, f"warning: {why}: not a device file, the "
                                             "gateway skips it"))
