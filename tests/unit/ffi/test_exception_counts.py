"""The engine's exception counters (csrc/emb_fault.c emb_exc_count, emb_exc_counts in
csrc/emb_edev.h): the first EMB_EXC_SLOTS distinct codes counted apart, every later code
in the "other" bucket, against a model written here from that rule; and what a device's
and a line's ``stats()`` read from them (_ffi/outcomes.py exception_counts)."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus._ffi.native import ffi, lib
from edgemodbus._ffi.outcomes import LineCounters, exception_counts
from edgemodbus.stats import LineStats

SLOTS = int(lib.EMB_EXC_SLOTS)


def _model(codes: list[int]) -> tuple[dict[int, int], int]:
    apart: dict[int, int] = {}
    other = 0
    for code in codes:
        if code in apart or len(apart) < SLOTS:
            apart[code] = apart.get(code, 0) + 1
        else:
            other += 1
    return apart, other


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(st.integers(1, 11), st.integers(0, 255)), max_size=60))
def test_codes_are_counted_apart_up_to_the_slots_then_in_other(codes: list[int]) -> None:
    x = ffi.new("emb_exc_counts *")
    for code in codes:
        lib.emb_exc_count(x, code)
    apart, other = _model(codes)
    assert exception_counts(x[0]) == tuple(sorted(apart.items()))
    assert x.other == other


def test_a_line_reports_the_codes_seen_and_the_rest() -> None:
    """The same ``exceptions`` by code as with a count per code (Modbus Application
    Protocol 1.1b3, section 7: 01-06, 08, 0A, 0B defined), and ``exceptionsOther``."""
    counters = LineCounters()
    lc = counters._lc
    seen = [2, 2, 4, 0x0B, 1, 3, 5, 6, 8, 0x0A, 2]  # nine distinct codes: the ninth, 0A, in other
    for code in seen:
        lib.emb_exc_count(ffi.addressof(lc, "exceptions"), code)
    stats = LineStats(native=counters.counts).as_dict()
    assert stats["exceptions"] == {1: 1, 2: 3, 3: 1, 4: 1, 5: 1, 6: 1, 8: 1, 0x0B: 1}
    assert stats["exceptionsOther"] == 1
    assert ffi.sizeof("emb_exc_counts") <= 96  # was 256 counts of 8 bytes: 2 kB
