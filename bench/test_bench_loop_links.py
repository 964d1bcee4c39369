"""The loop engine's links against the thread engine, in the same run.

N plain RTU DTU streams (1 slave x 10 holding registers each, one read per pass, 5 s
cycle) connected to one pymodbus slave in a process of its own (RTU over TCP), served
(a) by one loop thread (csrc/emb_loop_link.c via _ffi/loop.py: this test's thread) and
(b) by the blocking line engine with one thread per link (csrc/emb_engine.c, as a
LineWorker runs it).  Reported for each: threads of this process, RSS per link, CPU per
read (this process only), reads, timeouts and wrong values.  This measures the engines
alone: no pollers, items or listeners (the LoopWorker that delivers passes to them is
not built yet, docs/scale.md).

Quick mode: 50 links for 6 s.  ``EDGEMODBUS_BENCH_LINKS`` sets the count (the full run:
1,000; pymodbus in one process answers about 1,000 reads a second, so 5,000 links need
``EDGEMODBUS_BENCH_CYCLE_MS`` of 10000 or more), ``EDGEMODBUS_BENCH_SECONDS`` the time.
"""

from __future__ import annotations

import os
import resource
import threading
import time
from typing import Any

from tests.integration.test_loop_link import Dtu, dtus, serve
from tests.peers import PymodbusSlave, default_register

from bench.conftest import cpu_seconds, report, scale
from edgemodbus._ffi.engine import EV_CYCLE as ENGINE_CYCLE
from edgemodbus._ffi.engine import BlockSpec
from edgemodbus._ffi.loop import Loop

N = int(os.environ.get("EDGEMODBUS_BENCH_LINKS", scale(1000, 50)))
SECONDS = float(os.environ.get("EDGEMODBUS_BENCH_SECONDS", scale(20, 6)))
CYCLE = int(os.environ.get("EDGEMODBUS_BENCH_CYCLE_MS", 5000)) / 1000


def _memory() -> tuple[int, int]:
    """(address space, RSS) of this process, bytes."""
    with open("/proc/self/statm") as f:
        size, rss = f.read().split()[:2]
    page = os.sysconf("SC_PAGE_SIZE")
    return int(size) * page, int(rss) * page


def _start(i: int) -> int:
    return 10 * (i % 50)


def _plan(links: list[Dtu]) -> None:
    for i, d in enumerate(links):
        d.device.cycle = CYCLE
        d.device.set_blocks([BlockSpec(3, _start(i), 10, CYCLE, None, True)])


def _wrong(links: list[Dtu]) -> int:
    wrong = 0
    for i, d in enumerate(links):
        block = d.device.data(0)
        want = [default_register(1, "hr", a) for a in range(_start(i), _start(i) + 10)]
        wrong += block is None or block.to_list() != want
    return wrong


def _threads_run(links: list[Dtu], until: float) -> tuple[int, tuple[int, int]]:
    """One thread per link running the blocking engine: the threads alive and the
    memory once they all run."""
    def run(d: Dtu) -> None:
        while time.monotonic() < until:
            if d.engine.run(until) == ENGINE_CYCLE:
                d.passes += len(d.engine.take_ended())

    threads = [threading.Thread(target=run, args=(d,), daemon=True) for d in links]
    for t in threads:
        t.start()
    most = len(os.listdir("/proc/self/task"))
    memory = _memory()
    for t in threads:
        t.join(timeout=until - time.monotonic() + 30)
    assert not any(t.is_alive() for t in threads)
    return most, memory


def test_loop_links_against_thread_links(benchmark: Any) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < 4 * N + 100:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, 4 * N + 100), hard))
    rows: list[tuple[str, float, str]] = []
    results: dict[str, tuple[int, int]] = {}
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        benchmark.pedantic(lambda: _measure(slave.port, rows, results), rounds=1,
                           iterations=1)
    benchmark.extra_info.update({name: value for name, value, _ in rows})
    report(f"{N} DTU streams, 10 registers each, {CYCLE:.0f} s cycle", rows)
    for engine, (reads, wrong) in results.items():
        assert wrong == 0, engine
        assert reads >= N, engine


def _measure(port: int, rows: list[tuple[str, float, str]],
             results: dict[str, tuple[int, int]]) -> None:
    """Both engines, one after the other, on the same slave: rows and results filled."""
    for engine in ("loop", "thread"):
        with Loop(N) as loop:
            vm0, rss0 = _memory()
            with dtus(loop, port, [(1, _start(i)) for i in range(N)],
                      timeout=1.0) as links:
                _plan(links)
                cpu0 = cpu_seconds()
                until = time.monotonic() + SECONDS
                if engine == "loop":
                    serve(loop, links, until, lambda: False)
                    threads = len(os.listdir("/proc/self/task"))
                    vm1, rss1 = _memory()
                else:
                    for d in links:
                        d.link.detach()  # the blocking engine polls the fd itself
                        os.set_blocking(d.ctx.fd, True)
                    threads, (vm1, rss1) = _threads_run(links, until)
                cpu = cpu_seconds() - cpu0
                reads = sum(d.counters.counts().responses for d in links)
                timeouts = sum(d.counters.counts().timeouts for d in links)
                wrong = _wrong(links)
                if engine == "thread":
                    for d in links:  # the ExitStack detaches again: watch once more
                        loop.watch(d.ctx.fd, d.link.slot)
        results[engine] = (reads, wrong)
        rows += [(f"{engine}: threads of this process", threads, ""),
                 (f"{engine}: RSS per link", (rss1 - rss0) / N / 1024, "kB"),
                 (f"{engine}: address space per link", (vm1 - vm0) / N / 1024, "kB"),
                 (f"{engine}: CPU per read", cpu / max(reads, 1) * 1e6, "us"),
                 (f"{engine}: reads", reads, f"in {SECONDS:.0f} s"),
                 (f"{engine}: timeouts", timeouts, ""),
                 (f"{engine}: wrong values", wrong, "links")]
