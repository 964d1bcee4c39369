"""The engine's fault policy (csrc/emb_fault.c) without I/O.

* How a failed read is handled depends on its kind, decided in C from the errno: it must
  agree with the typed error Python words from the same errno (_ffi/errors.py), for
  every errno (a timeout is retried and ends the slave's cycle, a CRC error is retried,
  an exception response brings the slave back, a link error stops the pass).
* Offline and backoff, pass after pass, against a model written from the rules of
  poll/faults.py's docstring (failed cycles in a row, offline after N, the probe one
  backoff later doubling from the cycle up to maxBackoff, back on an answer).
"""

from __future__ import annotations

import errno as errno_mod
from dataclasses import dataclass, field

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus._ffi.engine import BlockSpec, EngineDevice
from edgemodbus._ffi.errors import error_from_errno
from edgemodbus._ffi.native import ffi, lib
from edgemodbus._ffi.outcomes import ST_AGAIN, ST_BACK, ST_OFFLINE
from edgemodbus.errors import (
    CrcError,
    ModbusConnectionError,
    ModbusExceptionResponse,
    ModbusTimeoutError,
    ProtocolError,
)

NS = 1_000_000_000
ENOBASE = lib.MODBUS_ENOBASE
EMB = lib.EMB_EEXCEPTION  # our errnos start here (csrc/emb_check.h)

errnos = st.one_of(
    st.sampled_from([errno_mod.ETIMEDOUT, errno_mod.ECONNRESET, errno_mod.EPIPE, 0]),
    st.integers(ENOBASE - 2, ENOBASE + 20),
    st.integers(EMB - 2, EMB + 270),
    st.integers(0, 200),
    st.integers(-5, 2**31 - 1),
)


@settings(max_examples=600, deadline=None)
@given(err=errnos)
def test_the_kind_of_a_failure_agrees_with_its_typed_error(err: int) -> None:
    code = ffi.new("int *")
    kind = lib.emb_fault_kind(err, code)
    exc = error_from_errno(err, "read")
    if isinstance(exc, ModbusTimeoutError):
        assert kind == lib.EMB_K_TIMEOUT, (err, exc)
    elif isinstance(exc, CrcError):
        assert kind == lib.EMB_K_CRC, (err, exc)
    elif isinstance(exc, ProtocolError):
        assert kind == lib.EMB_K_PROTOCOL, (err, exc)
    elif isinstance(exc, ModbusExceptionResponse):
        assert (kind, code[0]) == (lib.EMB_K_EXCEPTION, exc.code), (err, exc)
    else:
        assert isinstance(exc, ModbusConnectionError)
        assert kind == lib.EMB_K_LINK, (err, exc)


@dataclass
class Model:
    """The rules, written out (times in ns)."""

    offline_after: int
    cycle: int
    max_backoff: int
    failed: int = 0
    offline: bool = False
    running: bool = False
    backoff: int = 0
    failed_cycles: int = 0  # counted
    events: list[int] = field(default_factory=list)

    def end(self, timed_out: bool, answered: bool, now: int) -> int | None:
        """A pass ended; returns the probe's due time when it set one."""
        if not timed_out:
            self.failed = 0
            if answered and not self.running:
                self.events.append(ST_BACK | (ST_AGAIN if self.offline else 0))
                self.running, self.offline, self.backoff = True, False, self.cycle
            return None
        self.failed += 1
        self.failed_cycles += 1
        if self.failed < self.offline_after:
            return None
        if self.offline:
            self.backoff = min(2 * self.backoff, self.max_backoff)
        else:
            self.offline, self.running = True, False
            self.events.append(ST_OFFLINE)
            self.backoff = min(self.cycle, self.max_backoff)
        return now + self.backoff


outcomes = st.lists(st.sampled_from(["timeout", "answer", "garbage"]), max_size=40)


@settings(max_examples=300, deadline=None)
@given(steps=outcomes, offline_after=st.integers(1, 4),
       cycle_ms=st.sampled_from([10, 100, 1000]), max_ms=st.sampled_from([5, 100, 800, 60000]))
def test_offline_and_backoff_follow_the_rules(steps: list[str], offline_after: int,
                                              cycle_ms: int, max_ms: int) -> None:
    dev = EngineDevice(slave=1, timeout=0.1, report_all=False, cycle=cycle_ms / 1000)
    dev.set_policy(0, offline_after, max_ms / 1000)
    dev.set_blocks([BlockSpec(3, 0, 2, cycle_ms / 1000, None, False),
                    BlockSpec(3, 10, 2, cycle_ms / 1000, None, False)])
    model = Model(offline_after, cycle_ms * NS // 1000, max_ms * NS // 1000,
                  backoff=cycle_ms * NS // 1000)
    now = 1000 * NS
    raw = dev._dev
    for step in steps:
        dev.begin_pass(now / NS)
        raw.timed_out = 1 if step == "timeout" else 0
        raw.answered = 1 if step == "answer" else 0
        now += 3_000_000
        dev.end_pass(now / NS)
        lib.emb_fault_end_pass(raw, now)
        due = model.end(step == "timeout", step == "answer", now)
        events = dev.take_status()
        if model.events:
            assert events == model.events[-1] and len(model.events) == 1, (events, model)
            model.events.clear()
        else:
            assert events == 0
        assert (dev.failed_cycles, dev.offline) == (model.failed, model.offline)
        if model.offline or model.running:
            assert round(dev.backoff * NS) == model.backoff
        if due is not None:  # the probe: every block due one backoff later
            assert [round(dev.due_of(k) * NS) for k in range(2)] == [due, due]
            assert round(dev.due * NS) == due
        now = max(now, round(dev.due * NS))
    assert dev.counts().failed_cycles == model.failed_cycles
