"""Commissioning: what an engineer does on site before a device file exists.

* scan.py: :func:`scan_line` finds what answers on a line (serial settings swept,
  slave ids probed), one line at a time on the caller's thread, through the line
  layer's links (:func:`edgemodbus.line.connect.open_link`).
"""

from __future__ import annotations

from .scan import (
    DEFAULT_PROBES,
    Answer,
    Found,
    Progress,
    ScanEvent,
    SettingDone,
    SettingStarted,
    default_timeout,
    scan_line,
    serial_settings,
    setting_text,
)

__all__ = [
    "DEFAULT_PROBES",
    "Answer",
    "Found",
    "Progress",
    "ScanEvent",
    "SettingDone",
    "SettingStarted",
    "default_timeout",
    "scan_line",
    "serial_settings",
    "setting_text",
]
