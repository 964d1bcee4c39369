"""Polling for a condition in integration tests, with a message that says what was awaited."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_for(cond: Callable[[], object], timeout: float = 20.0, what: str = "") -> None:
    """Return as soon as ``cond()`` is true; AssertionError after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.01)  # poll: the step of wait_for itself
    raise AssertionError(f"timed out after {timeout} s waiting for {what or cond}")
