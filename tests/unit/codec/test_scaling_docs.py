"""docs/engineering-units.md's examples load as written and read and write the values
the page says they do."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from edgemodbus._ffi import Block
from edgemodbus.codec import BlockDecoder, ValueSpec, encode
from edgemodbus.config import load_device_config, validate_items
from edgemodbus.datatypes import Area

PAGE = Path(__file__).resolve().parents[3] / "docs" / "engineering-units.md"


def page_items() -> dict[str, dict[str, Any]]:
    """Every item of the page's JSON examples, by name."""
    items: dict[str, dict[str, Any]] = {}
    for block in re.findall(r"```json\n(.*?)```", PAGE.read_text("utf-8"), re.S):
        for item in json.loads(f"[{block.strip().rstrip(',')}]"):
            items[item["name"]] = item
    return items


def specs(*names: str) -> dict[str, ValueSpec]:
    items = page_items()
    cfg = load_device_config({"addressList": [items[n] for n in names]})
    return {p.name: p.value_spec() for p in validate_items(cfg.address_list, cfg.communication)}


def read(spec: ValueSpec, registers: list[int]) -> Any:
    area = Area.INPUT_REGISTER if spec.name == "TankLevel" else Area.HOLDING_REGISTER
    [(_, value, error)] = BlockDecoder(area, len(registers), [(0, spec)]).decode(
        Block.from_values(registers, bits=False))
    return value if error is None else error


def test_the_sunspec_example_reads_12_34() -> None:
    s = specs("W", "W_SF", "Hz", "Hz_SF")
    decoder = BlockDecoder(Area.HOLDING_REGISTER, 4, [(0, s["W"]), (1, s["W_SF"]),
                                                      (2, s["Hz"]), (3, s["Hz_SF"])])
    got = decoder.decode(Block.from_values([1234, 0xFFFE, 5000, 0xFFFE], bits=False))
    assert got == [(0, 12.34, None), (1, -2, None), (2, 50.0, None), (3, -2, None)]


def test_the_4_20_ma_examples() -> None:
    s = specs("TankLevel", "LoopCurrent", "Temp")
    assert read(s["TankLevel"], [13824]) == 2.5
    assert read(s["TankLevel"], [32767]) == "raw value 32767 outside rawMin..rawMax (0..27648)"
    assert read(s["LoopCurrent"], [32767]) == 20.0
    assert read(s["Temp"], [650]) == 25.0
    assert encode(s["Temp"], 25.5) == [655]
