"""Gateway soak (`make soak-gateway`, not in CI): the gateway service under the faults of
issue #25, run through its public CLI (``python -m edgemodbus.gateway``) in a child
process whose costs /proc shows (tests/gateway_proc.py).

Three bystander devices (slaves 1-3 of a pymodbus peer, rtu-over-tcp, readCycle 100 ms)
are polled throughout; device 1 is served as unit 1 by the gateway's Modbus TCP server
and every device is exported on /metrics.  Per case, with a fresh gateway:

1. a quiet window (--quiet seconds): the bystanders' polling rate (requests the peer
   answered per second) and the gateway's CPU;
2. the fault for --seconds (the case's ``attack``), sampled every 0.2 s: CPU (process,
   and its busiest thread: a spinning loop), highest RSS, fds and threads, the log lines
   written and the longest, the bystanders' polling rate relative to the quiet window;
3. the fault ends; the case's ``recover`` check must pass within RECOVER_S (a master
   served, a scrape answered, the process alive), then SIGTERM: exit status 0.

A case is a :class:`Case` in :func:`cases`: a name, the row it stands for, the open-files
limit, the server's connection cap, an attack (a context manager factory given
the :class:`Run`) and a recovery check; add a row by adding one.  Bounds (exit status 1
when a case breaks one): the busiest thread's CPU below MAX_THREAD_CPU, log lines at most
LOG_BASE + LOG_PER_S x seconds and none longer than MAX_LINE characters, bystander rate
at least MIN_RATE of the quiet one, threads at most MAX_EXTRA_THREADS over the quiet
window, recovery, no failed read of a bystander (timeouts, CRC or protocol errors
in /metrics: "values lost"), exit status 0.

    python tools/soak_gateway.py --seconds 20
    python tools/soak_gateway.py --quick --cases metrics-slowloris --json out.json
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from tests import gateway_proc  # (the repository's root is on the path first)
from tests.gateway_proc import (
    GatewayProcess,
    Usage,
    cpu_share,
    device_file,
    idle_connections,
    nested_json,
    write_json,
)
from tests.peers import PymodbusSlave, free_port

DEVICES = 3
MAX_THREAD_CPU = 0.05
MIN_RATE = 0.80
LOG_BASE, LOG_PER_S = 10, 0.5
MAX_LINE = 1024
MAX_EXTRA_THREADS = 2
RECOVER_S = 30.0
SLOW_HEADERS = b"GET /metrics HTTP/1.1\r\nHost: x\r\n"  # and never the blank line


@dataclass
class Run:
    """One case's gateway: its folder, ports, process and peer."""

    conf: Path
    serve_port: int
    metrics_port: int
    gw: GatewayProcess
    peer: PymodbusSlave
    notes: dict[str, Any] = field(default_factory=dict)  # the attack's own figures


Attack = Callable[[Run, float], AbstractContextManager[None]]


@dataclass(frozen=True)
class Case:
    name: str
    row: str  # the row it stands for
    attack: Attack
    recover: Callable[[Run], bool]
    nofile: int = 0  # the gateway's soft RLIMIT_NOFILE (0: unchanged)
    serve_max_connections: int = 32
    log_per_event: int = 0  # log lines each of the attack's own events may write


def served(run: Run) -> bool:
    return gateway_proc.served(run.serve_port)


def scraped(run: Run, timeout: float = 5.0) -> bool:
    try:
        return 'edgemodbus_requests_total{device="dev1"' in gateway_proc.scrape(
            run.metrics_port, timeout)
    except OSError:
        return False


@contextlib.contextmanager
def serve_flood(run: Run, seconds: float) -> Iterator[None]:
    """More masters than the gateway has fds, held open."""
    with idle_connections(run.serve_port, 200):
        yield


@contextlib.contextmanager
def metrics_slowloris(run: Run, seconds: float) -> Iterator[None]:
    """1,024 connections that send part of a request's headers and then nothing, while
    a scraper asks every second (its answers and slowest time are the case's notes)."""
    stop = threading.Event()
    times: list[float] = []
    failed = [0]

    def scraper() -> None:
        while not stop.wait(1.0):
            started = time.monotonic()
            if scraped(run, timeout=10.0):
                times.append(time.monotonic() - started)
            else:
                failed[0] += 1

    with idle_connections(run.metrics_port, 1024, send=SLOW_HEADERS, patience=2.0):
        thread = threading.Thread(target=scraper, name="soak-scraper")
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join()
    run.notes.update(scrapes=len(times), scrapesFailed=failed[0],
                     slowestScrapeS=round(max(times, default=0.0), 3))


