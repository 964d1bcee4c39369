"""The lease state machine (gateway/lease.py) on a fake clock and a fake engine whose
keys expire on that same clock: takeover, renewal, a paused leader, a slow renewal,
the write gate; and a property: at no instant do two leases believe they hold it."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.gateway.lease import Lease, NotLeaderError


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class FakeEngine:
    """A Redis key with PX on the fake clock; ``delay``: how long each call takes."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.holder: str | None = None
        self.until = 0.0
        self.fence = 0
        self.down = False
        self.delay = 0.0

    def _expire(self) -> None:
        if self.holder is not None and self.clock.now >= self.until:
            self.holder = None

    def acquire(self, token: str, ttl_ms: int) -> int | None:
        if self.down:
            raise ConnectionError("engine down")
        self._expire()
        if self.holder is not None:
            return None
        self.holder, self.until = token, self.clock.now + ttl_ms / 1000
        self.fence += 1
        self.clock.now += self.delay
        return self.fence

    def renew(self, token: str, ttl_ms: int) -> bool:
        if self.down:
            raise ConnectionError("engine down")
        self._expire()
        ok = self.holder == token
        if ok:
            self.until = self.clock.now + ttl_ms / 1000
        self.clock.now += self.delay
        return ok

    def release(self, token: str) -> None:
        if self.holder == token:
            self.holder = None


def pair(clock: Clock, engine: FakeEngine) -> tuple[Lease, Lease, list[str]]:
    events: list[str] = []
    a = Lease(engine, 3000, 1000, token="a", clock=clock,
              on_gain=lambda f: events.append(f"a+{f}"), on_loss=lambda r: events.append("a-"))
    b = Lease(engine, 3000, 1000, token="b", clock=clock,
              on_gain=lambda f: events.append(f"b+{f}"), on_loss=lambda r: events.append("b-"))
    return a, b, events


def test_one_leader_and_renewal() -> None:
    clock = Clock()
    engine = FakeEngine(clock)
    a, b, events = pair(clock, engine)
    assert a.step() == 1.0
    assert b.step() == 0.5  # standby retries at half the renew period
    assert (a.held, b.held, a.fence) == (True, False, 1)
    for _ in range(10):
        clock.now += 1.0
        assert a.step() == 1.0
        b.step()
    assert events == ["a+1"]
    assert a.valid_for() == pytest.approx(3.0)


def test_paused_leader_gives_up_before_anything_else_and_standby_takes_over() -> None:
    clock = Clock()
    engine = FakeEngine(clock)
    a, b, events = pair(clock, engine)
    a.step()
    clock.now += 2.9
    b.step()
    assert not b.held  # not yet expired
    clock.now += 0.1  # a is "paused": no renewal; the key expires
    b.step()
    assert b.held and b.fence == 2  # a higher fencing token
    clock.now += 2.0  # a wakes (b renews in time)
    assert not a.check()
    assert events == ["a+1", "b+2", "a-"]
    a.step()
    assert not a.held  # b holds the key


def test_woken_leader_whose_key_survived_still_gives_up_on_time() -> None:
    """No standby took it (the key is still ours in the engine if it never expired
    there, e.g. engine clock behind): the local monotonic time decides."""
    clock = Clock()
    engine = FakeEngine(clock)
    a, _b, events = pair(clock, engine)
    a.step()
    engine.until = 1e9  # the engine would still say yes
    clock.now += 3.0
    a.step()
    assert events[:2] == ["a+1", "a-"]


def test_renewal_slower_than_the_lease_loses_it() -> None:
    clock = Clock()
    engine = FakeEngine(clock)
    a, _b, events = pair(clock, engine)
    a.step()
    engine.delay = 3.5
    a.step()
    assert not a.held
    assert events == ["a+1", "a-"]


def test_engine_failure_stops_the_leader_at_once() -> None:
    clock = Clock()
    engine = FakeEngine(clock)
    a, _b, events = pair(clock, engine)
    a.step()
    engine.down = True
    clock.now += 1.0
    a.step()
    assert not a.held and events == ["a+1", "a-"]
    assert a.step() == 0.5  # and keeps trying without raising


def test_write_gate() -> None:
    clock = Clock()
    engine = FakeEngine(clock)
    a, b, _ = pair(clock, engine)
    a.step()
    b.step()
    with pytest.raises(NotLeaderError, match="not the leader of the pair"):
        b.require(1.0)
    a.require(1.0)
    clock.now += 2.5
    with pytest.raises(NotLeaderError, match=r"lease ends in 0\.500 s, the write may take "
                       r"1\.000 s"):
        a.require(1.0)


def test_release_lets_the_standby_in_at_once() -> None:
    clock = Clock()
    engine = FakeEngine(clock)
    a, b, events = pair(clock, engine)
    a.step()
    a.release()
    b.step()
    assert b.held and events == ["a+1", "a-", "b+2"]


