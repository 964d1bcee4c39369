"""What an existing path is when it is no regular file, in the words every error about a
file we read or keep uses (device and gateway files, TLS files, the spool, the bdSeq
file): a FIFO blocks a reader forever, SQLite fails on a device with a bare "disk I/O
error", so each is refused with the field named before anything opens it."""

from __future__ import annotations

import os
import stat

__all__ = ["mode_kind", "open_regular", "path_kind"]

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


def open_regular(path: str | os.PathLike[str]) -> tuple[int, os.stat_result]:
    """An fd open for reading on what ``path`` names, and its fstat (the caller closes
    the fd and checks the kind: :func:`mode_kind` of its ``st_mode``).  Opened without
    blocking: a FIFO put in place of a regular file between a caller's ``stat`` and its
    open blocked that ``open()`` forever (the reload thread of a gateway, a CLI check);
    the fd is blocking again before it is returned."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOCTTY)
    try:
        info = os.fstat(fd)
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd, info
