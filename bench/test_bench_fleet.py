"""What a dial-in fleet costs per DTU: one gateway process against three instances behind
HAProxy, the same fleet of simulated DTUs in the same run (docs/deploy.md, "What the fleet
costs").

N DTUs (``DtuFleet``, one slave each, two blocks polled every read cycle of
tests/fleet_gateways.py's ``Timing``) dial either one lone gateway (no ``fleet`` section)
or HAProxy in front of three instances (the documented config, PROXY v2), every instance
with all N device files, as a fleet has.  Once every DTU is polled and a few cycles have
passed, the CPU time (user + system, /proc/<pid>/stat) of the gateway processes is read
over a window: CPU seconds per DTU per second, summed over the instances; HAProxy's and
the simulator's are not the gateway's and are reported apart.  The ratio (three / one) is
gated (bench/gate.py ``fleet.cpu_three_vs_one``): the fleet should cost what one process
costs, per DTU.

Quick mode (``EDGEMODBUS_BENCH_QUICK=1``): 300 DTUs and 10 s windows; else 3,000 and 30 s
(``EDGEMODBUS_BENCH_FLEET`` any count); ``FLEET_ENGINE`` (thread or loop) sets the
listen-mode engine of both (default: the gateway's).  Needs haproxy and mosquitto (``make`` installs
them) and an open-files limit of about four times N.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest
from tests.fleet_gateways import INSTANCES, Fleet, fleet_engine, paced, value_of
from tests.haproxy import HAProxy, local_config
from tests.mosquitto import Mosquitto
from tests.peers import free_port
from tests.waiting import wait_for

from bench import gate
from bench.conftest import QUICK, report, scale
from edgemodbus.datatypes import Area
from edgemodbus.sim import DtuFleet

N = int(os.environ.get("EDGEMODBUS_BENCH_FLEET", "0")) or scale(3000, 300)
WINDOW = float(scale(30, 10))


TICK = os.sysconf("SC_CLK_TCK")


def _cpu(pid: int) -> float:
    """CPU seconds (user + system) of process ``pid`` so far (man 5 proc: utime, stime)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


@contextmanager
def _dialled(tmp: Path, broker: int, instances: int) -> Iterator[tuple[Fleet, Any, DtuFleet]]:
    """The gateways (one lone, or the three of a fleet behind HAProxy) with all N DTUs
    polled; yields the fleet, HAProxy (or None) and the simulator."""
    with ExitStack() as stack:
        # the status check at its default (the tests check departures 2.5x as often)
        mqtt, engine = {"statusCheckInterval": 500}, fleet_engine()
        if instances == 1:
            fleet = Fleet(tmp, broker, N, names=("gw-1",), fleet=False, mqtt=mqtt,
                          engine=engine)
        else:
            fleet = Fleet(tmp, broker, N, mqtt=mqtt, engine=engine)
        fleet.start(stack)
        balancer = None
        port = fleet.listen["gw-1"]
        if instances > 1:
            port = free_port()
            config = local_config(port, [fleet.listen[name] for name in INSTANCES])
            balancer = stack.enter_context(HAProxy(config, tmp / "haproxy.cfg", port))
        sim = DtuFleet("127.0.0.1", port, N, registration="FL{n:06d}", size=128,
                       reconnect=0.5, reconnect_max=2.0, dial_rate=fleet.timing.dial_rate)
        for dtu in sim.dtus:
            dtu.slave(1).set_registers(Area.HOLDING_REGISTER, 0, [value_of(dtu.number)])
        stack.enter_context(sim)
        # every DTU polled, then three more cycles of each: reads as regular as they
        # will be (the simulator's counters, not /metrics: a scrape of an instance is
        # about 6 kB per device file and would be measured too)
        wait_for(paced(lambda: all(d.requests for d in sim.dtus)),
                 timeout=fleet.timing.settle_timeout, what=f"all {N} DTUs polled")
        requests = sim.stats()["requests"]
        wait_for(paced(lambda: sim.stats()["requests"] >= requests + 6 * N),
                 timeout=60 + N / 10, what="three more cycles of every DTU")
        yield fleet, balancer, sim


def _measure(tmp: Path, instances: int) -> dict[str, float]:
    """CPU of the gateway processes per DTU per second, and what else ran meanwhile."""
    tmp.mkdir()
    with Mosquitto(tmp / "broker") as broker, \
            _dialled(tmp, broker.port, instances) as (fleet, balancer, sim):
        pids = [proc.pid for proc in fleet.procs.values()]
        others = [balancer.proc.pid] if balancer is not None else []
        before = [d.requests for d in sim.dtus]
        requests, started = sim.stats()["requests"], time.monotonic()
        cpu = sum(_cpu(pid) for pid in pids)
        other = sum(_cpu(pid) for pid in others)
        sim_cpu = time.process_time()
        time.sleep(WINDOW)  # pacing: the measuring window: CPU is read at both ends
        span = time.monotonic() - started
        cpu = sum(_cpu(pid) for pid in pids) - cpu
        other = sum(_cpu(pid) for pid in others) - other
        done = sim.stats()["requests"] - requests
        silent = sum(1 for d, n in zip(sim.dtus, before, strict=True) if d.requests == n)
        assert not silent, f"{silent} of {N} DTUs not polled during the window"
        return {"cpu_per_dtu_s": cpu / span / N, "requests_per_s": done / span,
                "balancer_cpu_s": other / span,
                "test_process_cpu_s": (time.process_time() - sim_cpu) / span}


@pytest.mark.timeout(300 if QUICK else 1800)  # two fleets started, dialled and measured
def test_fleet_cpu_per_dtu_one_against_three_instances(benchmark: Any, tmp_path: Path) -> None:
    results: dict[int, dict[str, float]] = {}

    def run() -> None:
        results[1] = _measure(tmp_path / "one", 1)
        results[3] = _measure(tmp_path / "three", 3)

    benchmark.pedantic(run, rounds=1, iterations=1)
    one, three = results[1], results[3]
    ratio = three["cpu_per_dtu_s"] / one["cpu_per_dtu_s"]
    rate = three["requests_per_s"] / one["requests_per_s"]
    engine = fleet_engine() or "default"
    report(f"Dial-in fleet, {N} DTUs, engine {engine}, {WINDOW:.0f} s windows "
           "(docs/deploy.md)", [
        ("one gateway: CPU us per DTU per s", one["cpu_per_dtu_s"] * 1e6, "us"),
        ("three instances: CPU us per DTU per s", three["cpu_per_dtu_s"] * 1e6, "us"),
        ("three / one", ratio, "x"),
        ("requests per s, one gateway", one["requests_per_s"], "/s"),
        ("requests per s, three instances", three["requests_per_s"], "/s"),
        ("HAProxy CPU (three instances)", three["balancer_cpu_s"] * 100, "% of a core"),
        ("simulator and test process, one", one["test_process_cpu_s"] * 100, "% of a core"),
        ("simulator and test process, three", three["test_process_cpu_s"] * 100,
         "% of a core"),
    ])
    benchmark.extra_info.update({f"one_{k}": v for k, v in one.items()})
    benchmark.extra_info.update({f"three_{k}": v for k, v in three.items()})
    # the same work in both: otherwise CPU per DTU compares different polling
    assert 0.8 <= rate <= 1.25, f"requests per second, three / one: {rate:.2f}"
    gate.record("fleet.cpu_three_vs_one", ratio)