@contextlib.contextmanager
def reload_nested(run: Run, seconds: float) -> Iterator[None]:
    """Device 1's file and the gateway file nested 100,000 deep; SIGHUP every 2 s."""
    dev1 = (run.conf / "dev1.json").read_text()
    gateway = (run.conf / "gateway.json").read_text()
    write_json(run.conf / "dev1.json", nested_json())
    write_json(run.conf / "gateway.json", nested_json())
    stop = threading.Event()
    sent = [0]

    def hup() -> None:
        while not stop.is_set() and run.gw.alive():
            run.gw.signal(signal.SIGHUP)
            sent[0] += 1
            stop.wait(2.0)

    thread = threading.Thread(target=hup, name="soak-sighup")
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        write_json(run.conf / "dev1.json", dev1)
        write_json(run.conf / "gateway.json", gateway)
        run.notes.update(events=sent[0])


def cases() -> list[Case]:
    return [
        Case("serve-emfile", "Modbus TCP server: accept4 EMFILE (ulimit 64)", serve_flood,
             served, nofile=64, serve_max_connections=1024),
        Case("metrics-slowloris", "metrics: 1,024 connections, headers never finished",
             metrics_slowloris, scraped, nofile=256),
        Case("metrics-emfile", "metrics: 1,024 slow connections, ulimit 64 (accept EMFILE)",
             metrics_slowloris, scraped, nofile=64),
        Case("reload-nested", "reload: deeply nested device and gateway files, SIGHUP",
             reload_nested, lambda run: run.gw.alive() and served(run) and scraped(run),
             log_per_event=3),  # per SIGHUP: "reloading" and one line per nested file
    ]


def sample(gw: GatewayProcess, seconds: float) -> tuple[Usage, Usage, Usage]:
    """First, last and the highest (RSS, fds, threads) of looks every 0.2 s."""
    first = peak = gw.usage()
    deadline = time.monotonic() + seconds
    last = first
    while time.monotonic() < deadline and gw.alive():
        time.sleep(0.2)
        try:
            last = gw.usage()
        except OSError:  # it died meanwhile (the case reports its exit status)
            break
        peak = Usage(last.at, last.cpu, last.thread_cpu, max(peak.rss_kib, last.rss_kib),
                     max(peak.fds, last.fds), max(peak.threads, last.threads))
    return first, last, peak


FAILED_READS = ("edgemodbus_timeouts_total", "edgemodbus_crc_errors_total",
                "edgemodbus_protocol_errors_total")


def failed_reads(run: Run) -> int | None:
    """The bystanders' failed reads so far (timeouts, CRC and protocol errors), from a
    scrape; None when the exporter does not answer."""
    try:
        text = gateway_proc.scrape(run.metrics_port, 5.0)
    except OSError:
        return None
    return int(sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
                   if line.startswith(FAILED_READS)))


def requests(peer: PymodbusSlave) -> int:
    return sum(peer.request_count(unit) for unit in range(1, DEVICES + 1))


def run_case(case: Case, seconds: float, quiet: float, workdir: Path) -> dict[str, Any]:
    conf = workdir / case.name
    conf.mkdir()
    serve_port, metrics_port = free_port(), free_port()
    with PymodbusSlave("rtu-over-tcp", units=tuple(range(1, DEVICES + 1)), size=200) as peer:
        for unit in range(1, DEVICES + 1):
            write_json(conf / f"dev{unit}.json", device_file(peer.port, unit, f"dev{unit}"))
        write_json(conf / "gateway.json", {
            "metrics": {"port": metrics_port},
            "serve": {"listen": f"127.0.0.1:{serve_port}",
                      "maxConnections": case.serve_max_connections, "idleTimeoutS": 600,
                      "units": [{"unitId": 1, "device": "dev1"}]}})
        with GatewayProcess(conf, workdir / f"{case.name}.log", nofile=case.nofile) as gw:
            run = Run(conf, serve_port, metrics_port, gw, peer)
            deadline = time.monotonic() + 30
            while not (served(run) and scraped(run)):
                if time.monotonic() > deadline or not gw.alive():
                    raise SystemExit(f"{case.name}: the gateway did not start:\n{gw.log}")
                time.sleep(0.1)
            polled = requests(peer)
            failed_before = failed_reads(run)
            q_first, q_last, _ = sample(gw, quiet)
            quiet_rate = (requests(peer) - polled) / (q_last.at - q_first.at)
            log_at = len(gw.log)
            with case.attack(run, seconds):
                polled = requests(peer)
                first, last, peak = sample(gw, seconds)
                rate = (requests(peer) - polled) / (last.at - first.at)
            lines = gw.log[log_at:].splitlines()
            started = time.monotonic()
            recovered = None
            while time.monotonic() - started < RECOVER_S and gw.alive():
                if case.recover(run):
                    recovered = time.monotonic() - started
                    break
                time.sleep(0.2)
            failed_after = failed_reads(run) if gw.alive() else None
            rc = gw.stop() if gw.alive() else gw.proc.returncode if gw.proc else None
    span = last.at - first.at
    figures = {
        "case": case.name, "row": case.row, "nofile": case.nofile,
        "cpuQuiet": round((q_last.cpu - q_first.cpu) / (q_last.at - q_first.at), 3),
        "cpuAttacked": round((last.cpu - first.cpu) / span, 3),
        "threadCpu": round(cpu_share(first, last)[1], 3),
        "rssKiB": [q_last.rss_kib, peak.rss_kib], "fds": [q_last.fds, peak.fds],
        "threads": [q_last.threads, peak.threads], "logLines": len(lines),
        "longestLine": max((len(ln) for ln in lines), default=0),
        "bystanderRate": round(rate / quiet_rate, 3) if quiet_rate else 0.0,
        "recoveredS": None if recovered is None else round(recovered, 2), "exit": rc,
        "valuesLost": (None if failed_before is None or failed_after is None
                       else failed_after - failed_before),
        **run.notes,
    }
    figures["failures"] = check(figures, seconds, case.log_per_event)
    return figures