def test_renew_period_bound() -> None:
    with pytest.raises(ValueError, match="renewMs 1500 must be at most a third of leaseMs 3000"):
        Lease(FakeEngine(Clock()), 3000, 1500)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.sampled_from("ab"), st.floats(0, 4.0),
                          st.sampled_from([0.0, 0.0, 0.2, 3.5])), max_size=40))
def test_never_two_leaders(moves: list[tuple[str, float, float]]) -> None:
    """Any interleaving of steps, clock jumps (pauses) and slow calls: when both check
    at the same instant, at most one believes it holds the lease."""
    clock = Clock()
    engine = FakeEngine(clock)
    a, b, _ = pair(clock, engine)
    for who, jump, delay in moves:
        clock.now += jump
        engine.delay = delay
        (a if who == "a" else b).step()
        engine.delay = 0.0
        held_a, held_b = a.check(), b.check()
        assert not (held_a and held_b)
        if held_a or held_b:  # whoever believes it holds it is the engine's holder
            assert engine.holder == ("a" if held_a else "b")


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.sampled_from("ab"), st.floats(0, 4.0),
                          st.sampled_from([0.0, 0.0, 0.2, 3.5])), max_size=40))
def test_never_two_deadlines_ahead(moves: list[tuple[str, float, float]]) -> None:
    """What a line reads (Lease.deadline, no check() between: the lease's thread may be
    paused): at no instant are both instances' deadlines ahead of the clock, whatever
    the interleaving of steps, pauses and slow calls; a deadline is never past the
    engine's expiry of that instance's key."""
    clock = Clock()
    engine = FakeEngine(clock)
    a, b, _ = pair(clock, engine)
    for who, jump, delay in moves:
        clock.now += jump
        engine.delay = delay
        (a if who == "a" else b).step()
        engine.delay = 0.0
        ahead = [lease for lease in (a, b) if clock.now < lease.deadline()]
        assert len(ahead) <= 1
        for lease in ahead:
            assert engine.holder == lease.token and lease.deadline() <= engine.until


def test_the_deadline_is_the_known_end_less_the_margin() -> None:
    clock = Clock()
    lease = Lease(FakeEngine(clock), 3000, 1000, token="a", clock=clock, margin_ms=250)
    assert lease.deadline() == 0.0  # not held
    lease.step()
    assert lease.deadline() == pytest.approx(100.0 + 3.0 - 0.25)
    clock.now += 1.0
    lease.step()  # renewed
    assert lease.deadline() == pytest.approx(101.0 + 3.0 - 0.25)
    lease.release()
    assert lease.deadline() == 0.0
    assert Lease(FakeEngine(clock), 3000, 1000).margin == pytest.approx(0.3)  # leaseMs/10
    assert Lease(FakeEngine(clock), 1000, 300).margin == pytest.approx(0.1)  # at least 100
    with pytest.raises(ValueError, match=r"marginMs 1600 must be 0\.\.1500"):
        Lease(FakeEngine(clock), 3000, 1000, margin_ms=1600)


def test_watchers_hear_of_a_loss_before_the_gateway() -> None:
    """A line gated by the lease is woken (LineWorker.lease_changed) at a loss."""
    clock = Clock()
    engine = FakeEngine(clock)
    events: list[str] = []
    lease = Lease(engine, 3000, 1000, token="a", clock=clock,
                  on_loss=lambda reason: events.append("gateway"))

    def line() -> None:
        events.append("line")

    lease.watch(line)
    lease.step()
    clock.now += 3.5  # paused past the lease
    assert not lease.check()
    assert events == ["line", "gateway"]
    lease.unwatch(line)
    lease.step()
    clock.now += 3.5
    lease.check()
    assert events == ["line", "gateway", "gateway"]


def test_an_unreachable_engine_is_one_line_per_interval_and_counted(
        caplog: pytest.LogCaptureFixture) -> None:
    """A standby retries every renewMs/2 (50 ms at the smallest): each failure used to
    log a line. Now one per kind of error and 10 s, a summary, one line at recovery."""
    clock = Clock()
    engine = FakeEngine(clock)
    a, _b, _events = pair(clock, engine)
    engine.down = True
    caplog.set_level("INFO", logger="edgemodbus.lease")
    start = clock.now
    for _ in range(200):  # an attempt every 0.5 s (renewMs 1000 / 2)
        clock.now += a.step()
    intervals = (clock.now - start) / 10.0  # 100 s: ten of the limiter's intervals
    lines = [r.getMessage() for r in caplog.records]
    assert sum("cannot reach the lease engine" in line for line in lines) <= intervals
    assert sum("more failed attempts" in line for line in lines) <= intervals
    assert a.counts["engineErrors"] == 200 and not a.held
    caplog.clear()
    engine.down = False
    a.step()
    assert a.held and a.counts["gained"] == 1
    assert "lease: the lease engine answers again" in [r.getMessage() for r in caplog.records]
