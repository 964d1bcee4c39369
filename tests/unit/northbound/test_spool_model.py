"""The spool against a plain in-memory model (hypothesis, stateful): appends (claimed or
not), claims, acks, releases, a clock that moves (also back), close and reopen, under
both bounds.  After every step the counters agree; the model says which messages are
stored, in which order, and which are in flight."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from edgemodbus.northbound.mqtt.spool import Message, Spool, message_size

MAX_AGE = 100.0


@dataclass
class Row:
    id: int
    number: int
    ts: float
    size: int


class SpoolModel(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.dir = tempfile.TemporaryDirectory()
        self.path = Path(self.dir.name) / "spool.db"
        self.max_bytes = 0
        self.now = 1_000_000.0
        self.rows: list[Row] = []  # the model: stored rows in order
        self.inflight: set[int] = set()
        self.dropped = {"droppedSize": 0, "droppedAge": 0}
        self.acked = 0
        self.counter = 0
        self.spool: Spool | None = None

    def clock(self) -> float:
        return self.now

    def open(self) -> Spool:
        return Spool(self.path, max_bytes=self.max_bytes, max_age_s=MAX_AGE,
                     clock=self.clock)

    @rule(max_bytes=st.sampled_from([60, 500, 2000, 100_000]))
    @precondition(lambda self: self.spool is None)
    def start(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.spool = self.open()

    # -- the model's rules ----------------------------------------------------------

    def drop(self, n: int, counter: str) -> None:
        for row in self.rows[:n]:
            self.inflight.discard(row.id)
        del self.rows[:n]
        self.dropped[counter] += n

    def expire(self) -> None:
        n = 0
        while n < len(self.rows) and self.rows[n].ts < self.now - MAX_AGE:
            n += 1
        self.drop(n, "droppedAge")

    # -- steps ----------------------------------------------------------------------

    @rule(sizes=st.lists(st.integers(0, 60), max_size=12), claimed=st.booleans())
    @precondition(lambda self: self.spool is not None)
    def append(self, sizes: list[int], claimed: bool) -> None:
        assert self.spool is not None
        messages = []
        for size in sizes:
            self.counter += 1
            messages.append(Message(f"d{self.counter % 3}", "t",
                                    str(self.counter).encode().ljust(size, b" "), 1, False))
        ids = self.spool.append(messages, claimed=claimed)
        if not messages:
            assert ids == []
            return
        self.expire()
        new = [(int(m.payload), message_size(m.topic, m.payload)) for m in messages]
        while sum(s for _, s in new) > self.max_bytes:
            new.pop(0)
            self.dropped["droppedSize"] += 1
        need = sum(r.size for r in self.rows) + sum(s for _, s in new) - self.max_bytes
        n = freed = 0
        while freed < need:
            freed += self.rows[n].size
            n += 1
        self.drop(n, "droppedSize")
        assert len(ids) == len(new)
        assert not self.rows or not ids or ids[0] > self.rows[-1].id
        self.rows += [Row(i, number, self.now, size)
                      for i, (number, size) in zip(ids, new, strict=True)]
        if claimed:
            self.inflight.update(ids)

    @rule(limit=st.integers(0, 12))
    @precondition(lambda self: self.spool is not None)
    def next_batch(self, limit: int) -> None:
        assert self.spool is not None
        got = self.spool.next_batch(limit)
        if limit > 0 and self.rows and self.rows[0].ts < self.now - MAX_AGE:
            self.expire()
        want = [r for r in self.rows if r.id not in self.inflight][:limit]
        assert [(m.id, int(m.payload)) for m in got] == [(r.id, r.number) for r in want]
        self.inflight.update(r.id for r in want)

    @rule(data=st.data())
    @precondition(lambda self: self.spool is not None and self.inflight)
    def ack(self, data: st.DataObject) -> None:
        assert self.spool is not None
        ids = data.draw(st.lists(st.sampled_from(sorted(self.inflight)), unique=True))
        stale = data.draw(st.lists(st.integers(-5, 0)))  # unknown ids: ignored
        assert self.spool.ack(ids + stale) == len(ids)
        self.acked += len(ids)
        self.rows = [r for r in self.rows if r.id not in ids]
        self.inflight -= set(ids)

    @rule(data=st.data())
    @precondition(lambda self: self.spool is not None and self.inflight)
    def release(self, data: st.DataObject) -> None:
        assert self.spool is not None
        ids = data.draw(st.lists(st.sampled_from(sorted(self.inflight)), unique=True))
        self.spool.release(ids)
        self.inflight -= set(ids)

    @rule()
    @precondition(lambda self: self.spool is not None)
    def release_all(self) -> None:
        assert self.spool is not None
        self.spool.release_all()
        self.inflight.clear()

    @rule(step=st.floats(-10, 60))
    def tick(self, step: float) -> None:
        self.now += step

    @rule()
    @precondition(lambda self: self.spool is not None)
    def reopen(self) -> None:
        """A restart: everything stored comes back pending, the counters start at 0."""
        assert self.spool is not None
        self.spool.close()
        self.spool = self.open()
        self.inflight.clear()
        self.dropped = dict.fromkeys(self.dropped, 0)
        self.acked = 0

    @invariant()
    def counters_agree(self) -> None:
        if self.spool is None:
            return
        stats = self.spool.stats()
        assert stats["stored"] == len(self.rows)
        assert stats["inflight"] == len(self.inflight)
        assert stats["pending"] == len(self.rows) - len(self.inflight)
        assert stats["bytes"] == sum(r.size for r in self.rows) <= self.max_bytes
        assert stats["acked"] == self.acked
        assert {k: stats[k] for k in self.dropped} == self.dropped

    def teardown(self) -> None:
        if self.spool is not None:
            self.spool.close()
        self.dir.cleanup()


SpoolModel.TestCase.settings = settings(max_examples=25, stateful_step_count=30,
                                        deadline=None)
TestSpoolModel = SpoolModel.TestCase