def check(f: dict[str, Any], seconds: float, log_per_event: int) -> list[str]:
    bad = []
    if f["threadCpu"] > MAX_THREAD_CPU:
        bad.append(f"thread CPU {f['threadCpu']} > {MAX_THREAD_CPU}")
    if f["valuesLost"] != 0:
        bad.append(f"values lost: {f['valuesLost']}")
    if f["logLines"] > LOG_BASE + LOG_PER_S * seconds + log_per_event * f.get("events", 0):
        bad.append(f"{f['logLines']} log lines")
    if f["longestLine"] > MAX_LINE:
        bad.append(f"a log line of {f['longestLine']} characters")
    if f["bystanderRate"] < MIN_RATE:
        bad.append(f"bystander polling at {f['bystanderRate']:.0%} of the quiet rate")
    if f["threads"][1] > f["threads"][0] + MAX_EXTRA_THREADS:
        bad.append(f"threads {f['threads'][0]} -> {f['threads'][1]}")
    if f["recoveredS"] is None:
        bad.append("did not recover")
    if f["exit"] != 0:
        bad.append(f"exit status {f['exit']}")
    return bad


def table(rows: list[dict[str, Any]]) -> str:
    head = ("| case | CPU quiet -> attacked | thread CPU | RSS MiB | fds | threads | "
            "log lines (longest) | bystander rate | values lost | recovered | result |")
    out = [head, "|" + "---|" * 11]
    for r in rows:
        out.append(
            f"| {r['case']} | {r['cpuQuiet']:.3f} -> {r['cpuAttacked']:.3f} | "
            f"{r['threadCpu']:.3f} | {r['rssKiB'][0] / 1024:.0f} -> {r['rssKiB'][1] / 1024:.0f}"
            f" | {r['fds'][0]} -> {r['fds'][1]} | {r['threads'][0]} -> {r['threads'][1]} | "
            f"{r['logLines']} ({r['longestLine']}) | {r['bystanderRate']:.0%} | "
            f"{r['valuesLost']} | "
            f"{r['recoveredS']} s | {'; '.join(r['failures']) or 'ok'} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="fault window per case")
    parser.add_argument("--quiet", type=float, default=5.0, help="quiet window per case")
    parser.add_argument("--cases", default="", help="comma-separated case names")
    parser.add_argument("--quick", action="store_true", help="6 s faults, 3 s quiet")
    parser.add_argument("--json", type=Path, default=None, help="write every figure here")
    args = parser.parse_args(argv)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # its client's retry lines
    if args.quick:
        args.seconds, args.quiet = 6.0, 3.0
    chosen = [c for c in cases() if not args.cases or c.name in args.cases.split(",")]
    if not chosen:
        parser.error(f"--cases {args.cases!r}: known: {', '.join(c.name for c in cases())}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="soak-gateway-") as tmp:
        for case in chosen:
            print(f"{case.name}: {case.row} ...", file=sys.stderr, flush=True)
            rows.append(run_case(case, args.seconds, args.quiet, Path(tmp)))
    print(table(rows))
    for r in rows:
        notes = {k: r[k] for k in ("scrapes", "scrapesFailed", "slowestScrapeS", "events")
                 if k in r}
        if notes:
            print(f"{r['case']}: {json.dumps(notes)}")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 1 if any(r["failures"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
