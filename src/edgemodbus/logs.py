"""Logging set-up for every entry point (the ``edgemodbus`` command, ``python -m
edgemodbus.gateway``, ``python -m edgemodbus.sim``): one rule, so that ``-v`` means the
same everywhere. A library never configures logging: only these entry points call this."""

from __future__ import annotations

import logging
import os

_STEPS = (logging.WARNING, logging.INFO, logging.DEBUG)


def configure_logging(verbose: int = 0, *, default: int = logging.WARNING,
                      quiet: bool = False) -> None:
    """Log to stderr at ``default`` (WARNING for commands, INFO for the service), one
    step more per ``-v`` (INFO, then DEBUG with the frame trace); ``quiet`` keeps
    warnings and errors only.  No timestamps under systemd: the journal has them."""
    if quiet:
        level = logging.WARNING
    else:
        start = _STEPS.index(default) if default in _STEPS else 0
        level = _STEPS[min(start + max(verbose, 0), len(_STEPS) - 1)]
    fmt = "%(levelname)s %(name)s: %(message)s"
    if not os.environ.get("JOURNAL_STREAM"):
        fmt = "%(asctime)s " + fmt
    logging.basicConfig(level=level, format=fmt)
    logging.getLogger("edgemodbus").setLevel(level)
