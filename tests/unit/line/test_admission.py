"""The listener's bookkeeping, no I/O: allow-lists, caps, byte budget, key check, and
the log limiter (a flood of events becomes a few lines and one summary)."""

from __future__ import annotations

import logging

import pytest
from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.line.admission import ByteBudget, Networks, Unregistered, key_matches
from edgemodbus.line.log_limit import LogLimiter, hex_prefix, short_text


def test_networks_allow_cidr_v4_v6_and_mapped_addresses() -> None:
    nets = Networks(["10.0.0.0/8", "192.168.1.7", "2001:db8::/32"], "listenAllowFrom")
    assert nets.allows("10.1.2.3")
    assert nets.allows("192.168.1.7")
    assert not nets.allows("192.168.1.8")
    assert nets.allows("2001:db8::5")
    assert not nets.allows("2001:db9::5")
    assert nets.allows("::ffff:10.0.0.9")  # an IPv4 peer on an IPv6 socket
    assert not nets.allows("not an address")
    assert Networks([], "x").allows("203.0.113.1")  # empty: any


def test_a_bad_network_names_field_and_value() -> None:
    with pytest.raises(ValueError, match=r"dtuAllowFrom: '10\.0\.0\.300/8' is not an IPv4"):
        Networks(["10.0.0.300/8"], "dtuAllowFrom")


def test_caps_per_port_and_per_source() -> None:
    caps = Unregistered(per_port=3, per_source=2)
    caps.add("10.0.0.1")
    caps.add("10.0.0.1")
    refusal = caps.refusal("10.0.0.1")
    assert refusal is not None and refusal[0] == "refusedSourceCap"
    assert caps.refusal("10.0.0.2") is None
    caps.add("10.0.0.2")
    refusal = caps.refusal("10.0.0.3")
    assert refusal is not None and refusal[0] == "refusedPortCap"
    caps.remove("10.0.0.1")
    assert caps.refusal("10.0.0.1") is None
    caps.remove("10.0.0.1")
    caps.remove("10.0.0.2")
    assert caps.total == 0 and not caps._by_source  # no source kept once gone


@given(st.lists(st.tuples(st.floats(0, 2), st.integers(1, 300)), max_size=40),
       st.integers(1, 5000), st.integers(1, 256))
def test_byte_budget_never_lets_more_than_burst_plus_rate_times_time(
        reads: list[tuple[float, int]], rate: int, burst: int) -> None:
    """Reading only when not paused, what was read never exceeds burst + rate * t."""
    budget = ByteBudget(rate, burst, 0.0)
    now = 0.0
    total = 0
    for gap, n in reads:
        now += gap
        total += n
        pause = budget.spend(n, now)
        assert total <= burst + rate * now + 1e-6 or pause > 0
        now += pause  # the reader waits that long before the next read
        assert total <= burst + rate * now + 1e-6


def test_no_rate_means_no_pause() -> None:
    assert ByteBudget(0, 64, 0.0).spend(10**6, 0.0) == 0.0


def test_key_matches_only_the_exact_key() -> None:
    assert key_matches(b"s3cret", b"s3cret")
    assert not key_matches(b"s3cre", b"s3cret")
    assert not key_matches(b"s3cretX", b"s3cret")
    assert not key_matches(None, b"s3cret")


def test_hex_prefix_and_short_text_bound_untrusted_bytes() -> None:
    assert hex_prefix(b"") == "nothing"
    assert hex_prefix(b"\x01\x02") == "01 02"
    shown = hex_prefix(bytes(range(256)) * 4000)
    assert shown.endswith("(+1023984 bytes)") and len(shown) < 80
    assert len(short_text("x" * 10**6)) < 60


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_the_limiter_logs_a_burst_then_one_summary_per_interval(
        caplog: pytest.LogCaptureFixture) -> None:
    clock = _Clock()
    limiter = LogLimiter(logging.getLogger("edgemodbus.test"), interval=10, burst=3,
                         clock=clock)
    with caplog.at_level(logging.WARNING, "edgemodbus.test"):
        for i in range(10_000):
            clock.now = i * 0.0005
            limiter.event(logging.WARNING, "connections refused (cap)",
                          "10.0.0.9" if i % 10 else "10.0.0.7", "refused %d", i)
            limiter.flush()
        assert len(caplog.records) == 3
        clock.now = 10.0
        limiter.flush()
    assert len(caplog.records) == 4
    summary = caplog.records[-1].getMessage()
    assert summary.startswith("9997 more connections refused (cap) in the last 10 s: ")
    assert "10.0.0.9 x8998" in summary and "10.0.0.7 x999" in summary  # 3 logged
    assert limiter.suppressed == 9997
    assert limiter.next_due() == float("inf")


def test_the_limiter_bounds_the_sources_it_names(caplog: pytest.LogCaptureFixture) -> None:
    clock = _Clock()
    limiter = LogLimiter(logging.getLogger("edgemodbus.test"), burst=1, clock=clock)
    with caplog.at_level(logging.WARNING, "edgemodbus.test"):
        for i in range(5000):
            limiter.event(logging.WARNING, "refusals", f"10.0.{i // 256}.{i % 256}", "x")
        limiter.flush(force=True)
    entries = list(limiter._kinds.values())
    assert not entries  # flushed
    summary = caplog.records[-1].getMessage()
    assert "4999 more refusals" in summary and "others x" in summary
    assert len(summary) < 300
