"""The gateway's web console (docs/console.md): devices and lines at a glance, a device's
tags live (server-sent events), writes and actions, commissioning a device file from the
driver descriptor.  Off unless the gateway file has a ``console`` section; the server
(server.py, aiohttp) is imported only then (edgemodbus[console])."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..config import NO_VALUE, ConfigError, Problem
from .host import ConsoleHost, HostDevice
from .settings import ConsoleSettings, ConsoleTls, ConsoleUser, console_key

if TYPE_CHECKING:
    from .server import ConsoleServer

__all__ = ["ConsoleHost", "ConsoleSettings", "ConsoleTls", "ConsoleUser", "HostDevice",
           "console_key", "start_console"]


def start_console(settings: ConsoleSettings | None, host: ConsoleHost) -> ConsoleServer | None:
    """The console ``settings`` ask for, listening (None when off).  OSError names the
    address; a ConfigError naming ``console`` when aiohttp (edgemodbus[console]) is
    missing."""
    if settings is None or not settings.enabled:
        return None
    try:
        from .server import ConsoleServer
    except ImportError as exc:
        raise ConfigError([Problem("console", NO_VALUE, "needs the optional packages of "
                                   f"edgemodbus[console], not installed ({exc}): pip "
                                   "install 'edgemodbus[console]', or remove the console "
                                   "section")]) from None
    return ConsoleServer(settings, host).start()
