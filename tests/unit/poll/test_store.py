"""poll/store.py against a model: a dict of one ItemReading per item, changed the way the
worker changes an item (the rules the items held before the store, written out again
here), after any sequence of results, blocks, host assignments and rebinds."""

from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import edgemodbus as em
from edgemodbus.config import DeviceAddressItem, ItemReading
from edgemodbus.datatypes import ItemStatus
from edgemodbus.poll.items import ItemState, holds, is_news, set_state
from edgemodbus.poll.store import ItemInUseError, ItemStore

N = 4
T0 = datetime(2026, 1, 1, tzinfo=timezone.utc)
UNREAD = ItemReading(None, ItemStatus.UNKNOWN, None, None)


def _states(deadband: float | None = None) -> list[ItemState]:
    cfg = em.load_device_config({"addressList": [
        {"name": f"t{k}", "address": f"hr:{k}", "deviceDataType": "Float",
         **({"deadband": deadband} if deadband is not None else {})} for k in range(N)]})
    return [ItemState(p, i) for i, p in enumerate(cfg.parsed_items())]


def _model_set(model: dict[int, ItemReading], i: int, value: Any, error: str | None,
               now: datetime) -> None:
    """The result rule: Ok with the value, or Invalid with the reason, the value kept."""
    old = model[i]
    model[i] = (ItemReading(value, ItemStatus.OK, now, None) if error is None
                else ItemReading(old.value, ItemStatus.INVALID, now, error))


def _exactly(held: Any, value: Any) -> bool:
    """The same value: same type, equal, or both NaN."""
    if type(held) is not type(value):
        return False
    nan = isinstance(held, float) and math.isnan(held) and math.isnan(value)
    return nan or held == value


def _number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _model_news(held: ItemReading, value: Any, error: str | None, deadband: float) -> bool:
    """Change mode: another reason, or a value not the held one (beyond the deadband)."""
    if error is not None:
        return held.status is not ItemStatus.INVALID or held.error_reason != error
    if held.status is not ItemStatus.OK or not _exactly(held.value, value):
        near = (held.status is ItemStatus.OK and deadband and _number(held.value)
                and _number(value) and abs(value - held.value) <= deadband)
        return not near
    return False


values = st.one_of(st.floats(allow_nan=True, width=32), st.integers(-3, 3), st.none())
errors = st.one_of(st.none(), st.sampled_from(["timeout", "CRC", "exception 02"]))
step = st.tuples(
    st.sampled_from(["set", "block", "assign", "rebind"]),
    st.lists(st.tuples(st.integers(0, N - 1), values, errors), min_size=1, max_size=N),
)


@settings(max_examples=300, deadline=None)
@given(st.lists(step, max_size=25), st.sampled_from([None, 0.5]))
def test_the_store_holds_what_the_model_holds(steps: list[tuple[str, Any]],
                                              deadband: float | None) -> None:
    states = _states(deadband)
    store = ItemStore(states)
    store.bind()
    model = {i: UNREAD for i in range(N)}
    for n, (kind, results) in enumerate(steps):
        now = T0 + timedelta(seconds=n)
        if kind == "set":
            for i, value, error in results:
                assert is_news(store, states[i], value, error) == _model_news(
                    model[i], value, error, deadband or 0.0)
                assert holds(store, states[i], value) == (
                    model[i].status is ItemStatus.OK and _exactly(model[i].value, value))
                assert set_state(store, states[i], value, error, now) is states[i].item
                _model_set(model, i, value, error, now)
        elif kind == "block":  # a block's change records: (k, value, error) of whole[k]
            whole = [states[i] for i, _, _ in results]
            reported: list[DeviceAddressItem] = []
            store.apply(whole, [(k, v, e) for k, (_, v, e) in enumerate(results)], now,
                        reported)
            assert reported == [s.item for s in whole]
            for i, value, error in results:
                _model_set(model, i, value, error, now)
        elif kind == "assign":  # a host's assignment, the compatibility path
            for i, value, error in results:
                item = states[i].item
                item.value = value
                model[i] = model[i]._replace(value=value)
                if error is not None:  # the time and the reason, one at a time
                    item.error_reason = error
                    model[i] = model[i]._replace(error_reason=error)
                    item.update_ts = now
                    model[i] = model[i]._replace(update_ts=now)
        else:  # a new plan of the same items: the state goes over with them
            previous, store = store, ItemStore(states)
            store.bind(previous=previous)
            previous.active = False
        for i in range(N):
            got, want = store.reading(i), model[i]
            assert got == want or (got[1:] == want[1:] and math.isnan(got.value)
                                   and math.isnan(want.value))
            item = states[i].item  # each field alone, as the item reads it
            assert (item.status, item.update_ts, item.error_reason) == (
                want.status, want.update_ts, want.error_reason)
    snap = store.snapshot()
    for i in range(N):
        entry = snap[f"t{i}"]
        assert entry["status"] == model[i].status.value
        assert entry["errorReason"] == model[i].error_reason


