"""Threads that each run a request in a closed loop (the next as soon as the last one
ended) until the ``with`` block ends: the masters and writers of the line-scheduling
tests.  A subclass gives ``_run(*args)``, which loops while ``self._stop`` is not set
and counts under ``self._lock``."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any, Self


class ClosedLoops:
    """One thread per entry of ``args`` running ``self._run(*entry)``, named
    ``<name>-<k>``; stopped and joined (within ``join_s``) when the block ends."""

    def __init__(self, args: Sequence[tuple[Any, ...]], name: str,
                 join_s: float = 30.0) -> None:
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._join_s = join_s
        self._threads = [threading.Thread(target=self._run, args=entry, name=f"{name}-{k}")
                         for k, entry in enumerate(args)]

    def _run(self, *args: Any) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        for thread in self._threads:
            thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(self._join_s)
        assert not any(t.is_alive() for t in self._threads), "a looping thread did not stop"
