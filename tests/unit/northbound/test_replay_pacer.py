"""The replay pacer: a token bucket in messages and bytes per second, on an injected clock."""

from __future__ import annotations

import pytest

from edgemodbus.northbound.mqtt.spool import ReplayPacer


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_messages_per_second_with_a_burst_of_one_second() -> None:
    clock = Clock()
    pacer = ReplayPacer(50, clock=clock)
    assert pacer.budget() == 50  # full at the start
    pacer.spend(50)
    assert pacer.budget() == 0 and pacer.delay() == pytest.approx(0.02)
    clock.t += 0.1
    assert pacer.budget() == 5
    clock.t += 100  # idle for long: never more than the burst
    assert pacer.budget() == 50
    # over a long run the rate holds whatever the batch sizes
    sent = 0
    pacer.spend(50)
    for _ in range(1000):
        clock.t += 0.013
        n = min(pacer.budget(), 7)
        pacer.spend(n)
        sent += n
    assert sent == pytest.approx(50 * 13, abs=8)


def test_bytes_per_second_go_into_debt_and_wait_for_it() -> None:
    clock = Clock()
    pacer = ReplayPacer(1000, bytes_per_s=10_000, clock=clock)
    assert pacer.budget() == 1000
    pacer.spend(10, 30_000)  # 20,000 bytes of debt: 2 s
    assert pacer.budget() == 0
    assert pacer.delay() == pytest.approx(2.0)
    clock.t += 1.999
    assert pacer.budget() == 0
    clock.t += 0.001
    assert pacer.budget() >= 1
    assert pacer.delay() == 0.0


def test_a_clock_that_goes_back_refills_nothing() -> None:
    clock = Clock()
    pacer = ReplayPacer(10, burst=2, clock=clock)
    pacer.spend(2)
    clock.t -= 50
    assert pacer.budget() == 0
    clock.t += 0.1
    assert pacer.budget() == 1


@pytest.mark.parametrize("rate, byte_rate, burst, match", [
    (0, None, None, "messages_per_s 0 must be"),
    (float("inf"), None, None, "messages_per_s inf must be"),
    (5, -1, None, "bytes_per_s -1 must be"),
    (5, None, 0.5, "burst 0.5 must be"),
])
def test_refused_settings(rate: float, byte_rate: float | None, burst: float | None,
                          match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ReplayPacer(rate, bytes_per_s=byte_rate, burst=burst)


def test_negative_spending_is_refused() -> None:
    with pytest.raises(ValueError, match=r"messages \(-1\) and nbytes"):
        ReplayPacer(5).spend(-1)
