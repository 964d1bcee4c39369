"""What an existing path is when it is no regular file, in the words every error about a
file we read or keep uses (device and gateway files, TLS files, the spool, the bdSeq
file): a FIFO blocks a reader forever, SQLite fails on a device with a bare "disk I/O
error", so each is refused with the field named before anything opens it."""

from __future__ import annotations

import os
import stat

__all__ = ["mode_kind", "path_kind"]

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))


def mode_kind(mode: int) -> str | None:
    """None for a regular file, else what it is: "a directory", "a FIFO", ..."""
    if stat.S_ISREG(mode):
        return None
    for test, kind in _KINDS:
        if test(mode):
            return kind
    return "a special file"


def path_kind(path: str | os.PathLike[str]) -> str | None:
    """:func:`mode_kind` of what ``path`` names; None when nothing is there (or it
    cannot be examined: the caller's own open says why)."""
    try:
        return mode_kind(os.stat(path).st_mode)
    except OSError:
        return None
