"""line/accept_pause.py: the pause after accept errors doubles from 50 ms to 2 s, starts
again after an accept that worked, and ends once."""

from __future__ import annotations

import math

from edgemodbus.line.accept_pause import MAX_ACCEPT_PAUSE, MIN_ACCEPT_PAUSE, AcceptPause


def test_the_pause_doubles_to_its_cap_and_starts_again_after_an_accept() -> None:
    paused = AcceptPause()
    assert paused.until == math.inf and not paused.over(1e9)
    pauses = [paused.failed(100.0) for _ in range(8)]
    assert pauses == [0.05, 0.1, 0.2, 0.4, 0.8, 1.6, 2.0, 2.0]
    assert (pauses[0], pauses[-1]) == (MIN_ACCEPT_PAUSE, MAX_ACCEPT_PAUSE)
    assert paused.until == 102.0
    paused.accepted()
    assert paused.failed(200.0) == MIN_ACCEPT_PAUSE


def test_a_pause_ends_once_at_its_time() -> None:
    paused = AcceptPause()
    paused.failed(10.0)
    assert not paused.over(10.04)
    assert paused.over(10.05)
    assert not paused.over(10.06) and paused.until == math.inf
