"""The argparse types of the commands' file and folder options: a bad path is one line
naming the option and what is allowed (argparse prefixes ``argument --dir:``), exit code
2, before anything is opened.

``Path("")`` is ``.``: ``check ''`` checked the current folder and said "ok", and
``templates --dir /no/such/folder`` listed the shipped templates as if it had been
searched; a FIFO given to ``import`` (or as its ``-o``) blocked the command forever.

Nothing here imports config/ at module level: ``read``'s options use :func:`host_name`,
and the one-shot read starts without pydantic (cli/oneshot.py).
"""

from __future__ import annotations

import argparse
import math
import os
import stat
from pathlib import Path

from ..protocol.hosts import check_host

__all__ = ["MAX_SECONDS", "MAX_TEXT_FILE_BYTES", "folder", "host_name", "input_file", "output_file",
           "path_text", "seconds", "serial_device", "word"]

MAX_TEXT_FILE_BYTES = 32 * 1024 * 1024
"""Bytes of a text file a command reads whole (a tag list of 100,000 rows is ~10 MB)."""


def path_text(text: str) -> Path:
    """A path as given: not empty, no NUL byte (what it names is checked where it is
    read: ``check`` reports a missing file as one of its problems)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"{text!r}: an empty path (give a file or folder)")
    if "\0" in text:
        raise argparse.ArgumentTypeError(f"{text!r}: a path cannot contain a NUL byte")
    return Path(text)


MAX_SECONDS = 10 * 365 * 86400
"""The longest --seconds: ten years (threading's waits overflow at 1e20 s)."""


def seconds(text: str) -> float:
    """A duration in seconds: finite, 0 or more (``demo --seconds -5`` ran until Ctrl-C;
    the service's --seconds, gateway/run.py, takes the same)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 <= value <= MAX_SECONDS:  # NaN too; a larger wait overflowed the clock
        raise argparse.ArgumentTypeError(f"{text!r}: not a number of seconds (0..{MAX_SECONDS:,}"
                                         "; 0: until stopped)")
    return value


def word(text: str) -> str:
    """A name or setting (a data type, a byte order, a parity): not empty or blank (an
    empty --format64 meant "unset" to the device file's loader, not an error)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"{text!r}: empty")
    return text


def folder(text: str) -> Path:
    """An existing folder."""
    from ..config.files import path_kind

    path = path_text(text)
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:  # missing, too long a name, no permission
        raise argparse.ArgumentTypeError(f"{text}: {exc.strerror or exc} (give an existing "
                                         "folder)") from None
    if not stat.S_ISDIR(mode):
        kind = "a file" if stat.S_ISREG(mode) else path_kind(path)
        raise argparse.ArgumentTypeError(f"{text}: is {kind} (give an existing folder)")
    return path


def input_file(text: str) -> Path:
    """An existing regular file of at most :data:`MAX_TEXT_FILE_BYTES` (a FIFO or a
    device would block the read, a folder cannot be read)."""
    from ..config.files import path_kind

    path = path_text(text)
    try:
        size = os.stat(path).st_size
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"{text}: {exc.strerror or exc}") from None
    kind = path_kind(path)
    if kind is not None:
        raise argparse.ArgumentTypeError(f"{text}: is {kind} (give a regular file)")
    if size > MAX_TEXT_FILE_BYTES:
        raise argparse.ArgumentTypeError(f"{text}: {size:,} bytes (at most "
                                         f"{MAX_TEXT_FILE_BYTES:,})")
    return path


def output_file(text: str) -> Path | None:
    """A file to write: ``-`` is stdout (None); else a regular file or a new one in an
    existing folder (a FIFO would block the command, a folder cannot be written)."""
    if text == "-":
        return None
    from ..config.files import path_kind

    path = path_text(text)
    kind = path_kind(path)
    if kind is not None:
        raise argparse.ArgumentTypeError(f"{text}: is {kind} (give a file to write, or - "
                                         "for stdout)")
    try:
        parent_mode = os.stat(path.parent).st_mode
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"{text}: its folder: {exc.strerror or exc}") \
            from None
    if not stat.S_ISDIR(parent_mode):
        raise argparse.ArgumentTypeError(f"{text}: {path.parent} is no folder")
    return path


def host_name(text: str) -> str:
    """A host to connect to or listen on: an IP address or a host name by the one rule
    (protocol/hosts.py); empty is refused here (it resolved to nothing, or to every
    interface, and failed later as "Name or service not known", exit code 1)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"{text!r}: an empty host (give a host name or an "
                                         "IP address)")
    try:
        return check_host(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text[:60]!r}: {exc}") from None


def serial_device(text: str) -> str:
    """A serial port: a path, and when something is there, a character device (libmodbus
    took an empty name with a message of its own on stderr, and opened a FIFO or a
    regular file and failed on its settings, exit code 1).  A missing device is the
    line's failure to open (exit code 1: an adapter unplugged)."""
    path = path_text(text)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return text
    except OSError as exc:  # a name too long, a file where a folder should be
        raise argparse.ArgumentTypeError(f"{text}: {exc.strerror or exc} (give a serial "
                                         "device, e.g. /dev/ttyUSB0)") from None
    if not stat.S_ISCHR(mode):
        kind = "a regular file" if stat.S_ISREG(mode) else "a special file"
        if stat.S_ISDIR(mode):
            kind = "a directory"
        elif stat.S_ISFIFO(mode):
            kind = "a FIFO"
        raise argparse.ArgumentTypeError(f"{text}: is {kind}, not a serial device (e.g. "
                                         "/dev/ttyUSB0)")
    return text
