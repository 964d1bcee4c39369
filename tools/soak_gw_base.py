"""What a case of `make soak-gateway` (tools/soak_gateway.py) is made of: the run it
gets (the gateway in a child process, its bystanders' peer, what the case set up beside
them), the case itself, and the looks every case takes (polling rate, usage, scrapes).
The case modules (tools/soak_cases_*.py) build on these."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from tests import gateway_proc  # (the repository's root is on the path first)
from tests.gateway_proc import (
    GatewayProcess,
    Usage,
    idle_connections,
    nested_json,
    write_json,
)
from tests.peers import PymodbusSlave

DEVICES = 3
OWN = 4  # the peer's slave the cases' own jobs go to (not a bystander)
BYSTANDERS = tuple(f"dev{unit}" for unit in range(1, DEVICES + 1))
MAX_THREAD_CPU = 0.05
MIN_RATE = 0.80  # of the quiet rate, while a fault does not touch the bystanders' line
FLOOD_RATE = 0.50  # the issue's bound under a flood of jobs on the bystanders' line
LOG_BASE, LOG_PER_S = 10, 0.5
# a kind of event the gateway logs through its limiter (line/log_limit.py): three lines
# and a summary per window
LINES_PER_KIND, LOG_WINDOW_S = 4, 10.0
MAX_LINE = 1024
MAX_EXTRA_THREADS = 2
RECOVER_S = 30.0
SLOW_HEADERS = b"GET /metrics HTTP/1.1\r\nHost: x\r\n"  # and never the blank line


@dataclass
class Prep:
    """What a case may set up before its gateway starts: resources it enters into
    ``stack`` (a broker, a small disk, more peers; left when the case ends), the gateway
    file's sections (``gateway``, merged over the soak's own), more device files
    (``devices``: file stem -> JSON), and objects its attack and checks use (``extras``)."""

    conf: Path
    workdir: Path
    stack: ExitStack
    peer: PymodbusSlave
    gateway: dict[str, Any] = field(default_factory=dict)
    devices: dict[str, Any] = field(default_factory=dict)
    extras: dict[str, Any] = field(default_factory=dict)
    bystanders: tuple[str, ...] = BYSTANDERS  # the devices whose polling is measured


@dataclass
class Run:
    """One case's gateway: its folder, ports, process and peer."""

    conf: Path
    serve_port: int
    metrics_port: int
    gw: GatewayProcess
    peer: PymodbusSlave
    notes: dict[str, Any] = field(default_factory=dict)  # the attack's own figures
    extras: dict[str, Any] = field(default_factory=dict)  # what the case's prep made
    bystanders: tuple[str, ...] = BYSTANDERS


Attack = Callable[[Run, float], AbstractContextManager[None]]


@dataclass(frozen=True)
class Case:
    """One row: its fault (``attack``, for the fault window), what recovery is
    (``recover``), and optionally what it sets up first (``prep``) and what it checks
    once the gateway stopped (``verdict``: failures in words)."""

    name: str
    row: str  # the row it stands for
    attack: Attack
    recover: Callable[[Run], bool]
    nofile: int = 0  # the gateway's soft RLIMIT_NOFILE (0: unchanged)
    serve_max_connections: int = 32
    log_per_event: int = 0  # log lines each of the attack's own events may write
    log_kinds: int = 0  # kinds of rate-limited lines the attack may cause
    prep: Callable[[Prep], None] | None = None
    verdict: Callable[[Run], list[str]] | None = None
    min_rate: float = MIN_RATE  # the bystanders' polling rate at least this of quiet
    extra_threads: int = MAX_EXTRA_THREADS  # threads over the quiet figure while it lasts
    peer_delay: float = 0.0  # the bystanders' peer answers every request this late (s)
    # the busiest thread's CPU share at most (a spin); a flood's own cost is not a spin
    max_thread_cpu: float = MAX_THREAD_CPU
    ready: Callable[[Run], bool] | None = None  # waited for before the quiet window
    # the bystanders' polls so far (None: the requests the pymodbus peer answered)
    polled: Callable[[Run], int | None] | None = None