def test_the_items_a_block_read_sets_share_one_time_and_reason() -> None:
    """Memory (docs/item-store.md): the update time and error reason of the items set
    together are one shared pair, so they cost one list entry per item, not two."""
    states = _states()
    store = ItemStore(states)
    store.bind()
    store.apply(states, [(0, 1.0, None), (1, None, "timeout"), (2, 2.0, None),
                         (3, None, "timeout")], T0, [])
    assert store.marks[0] is store.marks[2]
    assert store.marks[1] is store.marks[3]
    assert [s.item.error_reason for s in states] == [None, "timeout", None, "timeout"]
    assert {s.item.update_ts for s in states} == {T0}
    previous, store = store, ItemStore(states)  # a new plan: the pairs go over as they are
    store.bind(previous=previous)
    assert len({id(mark) for mark in store.marks}) == 2


def test_an_item_of_a_running_store_cannot_be_bound_to_another() -> None:
    states = _states()
    first = ItemStore(states)
    first.bind()
    other = ItemStore(_states())
    other.states = states  # the same item objects
    with pytest.raises(ItemInUseError, match=r"addressList\[0\] 't0'"):
        other.bind()
    assert all(s.item.reading == UNREAD for s in states)  # nothing bound, nothing changed
    first.active = False
    other.bind()


def test_an_unbound_items_runtime_fields_are_its_own() -> None:
    item = DeviceAddressItem(name="t", address="hr:1", device_data_type="Int16",
                             status="Ok", value=3)
    assert item.reading == ItemReading(3, ItemStatus.OK, None, None)
    item.error_reason = "x"
    assert item.reading.error_reason == "x"
    plain = DeviceAddressItem(name="u", address="hr:2", device_data_type="Int16")
    again = DeviceAddressItem(name="v", address="hr:3", device_data_type="Int16")
    assert plain.reading is again.reading  # one shared reading until set
    plain.value = 1
    assert again.value is None


def test_a_reader_never_mixes_the_store_of_one_binding_with_the_index_of_another() -> None:
    """An item moved between two stores (update_addresses moves it to a new index) while
    another thread reads it: every value read is the item's in one store or the other,
    never another item's (the new index into the old store)."""
    import sys
    import threading

    cfg = em.load_device_config({"addressList": [
        {"name": n, "address": f"hr:{k}", "deviceDataType": "Int16"}
        for k, n in enumerate(["x", "y"])]})
    x, y = cfg.address_list
    parsed = cfg.parsed_items()
    a = ItemStore([ItemState(parsed[0], 0), ItemState(parsed[1], 1)])  # x at 0
    b = ItemStore([ItemState(parsed[1], 0), ItemState(parsed[0], 1)])  # x at 1
    x.value, y.value = "x", "y"
    a.bind()
    b.bind(previous=a)
    a.values[:] = ["x", "y"]  # each store holds each item's own value
    b.values[:] = ["y", "x"]
    seen: set[Any] = set()
    stop = threading.Event()

    def read() -> None:
        while not stop.is_set():
            seen.add(x.value)

    interval = sys.getswitchinterval()
    reader = threading.Thread(target=read)
    sys.setswitchinterval(1e-6)
    reader.start()
    try:
        for n in range(20000):
            store, other = (a, b) if n % 2 else (b, a)
            store.bind(previous=other)
            store.values[:] = ["x", "y"] if store is a else ["y", "x"]
    finally:
        stop.set()
        reader.join()
        sys.setswitchinterval(interval)
    assert seen == {"x"}


@settings(max_examples=200, deadline=None)
@given(st.integers(0, N - 1), st.data())
def test_a_run_of_good_values_is_stored_as_apply_stores_it(first: int,
                                                            data: st.DataObject) -> None:
    """ItemStore.apply_run (a read that changed every item of a block whose items'
    indices run on) against apply() with a (k, value, None) record per item."""
    run = data.draw(st.lists(values, min_size=1, max_size=N - first))
    before = data.draw(st.lists(st.tuples(values, errors), min_size=N, max_size=N))
    states = _states()
    stores = [ItemStore(states), ItemStore(_states())]
    for store in stores:
        store.apply(store.states, [(k, v, e) for k, (v, e) in enumerate(before)], T0, [])
    now = T0 + timedelta(seconds=1)
    by_run: list[DeviceAddressItem] = []
    stores[0].apply_run(first, run, now, states[first:first + len(run)], by_run)
    by_record: list[DeviceAddressItem] = []
    whole = stores[1].states[first:first + len(run)]
    stores[1].apply(whole, [(k, v, None) for k, v in enumerate(run)], now, by_record)
    assert by_run == [s.item for s in states[first:first + len(run)]]
    assert len(by_record) == len(by_run)
    for i in range(N):
        got, want = stores[0].reading(i), stores[1].reading(i)
        assert got[1:] == want[1:]
        assert got.value is want.value or (math.isnan(got.value) and math.isnan(want.value))
    assert len({id(mark) for mark in stores[0].marks[first:first + len(run)]}) == 1


def test_a_run_outside_the_store_is_refused() -> None:
    store = ItemStore(_states())
    with pytest.raises(IndexError, match=r"items 3\.\.4 are outside the store of 4 items"):
        store.apply_run(3, [1.0, 2.0], T0, store.states[3:], [])
    assert store.values == [None] * N  # nothing stored
