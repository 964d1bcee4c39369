"""The service process: run the gateway until a signal (SIGHUP reloads), and its command
line ``python -m edgemodbus.gateway``."""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import Any

from ..config import ConfigError
from ..logs import configure_logging, set_log_format
from .config import GATEWAY_FILE, GatewayConfig, load_gateway_config
from .service import Gateway, one_line

log = logging.getLogger("edgemodbus.service")


def run_service(config_dir: Path, gateway_config: Path | None = None, *,
                seconds: float = 0.0) -> int:
    """Run the gateway until SIGTERM/SIGINT, or for ``seconds`` (0: until a signal);
    SIGHUP reloads.  Returns the exit code (docs/command-line.md, "Exit codes"): 0 after a
    clean stop (SIGTERM, --seconds), 130 after SIGINT (Ctrl-C), 2 for a configuration
    error, a missing optional package or a port in use (one line on stderr)."""
    config_dir = Path(config_dir)
    if not 0 <= seconds <= MAX_SECONDS:  # also refuses NaN and infinities
        most = f" and at most {MAX_SECONDS:,}" if seconds > MAX_SECONDS else ""
        print(f"edgemodbus service: --seconds {seconds}: must be >= 0{most} (0: run until "
              "a signal)", file=sys.stderr)
        return 2
    if not config_dir.is_dir():
        print(f"edgemodbus service: --config-dir {str(config_dir)!r}: not a directory",
              file=sys.stderr)
        return 2
    if gateway_config is None and os.path.lexists(config_dir / GATEWAY_FILE):
        gateway_config = config_dir / GATEWAY_FILE  # a FIFO or a broken link: said so
    try:
        config = (load_gateway_config(gateway_config) if gateway_config is not None
                  else GatewayConfig())
    except (ConfigError, OSError) as exc:
        for line in str(exc).splitlines() or [type(exc).__name__]:
            print(f"edgemodbus service: {gateway_config}: {line}", file=sys.stderr)
        return 2
    except Exception as exc:  # e.g. RecursionError of a deeply nested file: no traceback
        print(f"edgemodbus service: {gateway_config}: cannot load ({one_line(exc)})",
              file=sys.stderr)
        return 2
    if config.log_format != "text":  # the gateway file's logFormat
        set_log_format(config.log_format)
    wake = threading.Event()
    flags = {"stop": False, "reload": False, "interrupted": False}

    def on_stop(signum: int, _frame: FrameType | None) -> None:
        flags["stop"] = True
        flags["interrupted"] = flags["interrupted"] or signum == signal.SIGINT
        wake.set()

    def on_reload(signum: int, _frame: FrameType | None) -> None:
        flags["reload"] = True
        wake.set()

    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig, handler in ((signal.SIGTERM, on_stop), (signal.SIGINT, on_stop),
                             (signal.SIGHUP, on_reload)):
            previous[sig] = signal.signal(sig, handler)
    gateway = Gateway(config_dir, config, gateway_config)
    gateway.reload_hook = lambda: on_reload(signal.SIGHUP, None)  # the console's saves
    try:
        try:
            gateway.start()
        except (OSError, ValueError) as exc:  # a ConfigError too (e.g. mqtt without paho)
            text = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            for line in text.splitlines() or [type(exc).__name__]:
                print(f"edgemodbus service: {line}", file=sys.stderr)
            return 2
        except Exception as exc:
            print(f"edgemodbus service: cannot start ({one_line(exc)})", file=sys.stderr)
            return 2
        log.info("gateway %s running: %d device files in %s", gateway.gateway_id,
                 len(gateway.devices), config_dir)
        deadline = time.monotonic() + seconds if seconds > 0 else math.inf
        while not flags["stop"]:
            left = deadline - time.monotonic()
            if left <= 0:
                log.info("%g s elapsed (--seconds)", seconds)
                break
            wake.wait(min(gateway.config.status_check_interval / 1000, left))
            wake.clear()
            if flags["reload"] and not flags["stop"]:
                flags["reload"] = False
                log.info("SIGHUP: reloading %s", config_dir)
                gateway.reload()
            gateway.check_statuses()
        log.info("stopping")
    finally:
        started = time.monotonic()
        gateway.stop()
        for sig, old in previous.items():
            signal.signal(sig, old)
    log.info("stopped in %.0f ms", (time.monotonic() - started) * 1000)
    return 130 if flags["interrupted"] else 0


def _path(text: str) -> Path:
    """A path option's value: not empty (``Path("")`` is the current folder)."""
    if not text.strip() or "\0" in text:
        raise argparse.ArgumentTypeError(f"{text!r}: not a path (give a file or folder)")
    return Path(text)


MAX_SECONDS = 10 * 365 * 86400
"""The longest --seconds: ten years (a wait of 1e20 s overflowed the clock: a traceback)."""


def add_arguments(parser: argparse.ArgumentParser, *, config_dir_required: bool) -> None:
    """The service's options (``python -m edgemodbus.gateway``; ``edgemodbus run
    --config-dir`` takes the same ones)."""
    parser.add_argument("--config-dir", type=_path, required=config_dir_required,
                        default=None, help="gateway service: every device file (*.json) in "
                        "DIR; MQTT/metrics from DIR/gateway.json or --gateway; SIGHUP "
                        "reloads, SIGTERM stops")
    parser.add_argument("--gateway", type=_path, default=None,
                        help=f"gateway file (default: DIR/{GATEWAY_FILE} if present)")
    parser.add_argument("--seconds", type=float, default=0.0,
                        help="stop after N s (0: run until SIGTERM or SIGINT)")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m edgemodbus.gateway",
        description="Poll every device file in a folder; MQTT and metrics from a gateway "
                    "file; SIGHUP reloads, SIGTERM stops.")
    add_arguments(parser, config_dir_required=True)
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="-v: debug logs of edgemodbus (with the frame trace)")
    args = parser.parse_args(argv)
    configure_logging(args.verbose, default=logging.INFO, quiet=args.quiet)
    return run_service(args.config_dir, args.gateway, seconds=args.seconds)
