"""Subscribers as a list (poll/listeners.py) and their delivery (poll/sink.py Delivery):
removing one listener never drops another, an exception in one is counted and the
others still run, and random subscribe/unsubscribe sequences match a model list."""

from __future__ import annotations

import logging
import threading
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import edgemodbus as em
from edgemodbus.datatypes import DeviceDriverStatus
from edgemodbus.poll.listeners import BatchCallbackListener, Listener, Subscribers
from edgemodbus.poll.sink import BatchCallback, Delivery, ItemCallback, SnapshotPublisher
from edgemodbus.stats import DeviceStats

SOURCE = object()  # what the listeners hear from (the driver, in the library)


class Sink:
    """A poller's owner with subscribers, as the driver is (a PollSink)."""

    source: object = SOURCE

    def __init__(self) -> None:
        self.batch_callback: BatchCallback | None = None
        self.subscribers: Subscribers[object] = Subscribers(
            BatchCallbackListener(lambda: self.batch_callback))

    def item_callback(self) -> ItemCallback | None:
        return None

    def listeners(self) -> tuple[Listener[Any], ...]:
        if self.batch_callback is None:
            return self.subscribers.listeners
        return self.subscribers.with_head

    def snapshot_publisher(self) -> SnapshotPublisher | None:
        return None

    def snapshot(self) -> dict[str, Any]:
        return {"deviceCode": "d", "items": {}}


class Recorder(Listener[object]):
    """Records what it hears; ``fail`` makes each call raise after recording it."""

    def __init__(self, name: str, fail: bool = False) -> None:
        self.name = name
        self.fail = fail
        self.batches: list[list[em.DeviceAddressItem]] = []
        self.statuses: list[tuple[DeviceDriverStatus, str | None]] = []
        self.snapshots: list[dict[str, Any]] = []

    def on_changes(self, source: object, items: list[em.DeviceAddressItem]) -> None:
        assert source is SOURCE
        self.batches.append(items)
        if self.fail:
            raise RuntimeError(f"{self.name} bug")

    def on_status(self, source: object, status: DeviceDriverStatus,
                  reason: str | None) -> None:
        self.statuses.append((status, reason))
        if self.fail:
            raise RuntimeError(f"{self.name} bug")

    def on_snapshot(self, source: object, snapshot: dict[str, Any]) -> None:
        self.snapshots.append(snapshot)
        if self.fail:
            raise RuntimeError(f"{self.name} bug")

    def __repr__(self) -> str:
        return self.name


def item(name: str) -> em.DeviceAddressItem:
    return em.DeviceAddressItem(name=name, address="hr:0", device_data_type="UInt16")


def delivery(sink: Sink, counters: DeviceStats | None = None) -> Delivery:
    return Delivery(sink, counters or DeviceStats(), logging.getLogger("test.listeners"), "d")


def deliver(d: Delivery, *names: str) -> list[em.DeviceAddressItem]:
    """One cycle's batch: report the items, flush; the batch as the listeners got it."""
    d.report([item(n) for n in names])
    sent = d.batch
    d.flush()
    return sent


def test_removing_one_listener_keeps_the_others() -> None:
    sink = Sink()
    d = delivery(sink)
    a, b, c = Recorder("a"), Recorder("b"), Recorder("c")
    for listener in (a, b, c):
        sink.subscribers.add(listener)
    first = deliver(d, "x")
    sink.subscribers.remove(b)
    second = deliver(d, "y")
    third = deliver(d, "z")
    assert a.batches == [first, second, third]
    assert c.batches == [first, second, third]
    assert b.batches == [first]
    assert sink.subscribers.listeners == (a, c)


def test_the_batch_callback_is_the_head_and_leaves_the_list_when_unset() -> None:
    sink = Sink()
    d = delivery(sink)
    order: list[str] = []
    sink.batch_callback = lambda items: order.append("callback")

    class Last(Recorder):
        def on_changes(self, source: object, items: list[em.DeviceAddressItem]) -> None:
            order.append(self.name)

    sink.subscribers.add(Last("a"))
    deliver(d, "x")
    assert order == ["callback", "a"]
    sink.batch_callback = None  # the host's callback gone: the subscribers stay
    deliver(d, "y")
    assert order == ["callback", "a", "a"]


