"""Starting many drivers at once: :func:`starting_in_bulk` (docs/scale.md, "Starting
thousands of devices").

Inside it, ``DriverModbusRtu.start_device`` works as ever, but two costs that grow with
a fleet are left out: Python's cyclic garbage collector is off (each of its full passes
walks every object, and thousands of devices made it run hundreds of times during a
start), and a loop-engine line is handed to its loop thread without waiting for it
there and without waking it (line/loop_pool.py ``LoopPool.deferred``: a round trip and a
hand-over of the GIL per device); the loop threads are woken and the lines waited for
together at the end.  A job (a write, a read) or a stop inside wakes its loop thread at
once, as outside.  The gateway service starts a folder's devices inside it.
"""

from __future__ import annotations

import gc
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from .line.loop_pool import pool as loop_pool

__all__ = ["starting_in_bulk"]


@contextmanager
def starting_in_bulk(freeze: Callable[[], bool] | None = None) -> Iterator[None]:
    """Start many drivers inside (on this thread): the collector paused (on again after,
    if it was), loop-engine lines waited for together at the end, where the first
    failure of one to be taken by its loop thread is raised (a bug: the others run).
    ``freeze()`` true at the end: then ``gc.freeze()`` what the process holds, before the
    collector is on again (its first pass would walk every object the drivers are made
    of; the caller calls ``gc.unfreeze()`` before it stops drivers, as gateway/bulk.py
    does)."""
    was = gc.isenabled()
    gc.disable()
    try:
        with loop_pool.deferred():
            yield
    finally:
        if freeze is not None and was and freeze():
            gc.freeze()
        if was:
            gc.enable()
