"""An asyncio loop on a thread of its own, for the northbound command runners (MQTT
commands, Sparkplug DCMD writes): other threads hand it coroutines, many run at once
(``write_addresses_async`` waits on line workers without holding the thread)."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Callable, Coroutine
from typing import Any


class LoopThread:
    """``start()``, ``spawn(make)`` from any thread, ``stop()`` (cancels what still runs)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        self._thread = threading.Thread(target=self._run, args=(loop,), name=self.name,
                                        daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        loop = self._loop
        return loop is not None and not loop.is_closed()

    def spawn(self, make: Callable[[], Coroutine[Any, Any, None]]) -> bool:
        """Run the coroutine ``make()`` on the loop; False when the loop is not running
        (not started, or stopping): nothing was run."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return False
        try:
            loop.call_soon_threadsafe(lambda: loop.create_task(make()))
        except RuntimeError:  # the loop is closing: stop() is under way
            return False
        return True

    def _run(self, loop: asyncio.AbstractEventLoop) -> None:
        asyncio.set_event_loop(loop)
        try:
            loop.run_forever()
        finally:
            tasks = asyncio.all_tasks(loop)
            for task in tasks:
                task.cancel()
            if tasks:
                loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
            loop.close()

    def stop(self) -> None:
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(loop.stop)
        thread.join(5.0)
        self._thread = None