def test_an_exception_is_counted_and_the_others_still_run(
        caplog: pytest.LogCaptureFixture) -> None:
    sink = Sink()
    counters = DeviceStats()
    d = delivery(sink, counters)
    a, bad, c = Recorder("a"), Recorder("bad", fail=True), Recorder("c")
    for listener in (a, bad, c):
        sink.subscribers.add(listener)
    with caplog.at_level(logging.ERROR, logger="test.listeners"):
        batch = deliver(d, "x", "y")
        d.status(DeviceDriverStatus.OFFLINE, "no answer")
        d.snapshot_due()
    assert a.batches == c.batches == bad.batches == [batch]
    assert a.statuses == c.statuses == [(DeviceDriverStatus.OFFLINE, "no answer")]
    assert len(a.snapshots) == len(c.snapshots) == 1
    assert counters.callback_errors == 3
    assert counters.callback_time > 0
    logged = [r.getMessage() for r in caplog.records if r.exc_info is not None]
    assert logged == ["d: listener Recorder failed (2 items)",
                      "d: listener Recorder failed on status Offline",
                      "d: listener Recorder failed on the snapshot"]


def test_nobody_listening_costs_no_call() -> None:
    sink = Sink()
    counters = DeviceStats()
    d = delivery(sink, counters)
    deliver(d, "x")
    d.status(DeviceDriverStatus.RUNNING, None)
    d.snapshot_due()
    assert counters.callback_time == 0.0  # not even the clock was read
    assert d.batch == []


def test_subscribe_twice_unsubscribe_unknown_and_a_non_listener_are_errors() -> None:
    subs: Subscribers[object] = Subscribers(BatchCallbackListener(lambda: None))
    a = Recorder("a")
    subs.add(a)
    with pytest.raises(ValueError, match=r"listener a is already subscribed"):
        subs.add(a)
    assert subs.listeners == (a,)
    with pytest.raises(ValueError, match=r"listener b is not subscribed"):
        subs.remove(Recorder("b"))

    class OnlyChanges:
        def on_changes(self, source: object, items: list[em.DeviceAddressItem]) -> None:
            pass

    with pytest.raises(ValueError, match=r"has no method on_status\(\)"):
        subs.add(OnlyChanges())  # type: ignore[arg-type]
    subs.remove(a)
    assert subs.listeners == () and subs.with_head == (subs.head,)
    subs.add(a)  # subscribed again after its removal
    assert subs.listeners == (a,)


def test_subscribing_from_other_threads_while_delivering() -> None:
    """The worker iterates a snapshot tuple: listeners added and removed by other
    threads meanwhile never make a delivery skip one that stays subscribed."""
    sink = Sink()
    d = delivery(sink)
    stay = Recorder("stay")
    sink.subscribers.add(stay)
    stop = threading.Event()

    def churn() -> None:
        while not stop.is_set():
            extra = Recorder("extra")
            sink.subscribers.add(extra)
            sink.subscribers.remove(extra)

    threads = [threading.Thread(target=churn) for _ in range(2)]
    for thread in threads:
        thread.start()
    try:
        sent = [deliver(d, f"x{n}") for n in range(2000)]
    finally:
        stop.set()
        for thread in threads:
            thread.join()
    assert stay.batches == sent


@st.composite
def programs(draw: st.DrawFn) -> list[tuple[str, int]]:
    ops = st.one_of(st.tuples(st.just("sub"), st.integers(0, 4)),
                    st.tuples(st.just("unsub"), st.integers(0, 4)),
                    st.tuples(st.just("deliver"), st.integers(1, 3)))
    return draw(st.lists(ops, max_size=40))


@settings(max_examples=300, deadline=None)
@given(programs())
def test_random_subscriptions_match_a_model_list(program: list[tuple[str, int]]) -> None:
    """Each listener gets exactly the batches delivered while it was subscribed, in
    order, and each batch reaches the subscribers in subscription order."""
    sink = Sink()
    d = delivery(sink)
    heard: list[str] = []  # who got each batch, in call order

    class Model(Recorder):
        def on_changes(self, source: object, items: list[em.DeviceAddressItem]) -> None:
            heard.append(self.name)
            super().on_changes(source, items)

    listeners = [Model(f"l{k}") for k in range(5)]
    model: list[Model] = []  # the subscribers, in order
    expected: dict[str, list[list[em.DeviceAddressItem]]] = {m.name: [] for m in listeners}
    for op, arg in program:
        if op == "sub":
            listener = listeners[arg]
            if listener in model:
                with pytest.raises(ValueError):
                    sink.subscribers.add(listener)
            else:
                sink.subscribers.add(listener)
                model.append(listener)
        elif op == "unsub":
            listener = listeners[arg]
            if listener in model:
                sink.subscribers.remove(listener)
                model.remove(listener)
            else:
                with pytest.raises(ValueError):
                    sink.subscribers.remove(listener)
        else:
            heard.clear()
            batch = deliver(d, *(f"i{n}" for n in range(arg)))
            assert heard == [m.name for m in model]
            for listener in model:
                expected[listener.name].append(batch)
        assert list(sink.subscribers.listeners) == model
    for listener in listeners:
        assert listener.batches == expected[listener.name]
