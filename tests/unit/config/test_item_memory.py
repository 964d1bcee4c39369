"""Memory per tag: a DeviceAddressItem and the driver's ItemState stay small (a gateway
holds one of each per tag), with the public behaviour of the item unchanged."""

from __future__ import annotations

import gc
import tracemalloc
from collections.abc import Callable
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.codec import BlockDecoder
from edgemodbus.config import ConfigError, DeviceAddressItem, DeviceConfig
from edgemodbus.datatypes import DataType, ItemStatus
from edgemodbus.poll.items import ItemState, Slot, shared_offset
from edgemodbus.poll.schedule import build_plan

N = 2000


def _device(n: int, slave: int = 1) -> dict[str, Any]:
    """``n`` tags of the usual kinds, with a description and unit like a real map."""
    kinds: list[tuple[str, int, dict[str, Any]]] = [
        ("Int16", 1, {}),
        ("Float", 2, {"dataFormat": "CDAB"}),
        ("UInt16", 1, {"dataMultiplier": 0.1, "convertedDataType": "Float"}),
        ("Int32", 2, {}),
    ]
    items: list[dict[str, Any]] = []
    offset = 0
    for k in range(n):
        kind, regs, extra = kinds[k % len(kinds)]
        items.append({"name": f"s{slave}_t{k}", "address": f"hr:{offset}",
                      "deviceDataType": kind, "description": "phase voltage", "unit": "V",
                      **extra})
        offset += regs
    return {"communication": {"slaveId": slave}, "addressList": items}


def _traced_bytes(make: Callable[[], object]) -> tuple[object, int]:
    """What ``make`` returns and the bytes it allocated that are still held."""
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        made = make()
        gc.collect()
        after = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    return made, after - before


def test_loaded_items_take_under_300_bytes_each() -> None:
    data = [_device(N, s) for s in (1, 2)]  # two devices of one kind: addresses recur
    em.load_device_config(_device(8))  # imports and one-off caches
    # the least of three loads: tracemalloc also counts what other threads allocate
    # meanwhile (one full run on a loaded machine measured 666 B/item once; never alone)
    held = min(_traced_bytes(lambda: [em.load_device_config(d) for d in data])[1]
               for _ in range(3))
    # a BaseModel item took about 800 (its __dict__ and fields-set); a slotted one 168
    # plus its name
    assert held / (2 * N) < 300


def test_item_states_take_under_100_bytes_each() -> None:
    parsed = em.load_device_config(_device(N)).parsed_items()
    states, held = _traced_bytes(lambda: [ItemState(p) for p in parsed])
    assert held / N < 100  # was 192: a ValueSpec per item besides the state
    assert isinstance(states, list)
    kinds = {id(s.kind) for s in states}
    assert len(kinds) == 4  # one per kind of tag, shared


def _poll_state(cfg: DeviceConfig) -> tuple[list[ItemState], list[Slot]]:
    """What a poller keeps of a device, built the way it builds it: the item states, the
    read plan and a slot with its decoder per block."""
    parsed = cfg.parsed_items()
    states = [ItemState(p) for p in parsed]
    slots: list[Slot] = []
    for block in build_plan(parsed, cfg.communication):
        whole = [states[p.key] for p in block.pieces if isinstance(p.key, int)]
        decoder = BlockDecoder(block.area, block.count,
                               [(p.block_offset, s.shape) for p, s in zip(block.pieces, whole,
                                                                          strict=True)])
        slots.append(Slot(block, whole, decoder, []))
    return states, slots


def test_poll_state_takes_under_200_bytes_per_item() -> None:
    """The Python side of what polling keeps per tag (the decoders' C arrays come on
    top, see bench/test_bench_driver.py): item state, plan and decoder, for two devices
    of one kind."""
    configs = [em.load_device_config(_device(N, s)) for s in (1, 2)]
    _poll_state(em.load_device_config(_device(8)))  # imports and one-off caches
    kept, held = _traced_bytes(lambda: [_poll_state(c) for c in configs])
    assert isinstance(kept, list)
    # was 404: a Piece per item in the plan, and per item in each decoder a tuple of
    # where its value is, its spec, offset and index, and its own offset int; 205 since
    # an item state holds its index in the store (poll/store.py): 8 bytes more asked,
    # in the same 64-byte block of pymalloc
    assert held / (2 * N) < 210


def test_items_at_one_offset_share_one_int() -> None:
    """Devices of one kind repeat the same offsets: their item states share the ints."""
    first, second = (em.load_device_config(_device(300, s)).parsed_items() for s in (1, 2))
    offset = first[-1].address.offset
    assert offset > 256 and second[-1].address.offset == offset
    assert first[-1].address.offset is not second[-1].address.offset  # parsed apart
    a, b = ItemState(first[-1]), ItemState(second[-1])
    assert a.offset == offset and a.offset is b.offset
    assert shared_offset(70000) == 70000 and shared_offset(-1) == -1  # outside: as given


def test_item_has_no_dict_and_keeps_the_model_api() -> None:
    item = em.DeviceAddressItem(name="t", address="hr:1", device_data_type="Int16",
                                description="x")
    assert not hasattr(item, "__dict__")
    assert item.device_data_type is DataType.INT16
    item.value, item.status = 7, ItemStatus.OK  # runtime state: plain assignment
    assert (item.value, item.status) == (7, ItemStatus.OK)
    data = item.to_dict()
    assert data["deviceDataType"] == "Int16" and data["value"] == 7
    assert data == item.model_dump(mode="json", by_alias=True)
    assert DeviceAddressItem.model_validate(data) == item
    copied = item.model_copy(deep=True, update={"unit": "V"})
    assert copied is not item and copied.unit == "V" and item.unit == ""
    assert set(DeviceAddressItem.model_fields) >= {"name", "address", "value", "status"}
    assert DeviceAddressItem.model_fields["device_data_type"].alias == "deviceDataType"


def test_repeated_text_is_shared_between_items() -> None:
    a, b = em.load_device_config(_device(2, 1)), em.load_device_config(_device(2, 2))
    first, second = a.address_list[1], b.address_list[1]
    assert first.address is second.address
    assert first.description is second.description and first.unit is second.unit


@pytest.mark.parametrize("bad", ["x", 3, None, [1]])
def test_an_item_that_is_not_an_object_is_refused_with_its_path(bad: Any) -> None:
    with pytest.raises(ConfigError) as info:
        em.load_device_config({"addressList": [bad]})
    assert [str(p) for p in info.value.problems] == [
        f"addressList[0] {bad!r}: must be an object ({{...}})"
    ]


def test_keyword_spellings_in_a_call_are_the_json_keys_spellings() -> None:
    item = em.DeviceAddressItem(Name="t", Address="hr:1", DeviceDataType="float",
                                dataFormat="CDAB")
    assert (item.name, item.device_data_type) == ("t", DataType.FLOAT)
    with pytest.raises(ValueError, match="quantity"):
        em.DeviceAddressItem(name="t", address="hr:1", device_data_type="Int16", quantity=0)
