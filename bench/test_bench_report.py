"""Issue 30: report by period (reportEvery) costs nothing for devices that do not use it.

10 slaves x 200 tags over RTU-over-TCP (the simulator in its own process, 1% of the
values changing on every read, readCycle 10 ms: the line always busy), client CPU per
tag read (this process, all threads), in one run, windows alternating:

* ``plain``: no item has a period (every device as before period reports; its passes end in
  ``Poller._cycle_done``, which looks for a heap it does not have);
* ``before``: the same drivers with that pass-end hook taken out (``Poller._cycle_done``
  replaced by :func:`_cycle_done_without_periods`, the code before period reports), so
  the two are the same devices, line, slave and moment;
* ``periodic``: the same tags where every tenth item of half of the devices has
  ``reportEvery: 1000`` (its period reports counted, from the callbacks).

The figures go to the table and to ``benchmark.extra_info``; nothing is asserted but
that the period reports happened.
"""

from __future__ import annotations

import copy
import statistics
import threading
from typing import Any

import edgemodbus as em
from bench.conftest import QUICK, report, scale
from bench.slave_process import SimulatorProcess
from bench.test_bench_driver import (
    Drivers,
    Line,
    Window,
    device_dict,
    flip_ranges,
    initial_registers,
    make_tags,
    measure_driver,
)
from edgemodbus.poll.poller import Poller

SLAVES = list(range(1, 11))
TAGS = 200


def _cycle_done_without_periods(self: Poller, now: float) -> None:
    """Poller._cycle_done without the period reports' check (the baseline)."""
    self.delivery.flush()
    if self.snapshot_interval and now >= self.next_snapshot:
        self._snapshot(now)


def _periodic(config: dict[str, Any]) -> dict[str, Any]:
    periodic = copy.deepcopy(config)
    for k, item in enumerate(periodic["addressList"]):
        if k % 10 == 0:
            item["reportEvery"] = 1000
    return periodic


def test_report_every_costs_nothing_for_devices_without_it(benchmark: Any) -> None:
    repeats = scale(5, 2)
    window = 1.5 if not QUICK else 0.5
    with SimulatorProcess(SLAVES, size=1000) as sim:
        tags = {s: make_tags(s, TAGS) for s in SLAVES}
        sim.set_registers([w for s in SLAVES for w in initial_registers(s, tags[s])])
        plain = {s: device_dict(sim.port, s, tags[s]) for s in SLAVES}
        mixed = {s: _periodic(plain[s]) if s % 2 else plain[s] for s in SLAVES}
        configs = {s: em.load_device_config(c) for s, c in plain.items()}
        line = Line(sim, tags, configs, [])
        with Drivers(configs) as drivers:
            line.blocks = [(s, b["start"], b["count"], [])
                           for s, drv in zip(SLAVES, drivers.drivers, strict=True)
                           for b in drv.read_plan()]
        sim.flip(flip_ranges(line, 0.01))
        runs: dict[str, list[Window]] = {"plain": [], "before": [], "periodic": []}
        pairs: list[float] = []
        hook = Poller._cycle_done
        with Drivers(configs) as drivers:
            for _ in range(repeats):
                ours = measure_driver(drivers, window)
                Poller._cycle_done = _cycle_done_without_periods  # type: ignore[method-assign]
                try:
                    before = measure_driver(drivers, window)
                finally:
                    Poller._cycle_done = hook  # type: ignore[method-assign]
                runs["plain"].append(ours)
                runs["before"].append(before)
                pairs.append(ours.us_per_tag / before.us_per_tag)
            benchmark.pedantic(lambda: measure_driver(drivers, 0.2), rounds=1, iterations=1)
        reported = [0]
        lock = threading.Lock()

        def count(item: em.DeviceAddressItem) -> None:
            if item.report_every is not None:
                with lock:
                    reported[0] += 1

        with Drivers({s: em.load_device_config(c) for s, c in mixed.items()}) as drivers:
            for drv in drivers.drivers:
                drv.address_updated_callback = count
            for _ in range(repeats):
                runs["periodic"].append(measure_driver(drivers, window))
        sim.flip([])

    def best(key: str) -> Window:
        return min(runs[key], key=lambda w: w.us_per_tag)

    periodic_items = sum(1 for s in SLAVES if s % 2 for k in range(TAGS) if k % 10 == 0)
    info: dict[str, Any] = {
        "tags": len(SLAVES) * TAGS,
        "plain_us_per_tag": best("plain").us_per_tag,
        "before_us_per_tag": best("before").us_per_tag,
        "periodic_us_per_tag": best("periodic").us_per_tag,
        "paired_median_plain_vs_before": statistics.median(pairs),
        "periodic_items": periodic_items,
        "period_reports": reported[0],
        "all_us_per_tag": {k: [round(w.us_per_tag, 4) for w in v] for k, v in runs.items()},
    }
    benchmark.extra_info.update(info)
    report(
        f"client CPU per tag read, {len(SLAVES)} slaves x {TAGS} tags, 1% changing, "
        f"readCycle 10 ms (best of {repeats})",
        [
            ("before: pass end without the period hook", info["before_us_per_tag"], "us/tag"),
            ("plain: no item with reportEvery", info["plain_us_per_tag"], "us/tag"),
            ("    plain / before, median of paired windows",
             info["paired_median_plain_vs_before"], "x"),
            (f"periodic: {periodic_items} items reportEvery 1000 ms",
             info["periodic_us_per_tag"], "us/tag"),
            ("    period reports seen (callbacks)", float(reported[0]), ""),
        ],
    )
    assert reported[0] > 0
