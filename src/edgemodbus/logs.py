"""Logging set-up for every entry point (the ``edgemodbus`` command, ``python -m
edgemodbus.gateway``, ``python -m edgemodbus.sim``): one rule, so that ``-v`` means the
same everywhere. A library never configures logging: only these entry points call this.

Two formats: text lines (``2026-01-18 12:06:26,123 WARNING edgemodbus.line: ...``) and,
for log shippers (Loki, ELK), JSON lines (``--log-format json``, the gateway file's
``logFormat``): one object per record with ``time`` (ISO 8601, UTC, ms), ``level``,
``logger``, ``message``, ``thread``, and ``exception`` when there is a traceback.  The
JSON is written by orjson (a dependency already: codec/jsonable.py); a formatter of our
own is 20 lines and adds no package for the wheel to carry."""

from __future__ import annotations

import logging
import os
from datetime import datetime, timezone

__all__ = ["LOG_FORMATS", "JsonFormatter", "configure_logging", "set_log_format"]

LOG_FORMATS = ("text", "json")
_STEPS = (logging.WARNING, logging.INFO, logging.DEBUG)
_HANDLER = "edgemodbus"  # the name of the handler configure_logging installs


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line (a message's newlines are escaped)."""

    def format(self, record: logging.LogRecord) -> str:
        import orjson  # only when asked for: text logs never load it

        doc: dict[str, object] = {
            "time": datetime.fromtimestamp(record.created, timezone.utc)
            .isoformat(timespec="milliseconds").replace("+00:00", "Z"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
            "thread": record.threadName,
        }
        if record.exc_info:
            doc["exception"] = self.formatException(record.exc_info)
        elif record.exc_text:
            doc["exception"] = record.exc_text
        if record.stack_info:
            doc["stack"] = self.formatStack(record.stack_info)
        return orjson.dumps(doc, default=str).decode()


def _formatter(log_format: str) -> logging.Formatter:
    if log_format not in LOG_FORMATS:
        raise ValueError(f"log format {log_format!r}: must be one of {', '.join(LOG_FORMATS)}")
    if log_format == "json":
        return JsonFormatter()
    fmt = "%(levelname)s %(name)s: %(message)s"
    if not os.environ.get("JOURNAL_STREAM"):  # no timestamps under systemd: the journal
        fmt = "%(asctime)s " + fmt             # has them
    return logging.Formatter(fmt)


def configure_logging(verbose: int = 0, *, default: int = logging.WARNING,
                      quiet: bool = False, log_format: str = "text") -> None:
    """Log to stderr at ``default`` (WARNING for commands, INFO for the service), one
    step more per ``-v`` (INFO, then DEBUG with the frame trace); ``quiet`` keeps
    warnings and errors only; ``log_format`` "text" or "json" (one object a line)."""
    if quiet:
        level = logging.WARNING
    else:
        start = _STEPS.index(default) if default in _STEPS else 0
        level = _STEPS[min(start + max(verbose, 0), len(_STEPS) - 1)]
    handler = logging.StreamHandler()
    handler.set_name(_HANDLER)
    handler.setFormatter(_formatter(log_format))
    logging.basicConfig(level=level, handlers=[handler])
    logging.getLogger("edgemodbus").setLevel(level)


def set_log_format(log_format: str) -> None:
    """Switch the handler :func:`configure_logging` installed to ``log_format`` (the
    gateway file's ``logFormat``, known only once the file is read); nothing when logging
    was configured by someone else (a host application keeps its own)."""
    formatter = _formatter(log_format)
    for handler in logging.getLogger().handlers:
        if handler.get_name() == _HANDLER:
            handler.setFormatter(formatter)
