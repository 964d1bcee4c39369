"""Memory per DTU on the loop engine (issue #27, docs/scale.md "Memory per DTU"): what a
started listen-mode DTU driver allocates in Python, and the layout choices behind it
(slots on the per-line objects, the communication parameters not copied)."""

from __future__ import annotations

import gc
import logging
import tracemalloc

import pytest

from edgemodbus.config import effective_parameters
from edgemodbus.config.device import DeviceOrganizationParameter
from edgemodbus.line.loop import LoopLine
from edgemodbus.sim import Simulator
from edgemodbus.stats import DeviceStats, LineStats
from tests.integration.test_dtu import dtu_device, free_port, ok, running
from tests.waiting import wait_for

N = 200
TAGS = 20  # the bench's device (bench/test_bench_dtu_5000.py): 1 slave x 20 UInt16 tags
# Python bytes per started DTU driver, none dialled in (tracemalloc, every thread, here:
# reconnectInterval 300 ms, so the items' "not connected" reasons are written): 21.2-21.4 kB
# before the per-line objects took slots and the parameters stopped being copied, 14.1 kB
# after (docs/scale.md "Memory per DTU"); 13.7 kB with the engine's exception counters
# in 80 bytes (csrc/emb_edev.h emb_exc_counts).
MAX_BYTES_PER_DTU = 15_000
DIALLED = 20
# What dialling in adds per plain DTU in the binding's allocations (src/edgemodbus/_ffi:
# the context, its link and stream buffers, the decoder's state): 1.66 kB, where every
# stream link's 4 kB report ring alone put it above 5.7 kB before.
MAX_FFI_BYTES_PER_DIALLED_DTU = 2_500


def test_a_started_loop_dtu_driver_costs_at_most_15_kB_of_python_objects(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.CRITICAL, logger="edgemodbus")  # kept log records are not ours
    port = free_port()
    cfgs = [dtu_device(port, f"M{k:04d}", 1, addresses=tuple(range(TAGS)), readCycle=5000,
                       registrationTimeout=5000, engine="loop") for k in range(N)]
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        with running(*cfgs) as drivers:
            gc.collect()
            per_dtu = (tracemalloc.get_traced_memory()[0] - before) / N
            assert all(d.stats()["line"]["connects"] == 0 for d in drivers)  # none dialled
    finally:
        tracemalloc.stop()
    assert per_dtu <= MAX_BYTES_PER_DTU, f"{per_dtu:.0f} B per DTU"


def test_a_dialled_in_plain_dtu_allocates_little_in_the_binding(
        caplog: pytest.LogCaptureFixture) -> None:
    """A plain DTU stream gets its 512 B receive buffer and no report ring; the engine's
    exception counters are 80 B, not 2 kB, per device and per line.  Counted from the
    allocation sites in src/edgemodbus/_ffi (cffi's buffers are traced where made), so
    the simulator's own objects stay out of it."""
    caplog.set_level(logging.CRITICAL, logger="edgemodbus")
    port = free_port()
    cfgs = [dtu_device(port, f"D{k:04d}", 1, addresses=tuple(range(TAGS)), readCycle=5000,
                       engine="loop") for k in range(DIALLED)]
    ffi_only = [tracemalloc.Filter(True, "*/edgemodbus/_ffi/*")]
    gc.collect()
    tracemalloc.start()
    try:
        with Simulator(slaves=[1]) as sim, running(*cfgs):
            gc.collect()
            before = tracemalloc.take_snapshot().filter_traces(ffi_only)
            for cfg in cfgs:
                sim.dial("127.0.0.1", port, registration=cfg.communication.dtu_id.encode())
            for cfg in cfgs:
                wait_for(ok(cfg), what=f"{cfg.organization.device_code} Ok")
            gc.collect()
            after = tracemalloc.take_snapshot().filter_traces(ffi_only)
    finally:
        tracemalloc.stop()
    grown = sum(d.size_diff for d in after.compare_to(before, "filename"))
    per_dtu = grown / DIALLED
    assert per_dtu <= MAX_FFI_BYTES_PER_DIALLED_DTU, f"{per_dtu:.0f} B per dialled DTU"


def test_per_line_objects_have_no_instance_dict() -> None:
    line_stats, device_stats = LineStats(), DeviceStats()
    assert not hasattr(line_stats, "__dict__") and not hasattr(device_stats, "__dict__")
    assert "__dict__" not in dir(LoopLine)
    # the counters read the same through the slots (and their native source)
    line_stats.link_errors, device_stats.writes = 3, 2
    assert line_stats.as_dict()["linkErrors"] == 3 and line_stats.as_dict()["requests"] == 0
    assert device_stats.as_dict()["writes"] == 2 and "cycleTimeHistogram" in device_stats.as_dict()


def test_effective_parameters_copy_only_what_the_organisation_overrides() -> None:
    cfg = dtu_device(free_port(), "P0001", 1, readCycle=5000)
    comm = cfg.communication
    # nothing to override: the driver keeps the validated model itself (no 2.3 kB copy)
    assert effective_parameters(None, comm) is comm
    assert effective_parameters(DeviceOrganizationParameter(deviceCode="x"), comm) is comm
    # an override: a copy with it applied, the device file's model unchanged
    org = DeviceOrganizationParameter(deviceCode="x", readCycle=700)
    params = effective_parameters(org, comm)
    assert params is not comm and params.read_cycle == 700 and comm.read_cycle == 5000
    assert params.dtu_id == comm.dtu_id