def own_device(prep: Prep, unit: int = OWN, code: str = "dev4", tags: int = 3,
               read_cycle: int = 1000, **comm: Any) -> None:
    """A device of the case's own on the bystanders' line (a write or forward target;
    its polling is not what is measured)."""
    data = gateway_proc.device_file(prep.peer.port, unit, code, tags, read_cycle)
    data["communication"].update(comm)
    prep.devices[code] = data


def served(run: Run) -> bool:
    return gateway_proc.served(run.serve_port)


def scraped(run: Run, timeout: float = 5.0) -> bool:
    try:
        return 'edgemodbus_requests_total{device="dev1"' in gateway_proc.scrape(
            run.metrics_port, timeout)
    except OSError:
        return False


def served_and_scraped(run: Run) -> bool:
    return run.gw.alive() and served(run) and scraped(run)


def repeat(run: Run, what: Callable[[], None], name: str,
           pause: float = 0.0) -> AbstractContextManager[None]:
    """``what`` over and over on a thread of its own while the fault window lasts (it
    counts its own events in ``run.notes``)."""
    return _repeating(run, what, name, pause)


@contextlib.contextmanager
def _repeating(run: Run, what: Callable[[], None], name: str,
               pause: float) -> Iterator[None]:
    stop = threading.Event()
    errors: list[str] = []

    def loop() -> None:
        while not stop.is_set() and run.gw.alive():
            try:
                what()
            except Exception as exc:  # the attacker's own failure: noted, not fatal
                if len(errors) < 3:
                    errors.append(repr(exc)[:200])
            if pause:
                stop.wait(pause)

    thread = threading.Thread(target=loop, name=name)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        if errors:
            run.notes.setdefault("attackerErrors", errors)


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


def server_cases() -> list[Case]:
    """The rows of the server, the exporter and reload (the script's first cases)."""
    return [
        Case("serve-emfile", "Modbus TCP server: accept4 EMFILE (ulimit 64)", serve_flood,
             served, nofile=64, serve_max_connections=1024),
        Case("metrics-slowloris", "metrics: 1,024 connections, headers never finished",
             metrics_slowloris, scraped, nofile=256),
        Case("metrics-emfile", "metrics: 1,024 slow connections, ulimit 64 (accept EMFILE)",
             metrics_slowloris, scraped, nofile=64),
        Case("reload-nested", "reload: deeply nested device and gateway files, SIGHUP",
             reload_nested, served_and_scraped,
             # per SIGHUP: "reloading" and an error of two lines per nested file (which
             # file and what is kept, then why)
             log_per_event=5),
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
    scrape; None when the exporter does not answer.  Devices a case adds (a dead slave,
    a forward target) are not bystanders: their failures are the fault."""
    try:
        text = gateway_proc.scrape(run.metrics_port, 5.0)
    except OSError:
        return None
    labels = tuple(f'device="{code}"' for code in run.bystanders)
    return int(sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
                   if line.startswith(FAILED_READS) and any(lb in line for lb in labels)))


def requests(peer: PymodbusSlave) -> int:
    return sum(peer.request_count(unit) for unit in range(1, DEVICES + 1))


def answered_each(run: Run) -> dict[str, int] | None:
    """Each bystander's polls the gateway counts answered (its /metrics), None when the
    exporter does not answer."""
    try:
        text = gateway_proc.scrape(run.metrics_port, 5.0)
    except OSError:
        return None
    out = dict.fromkeys(run.bystanders, 0)
    for line in text.splitlines():
        if line.startswith("edgemodbus_responses_total{"):
            for code in run.bystanders:
                if f'device="{code}"' in line:
                    out[code] += int(float(line.rsplit(" ", 1)[1]))
    return out


def answered(run: Run) -> int | None:
    """The bystanders' answered polls (for bystanders behind a peer that does not count
    requests per slave: the DTU fleet)."""
    each = answered_each(run)
    return None if each is None else sum(each.values())


def worst_ratio(quiet: dict[str, float], attacked: dict[str, float]) -> float:
    """The lowest of the bystanders' attacked / quiet polling rates (one starved device
    among several that are not shows here, not in the sum)."""
    return min((attacked.get(code, 0.0) / rate for code, rate in quiet.items() if rate),
               default=0.0)
