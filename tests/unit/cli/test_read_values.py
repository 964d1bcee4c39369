"""``edgemodbus read --host`` prints what the device-file contract says the registers hold:
a pymodbus slave holds random registers, the command (the one-shot read of
cli/oneshot.py, or the polled read it hands --format64 and the rest to) prints a value,
and tests/value_reference.py decodes the same registers independently (byte orders of
every width, Int24, bits, Float32 text, NaN and infinities, Modicon entity numbers).
test_oneshot.py holds the one-shot read equal to the polled one; this holds both to the
contract."""

from __future__ import annotations

import contextlib
import io
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edgemodbus.cli import build_parser
from edgemodbus.cli.exits import CommandFailed
from edgemodbus.cli.oneshot import one_shot_item, read
from tests.peers import PymodbusSlave
from tests.value_reference import decode, float32_text

TYPES = ["UInt16", "Int16", "BCD16", "Int32", "UInt32", "Float", "Int24", "UInt24", "Int64",
         "UInt64", "Double", "Boolean"]
FORMATS64 = ["ABCDEFGH", "BADCFEHG", "CDABGHEF", "DCBAHGFE", "EFGHABCD", "FEHGBADC",
             "GHEFCDAB", "HGFEDCBA"]
# registers a float reads as NaN, an infinity, a negative zero, a denormal, in any order
SPECIAL = [0x7FC0, 0x7F80, 0xFF80, 0x8000, 0x0000, 0x0001, 0xFFFF, 0x7FF8, 0xFFF0, 0x7FF0,
           0x428B, 0x7D5F]
START = 30  # holding register offset 30 = Modicon entity 40031


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("tcp", units=(1,)) as peer:
        yield peer


def _run(words: list[str]) -> tuple[int, str, str]:
    args = build_parser("read").parse_args(["read", *words])
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = read(args)
    return code, out.getvalue(), err.getvalue()


def expected_text(value: Any, data_type: str) -> str:
    """The contract's text: integers in decimal, a Float as the shortest float32
    decimal, a Double as the shortest double, NaN and infinities as Python writes them."""
    if data_type == "Float":
        return float32_text(value)
    if isinstance(value, float):
        return repr(value)
    return str(value)


@settings(max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(registers=st.lists(st.sampled_from(SPECIAL) | st.integers(0, 0xFFFF), min_size=4,
                          max_size=4),
       data_type=st.sampled_from(TYPES), fmt=st.sampled_from(["ABCD", "BADC", "CDAB", "DCBA"]),
       swap=st.booleans(), fmt64=st.none() | st.sampled_from(FORMATS64),
       bit=st.integers(0, 15), entity=st.booleans())
def test_read_prints_what_the_contract_decodes(
        slave: PymodbusSlave, registers: list[int], data_type: str, fmt: str, swap: bool,
        fmt64: str | None, bit: int, entity: bool) -> None:
    slave.set_registers(1, "hr", START, registers)
    where = f"4{START + 1:04d}" if entity else f"hr:{START}"
    if data_type == "Boolean":
        where += f".{bit}"
    words = ["--host", "127.0.0.1", "--port", str(slave.port), "--type", data_type,
             "--format", fmt, *(["--byte-swap16"] if swap else []),
             *(["--format64", fmt64] if fmt64 and data_type in ("Int64", "UInt64", "Double")
               else []),
             *(["--address-prefix", "entity"] if entity else []), "--", where]
    item = {"deviceDataType": data_type, "dataFormat": fmt, "byteSwap16": swap, "bit": bit}
    if fmt64:
        item["dataFormat64"] = fmt64
    ok, value = decode(registers, item, {})
    if not ok:  # a BCD digit over 9: the read fails, naming why
        with pytest.raises(Exception, match="BCD"):
            _run(words)
        return
    code, out, err = _run(words)
    assert code == 0, err
    assert out == expected_text(value, data_type) + "\n", (words, registers, value)
    assert "notice" not in err, err  # --address-prefix entity, or a plain hr: address


def test_an_entity_lookalike_is_read_as_its_offset_with_one_notice(
        slave: PymodbusSlave) -> None:
    """40031 without --address-prefix is holding register offset 40031 (SunSpec's
    numbering; this slave has none there: exception 02), told once on stderr with the
    option; with it, offset 30."""
    slave.set_registers(1, "hr", START, [1234])
    base = ["--host", "127.0.0.1", "--port", str(slave.port)]
    told = io.StringIO()
    with contextlib.redirect_stderr(told), pytest.raises(CommandFailed) as info:
        read(build_parser("read").parse_args(["read", *base, "40031"]))
    assert "FC03 @40031+1" in " ".join(info.value.lines), info.value.lines
    assert told.getvalue().count("notice:") == 1, told.getvalue()
    assert "--address-prefix entity" in told.getvalue(), told.getvalue()
    assert _run([*base, "--address-prefix", "entity", "40031"]) == (0, "1234\n", "")


def test_the_one_shot_read_takes_the_float_nan_and_infinities(slave: PymodbusSlave) -> None:
    """The special floats go the one-shot way (not a fallback) and print as Python
    writes them, a float32 as its shortest decimal."""
    cases = {(0x7FC0, 0x0000): "nan", (0x7F80, 0x0000): "inf", (0xFF80, 0x0000): "-inf",
             (0x428B, 0x7D5F): "69.744865", (0x8000, 0x0000): "-0.0"}
    for regs, text in cases.items():
        slave.set_registers(1, "hr", START, list(regs))
        words = ["--host", "127.0.0.1", "--port", str(slave.port), "--type", "Float",
                 f"hr:{START}"]
        assert one_shot_item(build_parser("read").parse_args(["read", *words])) is not None
        assert _run(words)[1] == text + "\n", regs
