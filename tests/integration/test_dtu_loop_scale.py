"""The loop engine at scale (issue #27, line/loop.py): 200 DTUs from the fleet simulator
(``edgemodbus simulate --dial ... --dtus N``, a process of its own) dial in to drivers
whose DTU lines run on two loop threads; the process keeps a handful of threads, not
one per DTU, and every value is exact.  The same run on the thread engine gives the
figures to compare (printed: ``-s``; docs/scale.md quotes them)."""

from __future__ import annotations

import resource
import signal
import subprocess
import sys
import threading

import pytest

from edgemodbus.sim import default_register
from tests.integration.test_dtu import dtu_device, free_port, ok, running, values
from tests.waiting import wait_for

N = 200
TAGS = 3  # items per device (tests/integration/test_dtu.py dtu_device: hr 0, 1, 7)


def proc_status(key: str) -> int:
    """A count from /proc/self/status (Threads: as the kernel counts them; VmRSS: kB)."""
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith(key))


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


@pytest.mark.parametrize("engine", ["loop", "thread"])
def test_two_hundred_dtus_read_exact_values_on_a_handful_of_threads(engine: str) -> None:
    port = free_port()
    cfgs = [dtu_device(port, f"L{k:03d}", 1, registrationTimeout=5000, readCycle=1000,
                       readTimeout=1000, engine=engine, loopThreads=2) for k in range(N)]
    threads, rss = proc_status("Threads:"), proc_status("VmRSS:")
    with running(*cfgs) as drivers:
        proc = subprocess.Popen(
            [sys.executable, "-m", "edgemodbus.cli", "simulate", "--dial", f"127.0.0.1:{port}",
             "--dtus", str(N), "--registration", "L{n:03d}", "--slaves", "1", "--size", "16"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )
        try:
            for cfg in cfgs:
                wait_for(ok(cfg), timeout=90, what=f"{cfg.organization.device_code} Ok")
            cpu = cpu_seconds()
            before = [int(d.stats()["requests"]) for d in drivers]
            for d, n in zip(drivers, before, strict=True):  # five more passes of each
                wait_for(lambda d=d, n=n: int(d.stats()["requests"]) >= n + 5, timeout=60,
                         what="five more passes")
            reads = sum(int(d.stats()["requests"]) for d in drivers) - sum(before)
            cpu = cpu_seconds() - cpu
            for cfg in cfgs:
                assert values(cfg) == [default_register(1, a) for a in (0, 1, 7)]
            added = proc_status("Threads:") - threads
            print(f"\n{engine} engine, {N} DTUs: +{added} threads, RSS "
                  f"+{(proc_status('VmRSS:') - rss) / N:.1f} kB per DTU, "
                  f"{cpu / (reads * TAGS) * 1e6:.0f} us CPU per tag ({reads} reads)")
            if engine == "loop":  # two loop threads and the listener's: not one per DTU
                assert added <= 5, [t.name for t in threading.enumerate()]
            else:
                assert added >= N
        finally:
            proc.send_signal(signal.SIGINT)
            proc.communicate(timeout=30)
