"""The line engine's schedule (csrc/emb_engine.c) against an independent model.

No I/O: passes are begun and ended by hand at generated times, and after every step the
blocks chosen, the due times and the counters must equal those of a plain Python model
of the rules (the scan-rate rules of poll/schedule.py's docstring)."""

from __future__ import annotations

from dataclasses import dataclass, field

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus._ffi.engine import BlockSpec, EngineDevice
from edgemodbus.stats import CYCLE_BUCKETS

JOIN = 5_000_000  # ns
NS = 1_000_000_000


@dataclass
class Model:
    """The rules, written out: a block due within min(period / 10, 5 ms) joins the pass
    beginning now; after a pass its blocks are due one period after it began, or at once
    if the pass took longer than their period."""

    periods: list[int]  # ns, as every time of the model
    due: list[int] = field(default_factory=list)
    passes: int = 0
    cycles: int = 0
    overruns: int = 0
    hist: list[int] = field(default_factory=lambda: [0] * (len(CYCLE_BUCKETS) + 1))

    def begin(self, now: int) -> list[int]:
        chosen = [k for k, p in enumerate(self.periods)
                  if self.due[k] - now <= min(p // 10, JOIN)]
        if chosen:
            self.passes += 1
        return chosen

    def end(self, chosen: list[int], start: int, now: int) -> bool:
        elapsed = now - start
        over = False
        for k in chosen:
            if elapsed > self.periods[k]:
                over = True
                self.due[k] = now
            else:
                self.due[k] = start + self.periods[k]
        self.cycles += 1
        self.overruns += over
        self.hist[next((i for i, b in enumerate(CYCLE_BUCKETS) if elapsed <= round(b * NS)),
                       len(CYCLE_BUCKETS))] += 1
        return over


def _device(periods: list[float]) -> EngineDevice:
    dev = EngineDevice(slave=1, timeout=1.0, report_all=False, cycle=min(periods))
    dev.set_blocks([BlockSpec(3, 10 * k, 2, p, None, False) for k, p in enumerate(periods)])
    return dev


def _ns(seconds: float) -> int:
    return round(seconds * NS)


periods_st = st.lists(st.sampled_from([0.001, 0.01, 0.05, 0.1, 0.3, 1.0, 60.0]),
                      min_size=1, max_size=8)
# idle and pass times in us: whole milliseconds too, which meet the join and overrun
# boundaries exactly (a block due exactly min(period / 10, 5 ms) from now joins)
_us = st.one_of(st.integers(0, 400_000), st.integers(0, 400).map(lambda ms: 1000 * ms),
                st.sampled_from([1000, 5000, 9000, 10_000, 45_000, 50_000, 100_000, 300_000]))
steps_st = st.lists(st.tuples(_us, _us), max_size=30)


@settings(max_examples=300, deadline=None)
@given(periods=periods_st, steps=steps_st)
def test_passes_and_due_times_follow_the_rules(periods: list[float],
                                               steps: list[tuple[int, int]]) -> None:
    dev = _device(periods)
    model = Model([_ns(p) for p in periods])
    now = 1000 * NS
    dev.all_due(now / NS)
    model.due = [now] * len(periods)
    for idle, duration in steps:
        now += idle * 1000
        n = dev.begin_pass(now / NS)
        chosen = model.begin(now)
        assert n == len(chosen)
        if not chosen:
            assert _ns(dev.due) == min(model.due) and not dev.in_pass
            continue
        assert dev.pass_blocks() == chosen and dev.in_pass
        start, now = now, now + duration * 1000
        assert dev.end_pass(now / NS) == model.end(chosen, start, now)
        assert [_ns(dev.due_of(k)) for k in range(len(periods))] == model.due
        assert _ns(dev.due) == min(model.due) and not dev.in_pass
        assert dev.pass_blocks() == chosen  # still readable once the pass ended
    counts = dev.counts()
    assert (dev.passes, counts.cycles, counts.overruns) == (model.passes, model.cycles,
                                                            model.overruns)
    assert list(counts.cycle_hist) == model.hist


def test_a_device_without_blocks_runs_empty_cycles_at_its_rate() -> None:
    dev = EngineDevice(slave=1, timeout=1.0, report_all=False, cycle=0.2)
    dev.all_due(10.0)
    assert dev.due == 10.0
    dev.begin_pass(10.0)
    dev.end_pass(10.05)
    assert dev.due == 10.2
    dev.begin_pass(10.2)
    assert dev.end_pass(10.5)  # overran its cycle: due at once, not in a burst
    assert dev.due == 10.5


def test_a_report_only_device_is_never_due() -> None:
    dev = EngineDevice(slave=1, timeout=1.0, report_all=False, cycle=0.0)
    dev.all_due(10.0)
    assert dev.due == float("inf")


def test_split_keeps_the_pass_and_puts_the_halves_in_place() -> None:
    dev = _device([0.1, 0.1, 0.1])
    dev.all_due(5.0)
    assert dev.begin_pass(5.0) == 3  # block 0 (the pass's next) answered exception 02
    dev.split(0, [BlockSpec(3, 0, 1, 0.1, None, False), BlockSpec(3, 1, 1, 0.1, None, False)])
    assert dev.pass_blocks() == [0, 1, 2, 3] and dev.index == 0 and dev.in_pass
    assert [dev.due_of(k) for k in range(4)] == [5.0] * 4
