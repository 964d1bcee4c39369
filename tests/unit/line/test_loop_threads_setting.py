"""``loopThreads`` is process-wide (line/dtu_registry.py): the largest asked by the open
DTUs wins, whatever order their devices start in, and the number falls back when they
close; a worker full of lines gets company (line/loop_pool.py LoopPool)."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.line import DtuEndpoint, DtuRegistry, PortSettings
from edgemodbus.line.loop import LoopLine
from edgemodbus.line.loop_pool import LoopPool, pool
from tests.peers import free_port
from tests.unit.line.test_loop_pool import Absent


@pytest.fixture
def restored() -> Iterator[None]:
    threads = pool.threads
    try:
        yield
    finally:
        pool.threads = threads


@pytest.mark.usefixtures("restored")
@settings(max_examples=15, deadline=None)
@given(st.permutations([None, 3, 1, 2]), st.data())
def test_the_largest_loop_threads_of_the_open_dtus_wins(order: list[int | None],
                                                        data: st.DataObject) -> None:
    registry = DtuRegistry()
    registry.set_engine("loop", 5)  # while no open DTU asks for a number
    port = free_port()
    slots = [registry.acquire(PortSettings("127.0.0.1", port, "text", loop_threads=t),
                              DtuEndpoint("127.0.0.1", port, f"D{k}"))
             for k, t in enumerate(order)]
    # every device of a port agrees on the other keys; loopThreads is the process's
    try:
        assert pool.threads == 3
        closing = data.draw(st.permutations(list(zip(order, slots, strict=True))))
        left = list(order)
        for threads, slot in closing:
            registry.release(slot)
            left.remove(threads)
            asked = [t for t in left if t is not None]
            assert pool.threads == (max(asked) if asked else 5)
    finally:
        for slot in slots:
            registry.release(slot)
    registry.set_engine("loop")
    assert pool.threads == (os.cpu_count() or 1)


def test_lines_past_every_worker_s_capacity_get_one_more_worker() -> None:
    """A worker serves ``capacity`` lines (its loop's slots): the next line starts one
    more worker instead of failing in the full one (an IndexError from its free slots
    stopped 19,000 DTUs on two loop threads of 8,192 each)."""
    pool_ = LoopPool(1, capacity=2)
    lines = [LoopLine(DtuEndpoint("127.0.0.1", 1, f"C{k}"), None, Absent(), pool_)
             for k in range(5)]
    try:
        for line in lines:
            line.start()
        assert pool_.workers == 3
        names = {line._thread.name for line in lines if line._thread is not None}
        assert len(names) == 3
    finally:
        for line in lines:
            line.stop()
    assert pool_.workers == 0
