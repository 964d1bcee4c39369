"""The target backoff of a line (line/jobs.py): how long a silent slave's forwards and
writes fail at once, and what ends it."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.errors import ModbusTimeoutError, ProtocolError, TargetBackoffError
from edgemodbus.line.forward import QueuedTooLongError
from edgemodbus.line.jobs import BACKOFF_FACTOR, TargetBackoff

costs = st.floats(0.0, 30.0, allow_nan=False)


def backing_off(b: TargetBackoff, slave: int, now: float, marker: int) -> bool:
    try:
        b.check(slave, now, marker)
    except TargetBackoffError as exc:
        assert f"slave {slave} did not answer" in str(exc)
        return True
    return False


@given(st.lists(costs, min_size=1, max_size=12), st.floats(1.0, 120.0))
def test_each_timeout_in_a_row_backs_off_longer_up_to_max_backoff(
        cost_list: list[float], max_backoff: float) -> None:
    b = TargetBackoff(max_backoff)
    now, previous = 0.0, 0.0
    for cost in cost_list:
        interval = b.settled(5, None, True, now, cost, marker=0)
        assert interval is not None
        base = BACKOFF_FACTOR * max(cost, 0.05)
        # at least four times what it cost the line: a dead slave takes <= 1/5 of it
        assert interval >= min(base, max(max_backoff, base)) - 1e-9
        assert interval >= min(2 * previous, max(max_backoff, base)) - 1e-9
        assert interval <= max(max_backoff, base) + 1e-9
        assert backing_off(b, 5, now + interval * 0.99, 0)
        assert not backing_off(b, 5, now + interval, 0)
        assert not backing_off(b, 6, now, 0)  # other slaves are not concerned
        previous = interval
        now += interval


def test_an_answer_ends_the_backoff() -> None:
    b = TargetBackoff(60.0)
    b.settled(3, ModbusTimeoutError("no answer"), True, 0.0, 1.4, marker=10)
    assert backing_off(b, 3, 1.0, 10)
    # a forward that waited out its time in the queue was never sent: no news
    b.settled(3, QueuedTooLongError("ran out"), False, 1.0, 0.0, marker=10)
    b.settled(3, TargetBackoffError("backing off"), False, 1.0, 0.0, marker=10)
    assert backing_off(b, 3, 1.0, 10)
    # a poll of it got an answer (its devices' responses grew): alive again
    assert not backing_off(b, 3, 1.0, 11)
    b.settled(3, None, True, 2.0, 1.4, marker=11)
    # any reply (a bad one too) ends it
    b.settled(3, ProtocolError("bad echo"), False, 2.5, 0.01, marker=11)
    assert not backing_off(b, 3, 2.5, 11)
    assert b.backing_off() == []
