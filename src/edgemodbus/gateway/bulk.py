"""A folder of thousands of device files started and stopped in bulk (docs/scale.md,
"Starting thousands of devices").

:func:`read_device` reads a file once for both its digest (what a reload compares)
and its load; :func:`starting_in_bulk` starts the devices inside edgemodbus/bulk.py's
(the garbage collector paused, loop-engine lines handed over without a round trip
each); :func:`stop_each` stops devices on a few threads, not one thread per device.
"""

from __future__ import annotations

import gc
import hashlib
import logging
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

from ..bulk import starting_in_bulk as starting_drivers_in_bulk
from ..config import DeviceConfig, load_device_config
from ..config.device import load_device_file
from ..config.jsonfile import MAX_JSON_BYTES, parse_json
from ..config.problems import ConfigError
from ..config.templates import template_bytes
from .config import file_bytes

log = logging.getLogger("edgemodbus.service")

T = TypeVar("T")

STOP_THREADS = 16
"""Threads that stop a folder's devices: a device on its own line worker waits for that
thread to end, so a few stop at once; a thread per device cost a thread start each."""


def read_device(path: Path) -> tuple[str, Callable[[], DeviceConfig]]:
    """The file's digest (its bytes and its template's: a changed template reloads it)
    and its loader (raises as :func:`~edgemodbus.config.load_device_config` does).
    OSError when it cannot be read.  The file is read once; one that is not a regular
    UTF-8 JSON object within config/jsonfile.py's limits is loaded from its path,
    which says why."""
    raw = file_bytes(path)
    data = _decoded(raw, path)
    digest = hashlib.sha256(raw + template_bytes(path, data)).hexdigest()
    if data is None:
        return digest, lambda: load_device_config(path)
    return digest, lambda: load_device_file(path, data)


def file_id(path: Path) -> tuple[int, int] | None:
    """(device, inode) of the file ``path`` names, None when there is none."""
    try:
        info = path.stat()
    except OSError:
        return None
    return info.st_dev, info.st_ino


def _decoded(raw: bytes, path: Path) -> dict[str, object] | None:
    """The JSON object of a file's bytes, or None when loading it from its path is to
    say what is wrong with it (too large, not UTF-8, not JSON, too deep, no object; a
    FIFO or a folder, which file_bytes describes instead of reading)."""
    if len(raw) > MAX_JSON_BYTES:  # (no JSON: file_bytes' words for a FIFO or a folder)
        return None
    try:
        data = parse_json(raw.decode("utf-8-sig"), str(path))
    except (UnicodeDecodeError, ConfigError):
        return None
    return data if isinstance(data, dict) else None


class Thaws:
    """How many times :func:`thaw` gave frozen objects back (``count``)."""

    count = 0


@contextmanager
def starting_in_bulk(started: Callable[[], bool]) -> Iterator[None]:
    """A folder's devices start inside edgemodbus/bulk.py's :func:`starting_in_bulk`; a
    line its loop thread did not take (a bug) is logged, not raised (a reload never
    raises).  When ``started()`` (devices were started) and no device stopped inside,
    what the process holds is then frozen (``gc.freeze``): the devices live until they
    are stopped, and the collector's first pass after the start walked every object
    they are made of (a sixth of a 5,000-device start).  :func:`thaw` gives them back
    to it before a device stops (its cycles are collected as before); a block in which
    one stopped freezes nothing (that device's garbage is not to be kept)."""
    thaws = Thaws.count
    try:
        with starting_drivers_in_bulk(freeze=lambda: started() and Thaws.count == thaws):
            yield
    except Exception:
        log.exception("loop engine: a line was not taken by its loop thread")


def thaw() -> None:
    """Give the objects :func:`starting_in_bulk` froze back to the collector (before a
    device stops: what it leaves is collected as ever); cheap when nothing is frozen."""
    Thaws.count += 1
    if gc.get_freeze_count():
        gc.unfreeze()


def stop_each(devices: Sequence[T], stop: Callable[[T], None],
              threads: int = STOP_THREADS) -> None:
    """``stop(device)`` for every device, on at most ``threads`` threads at once (the
    caller's when there is one device); returns when all are stopped.  ``stop`` logs
    its own failures."""
    if len(devices) <= 1:
        for device in devices:
            stop(device)
        return
    it = iter(devices)
    lock = threading.Lock()

    def work() -> None:
        while True:
            with lock:
                device = next(it, None)
            if device is None:
                return
            stop(device)

    workers = [threading.Thread(target=work, name=f"edgemodbus-stop {k + 1}")
               for k in range(min(threads, len(devices)))]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
