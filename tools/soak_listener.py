"""Listener soak (`make soak-listener`, not in CI): the DTU listener under attack.

Six legitimate DTUs (``DtuFleet`` in a child process, its CPU and memory are not ours)
dial in to one listen port of the drivers running here: one DriverModbusRtu per DTU, 100
registers each, values known exactly (holding register a of DTU k holds 1000 (k + 1) + a,
input register a holds 1000 (k + 1) + 500 + a), so every reported value is checked.  Per
case (the rows of issue #14, plus the new defences), with fresh drivers and DTUs:

1. all six DTUs register and read Ok, then a quiet window (--quiet seconds) is measured;
2. tools/dtu_attack.py (an independent process, stdlib only) attacks for --seconds, from
   127.0.1.x source addresses (the DTUs dial from 127.0.0.1); a third of the way in, DTU 0
   drops its connection and dials again (the time until its line is up again is
   "redial");
3. the attacker stops (SIGTERM; its JSON summary is kept), the drivers stop, and fds and
   threads must be back where they were before the case.

Per case: our process's fds, threads and RSS (highest while attacked), CPU seconds per
second (quiet -> attacked), log records of the ``edgemodbus`` logger while attacked (a
counting handler at INFO, not printed; the longest formatted line and the longest run of
hex-dumped bytes in one line), the listener's counters (``DriverModbusRtu.dtu_registry
.stats()``, the change while attacked), the bystander DTUs' polling rate (device cycles/s of
the DTUs neither dropped nor impersonated) relative to the quiet window, and wrong values.

Bounds (exit status 1 when a case breaks one):

* wrong values: 0 (for ``impostor-replace``: 0 once the id is contested);
* bystander polling rate at least 90 % of the quiet rate;
* log records while attacked at most LOG_BASE + LOG_PER_S x seconds, no line longer than
  MAX_LINE characters, no more than MAX_HEX untrusted bytes hex-dumped in one line;
* no fd or thread left once the drivers have stopped.

Prints a markdown table (for docs/dtu.md's security section) and --json writes every
figure.  ``--cases`` picks cases (default all), ``--quick`` shortens everything.

    python tools/soak_listener.py --seconds 20
    python tools/soak_listener.py --quick --cases idle-fd1024,junk-stream-text --json out.json
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import resource
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
ATTACKER = os.path.join(HERE, "dtu_attack.py")
DTUS = 6
HR_COUNT, IR_COUNT = 60, 40
IMPOSTOR_BASE = 0xC000  # the attacker's values: 49152 + address, never a DTU's
LOG_BASE, LOG_PER_S = 30, 2.0
MAX_LINE = 1024
MAX_HEX = 64
MIN_RATE = 0.90
TEXT_PATTERN = ""
REGEX_PATTERN = r"^ID:(?P<id>SOAK\d+)(?:;KEY:(?P<key>\w+))?\r\n"
HEX_RUN = re.compile(r"(?:\b[0-9A-Fa-f]{2}[ :]){8,}[0-9A-Fa-f]{2}\b|(?:[0-9A-Fa-f]{2}){16,}")


@dataclass(frozen=True)
class Case:
    """One row: the port's settings, the attack, and what it tests."""

    name: str
    row: str  # the row (or the defence) it stands for
    attack: tuple[str, ...]  # dtu_attack.py arguments after HOST:PORT
    mode: str = "text"  # the port's registration: text | regex
    extra: dict[str, Any] = field(default_factory=dict)  # more communication keys
    nofile: int = 0  # soft RLIMIT_NOFILE while the case runs (0: unchanged)
    keys: bool = False  # the DTUs register with a registrationKey
    displaces_target: bool = False  # the impersonated DTU may lose its place (replace)


def cases() -> list[Case]:
    spread = ("--sources", "40")
    return [
        Case("idle-fd1024", "2000 idle connections, fd limit 1024",
             ("idle", "-n", "2000", *spread), nofile=1024),
        Case("idle-reconnect-fd1024", "the same, attackers reconnecting",
             ("idle-reconnect", "-n", "2000", *spread), nofile=1024),
        Case("idle-reconnect", "2000 idle connections reconnecting from one address, "
             "fd limit 20000", ("idle-reconnect", "-n", "2000", "--sources", "1")),
        Case("random-registration-regex", "200 x 64 KB random registration, regex mode",
             ("random-registration", "-n", "200", "--bytes", "65536", "--sources", "4",
              "--reconnect", "--reconnect-delay", "1"), mode="regex"),
        Case("junk-stream-regex", "junk streamed at full speed before registration, "
             "regex mode", ("junk-stream", "-n", "4", "--sources", "1", "--reconnect",
                            "--reconnect-delay", "0.2"), mode="regex"),
        Case("junk-stream-text", "junk streamed, text mode",
             ("junk-stream", "-n", "4", "--sources", "1", "--reconnect",
              "--reconnect-delay", "0.2")),
        Case("slow-id", "a configured id one byte per second (duplicateId keep-existing, "
             "the default)",
             ("slow-id", "SOAK1", "--interval", "1", "--sources", "1", "--reconnect",
              "--reconnect-delay", "0.5"), extra={"duplicateId": "keep-existing"}),
        Case("impostor-keep", "two DTUs claiming one id (duplicateId keep-existing, the "
             "default)",
             ("impostor", "SOAK1", "--template", "{id}\\r\\n", "--sources", "1",
              "--reconnect", "--reconnect-delay", "0.2"),
             extra={"duplicateId": "keep-existing"}),
        Case("challenger-flood-fd1024", "2000 connections claiming a connected id "
             "(keep-existing holds each for the registration timeout), fd limit 1024",
             ("impostor", "SOAK1", "-n", "2000", "--template", "{id}\\r\\n", "--reconnect",
              *spread),
             extra={"duplicateId": "keep-existing"}, nofile=1024),
        Case("impostor-replace", "two DTUs claiming one id (duplicateId replace)",
             ("impostor", "SOAK1", "--template", "{id}\\r\\n", "--sources", "1",
              "--reconnect", "--reconnect-delay", "0.2"),
             extra={"duplicateId": "replace"}, displaces_target=True),
        Case("key-guess", "registrations with wrong keys (registrationKey)",
             ("key-guess", "SOAK1", "-n", "8", "--template", "ID:{id};KEY:{key}\\r\\n",
              "--sources", "1", "--reconnect", "--reconnect-delay", "0.05"),
             mode="regex", keys=True),
    ]


def dtu_key(k: int) -> str:
    return f"k{k}s3cr3t{k * 7919:05d}"


def registration_template(case: Case) -> str:
    if case.mode == "regex":
        return "ID:SOAK{n};KEY:{key}\r\n" if case.keys else "ID:SOAK{n}\r\n"
    return "SOAK{n}\r\n"


def expected(k: int) -> dict[str, int]:
    base = 1000 * (k + 1)
    out = {f"d{k}.hr{a}": base + a for a in range(HR_COUNT)}
    out.update({f"d{k}.ir{a}": base + 500 + a for a in range(IR_COUNT)})
    return out


# -- the DTUs (child process) ----------------------------------------------------------------


def serve_dtus(args: argparse.Namespace) -> int:
    """The six DTUs: print {"ready": 1}; stdin "drop K" drops DTU K, "stats" prints the
    fleet's stats; stop at EOF."""
    from edgemodbus.datatypes import Area
    from edgemodbus.sim import DtuFleet

    template = args.template

    def packet(n: int) -> bytes:
        return template.format(n=n, key=dtu_key(n)).encode()

    fleet = DtuFleet("127.0.0.1", args.port, DTUS, registration=packet, size=1000,
                     reconnect=0.2, reconnect_max=1.0)
    for dtu in fleet.dtus:
        values = expected(dtu.number)
        dtu.slave(1).set_registers(Area.HOLDING_REGISTER, 0,
                                   [values[f"d{dtu.number}.hr{a}"] for a in range(HR_COUNT)])
        dtu.slave(1).set_registers(Area.INPUT_REGISTER, 0,
                                   [values[f"d{dtu.number}.ir{a}"] for a in range(IR_COUNT)])
    with fleet:
        print(json.dumps({"ready": 1}), flush=True)
        for line in sys.stdin:
            word = line.split()
            if word[:1] == ["drop"]:
                fleet.drop(int(word[1]))
            elif word[:1] == ["stats"]:
                print(json.dumps(fleet.stats()), flush=True)
            elif word[:1] == ["proc"]:
                print(json.dumps(proc_figures(int(word[1]))), flush=True)
    return 0


class Child:
    """A child process speaking JSON lines on stdout."""

    def __init__(self, cmd: list[str], stdin: bool = True) -> None:
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE if stdin else None,
                                     stdout=subprocess.PIPE, text=True)

    def line(self, timeout: float) -> dict[str, Any]:
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        text = self.proc.stdout.readline() if ready else ""
        if not text:
            raise RuntimeError(f"soak: child {self.proc.args[1:3]} did not answer")
        result: dict[str, Any] = json.loads(text)
        return result

    def say(self, text: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(text + "\n")
        self.proc.stdin.flush()

    def stop(self, sig: int | None = None, timeout: float = 10.0) -> str:
        """Stop it (EOF on its stdin, or ``sig``); what it wrote meanwhile."""
        out = ""
        if self.proc.poll() is None and sig is not None:
            self.proc.send_signal(sig)
        try:
            out = self.proc.communicate(timeout=timeout)[0] or ""
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out = self.proc.communicate()[0] or ""
        except ValueError:  # stopped before: its pipes are closed
            self.proc.wait()
        return out


# -- measuring ourselves -----------------------------------------------------------------


def proc_figures(pid: int | str = "self") -> dict[str, float]:
    """fds, threads (the kernel's: Python's and the others) and RSS (MB) of ``pid``;
    read by the DTU child for us, as our own fds may run out (the fd-limit cases)."""
    out = {"fds": float(len(os.listdir(f"/proc/{pid}/fd")))}
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                out["rss"] = int(line.split()[1]) / 1024
            elif line.startswith("Threads:"):
                out["threads"] = float(line.split()[1])
    return out


def fd_count() -> int:
    return len(os.listdir("/proc/self/fd"))


def cpu_seconds() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


class LogCounter(logging.Handler):
    """Counts the records of the ``edgemodbus`` logger (formatted, as a file handler would
    write them) and keeps the longest line, the longest hex run and a few samples."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        self.reset()

    def reset(self) -> None:
        self.lines = 0
        self.warnings = 0
        self.chars = 0
        self.longest = 0
        self.hex_bytes = 0
        self.samples: dict[str, str] = {}  # the first line of each level

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
        except Exception:  # a record that cannot be formatted still counts
            text = str(record.msg)
        self.lines += 1
        self.warnings += record.levelno >= logging.WARNING
        self.chars += len(text) + 1
        self.longest = max(self.longest, len(text))
        if len(text) > 200 or "  " not in text:  # cheap: look for hex dumps in long lines
            for run in HEX_RUN.findall(text[:200_000]):
                digits = sum(c in "0123456789abcdefABCDEF" for c in run)
                self.hex_bytes = max(self.hex_bytes, digits // 2)
        self.samples.setdefault(record.levelname, text[:300])

    def figures(self) -> dict[str, Any]:
        return {"lines": self.lines, "warnings": self.warnings, "bytes": self.chars,
                "longest": self.longest, "hexBytes": self.hex_bytes,
                "samples": dict(self.samples)}


class Checker:
    """address_updated_callback: every Ok value must be the DTU's own."""

    def __init__(self) -> None:
        self.want: dict[str, int] = {}
        for k in range(DTUS):
            self.want.update(expected(k))
        self.lock = threading.Lock()
        self.ok = self.invalid = self.wrong = 0
        self.wrong_at: list[float] = []
        self.examples: list[str] = []
        self.reasons: dict[str, str] = {}  # the last errorReason of each DTU's items

    def __call__(self, item: Any) -> None:
        from edgemodbus.datatypes import ItemStatus

        with self.lock:
            if item.status is not ItemStatus.OK:
                self.invalid += 1
                self.reasons[item.name.split(".")[0]] = str(item.error_reason or "")
                return
            self.ok += 1
            want = self.want[item.name]
            if item.value != want:
                self.wrong += 1
                self.wrong_at.append(time.monotonic())
                if len(self.examples) < 5:
                    self.examples.append(f"{item.name} = {item.value!r}, expected {want}")


def device_config(port: int, k: int, case: Case) -> Any:
    import edgemodbus as em

    comm: dict[str, Any] = {
        "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
        "dtuId": f"SOAK{k}", "registration": case.mode, "registrationTimeout": 5000,
        "slaveId": 1, "readTimeout": 300, "byteTimeout": 50, "readCycle": 100,
        "reconnectInterval": 200, "maxBackoff": 1000,
    }
    if case.mode == "regex":
        comm["registrationPattern"] = REGEX_PATTERN
    if case.keys:
        comm["registrationKey"] = dtu_key(k)
    comm.update(case.extra)
    items = [{"name": f"d{k}.hr{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
             for a in range(HR_COUNT)]
    items += [{"name": f"d{k}.ir{a}", "address": f"ir:{a}", "deviceDataType": "UInt16"}
              for a in range(IR_COUNT)]
    return em.load_device_config({"organization": {"deviceCode": f"soak-dtu{k}"},
                                  "communication": comm, "addressList": items})


@contextlib.contextmanager
def drivers_for(port: int, case: Case, checker: Checker) -> Iterator[list[Any]]:
    import edgemodbus as em

    drivers: list[Any] = []
    try:
        for k in range(DTUS):
            cfg = device_config(port, k, case)
            drv = em.DriverModbusRtu()
            drv.address_updated_callback = checker
            if not drv.start_device(cfg.organization, cfg.communication, cfg.address_list):
                raise RuntimeError(f"soak: device {k} did not start")
            drivers.append(drv)
        yield drivers
    finally:
        for drv in drivers:
            drv.stop_device()


def wait(cond: Callable[[], bool], timeout: float, step: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() >= deadline:
            return False
        time.sleep(step)
    return True


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cycles(drivers: list[Any], which: list[int]) -> int:
    return sum(int(drivers[k].stats().get("cycles", 0)) for k in which)


def link_ups(drv: Any) -> int:
    """Times the device's line has come up (its first connect and every reconnect)."""
    line = drv.stats()["line"]
    return int(line.get("connects", 0)) + int(line.get("reconnects", 0))


def port_stats(port: int) -> dict[str, int]:
    import edgemodbus as em

    stats: dict[str, dict[str, int]] = em.DriverModbusRtu.dtu_registry.stats()
    return dict(stats.get(f"127.0.0.1:{port}", {}))


GAUGES = ("unregistered", "dtus", "connected")


def delta(after: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    return {k: (v if k in GAUGES else v - before.get(k, 0)) for k, v in after.items()}


def settle(fn: Callable[[], int], target: int, seconds: float = 5.0) -> int:
    deadline = time.monotonic() + seconds
    value = fn()
    while value > target and time.monotonic() < deadline:
        time.sleep(0.05)
        value = fn()
    return value


# -- one case ----------------------------------------------------------------------------


def run_case(case: Case, args: argparse.Namespace, counter: LogCounter) -> dict[str, Any]:
    checker = Checker()
    port = free_port()
    limit = resource.getrlimit(resource.RLIMIT_NOFILE)
    fds0, threads0 = fd_count(), threading.active_count()
    target = 1 if case.attack[0] in ("slow-id", "impostor", "key-guess") else None
    bystanders = [k for k in range(1, DTUS) if not (case.displaces_target and k == target)]
    out: dict[str, Any] = {"case": case.name, "row": case.row, "attack": list(case.attack),
                           "mode": case.mode, "config": dict(case.extra)}
    if case.nofile:
        resource.setrlimit(resource.RLIMIT_NOFILE, (case.nofile, limit[1]))
    dtus: Child | None = None
    attacker: Child | None = None
    try:
        with drivers_for(port, case, checker) as drivers:
            dtus = Child([sys.executable, __file__, "--serve-dtus", "--port", str(port),
                          "--template", registration_template(case)])
            dtus.line(20.0)
            if not wait(lambda: all(d.stats().get("cycles", 0) >= 2 for d in drivers)
                        and checker.ok >= DTUS * (HR_COUNT + IR_COUNT), 30.0):
                raise RuntimeError("soak: the legitimate DTUs did not all read Ok")
            # quiet window
            counter.reset()
            c0, cpu0, t0 = cycles(drivers, bystanders), cpu_seconds(), time.monotonic()
            time.sleep(args.quiet)
            quiet_s = time.monotonic() - t0
            quiet_rate = (cycles(drivers, bystanders) - c0) / quiet_s
            quiet_cpu = (cpu_seconds() - cpu0) / quiet_s
            out["quiet"] = {"rate": round(quiet_rate, 2), "cpu": round(quiet_cpu, 3),
                            "logLines": counter.lines}
            # attacked window
            before = port_stats(port)
            counter.reset()
            wrong0 = checker.wrong
            attacker = Child([sys.executable, ATTACKER, f"127.0.0.1:{port}", *case.attack,
                              "--value-base", str(IMPOSTOR_BASE)], stdin=False)
            c0, cpu0, t0 = cycles(drivers, bystanders), cpu_seconds(), time.monotonic()
            dtus.say(f"proc {os.getpid()}")
            rss_start = rss_max = dtus.line(10.0)["rss"]
            fds_max, threads_max = fds0, threads0
            drop_at = t0 + args.seconds / 3
            dropped: tuple[float, int] | None = None
            redial: float | None = None
            contested_at: float | None = None
            while (now := time.monotonic()) < t0 + args.seconds:
                time.sleep(0.2)
                dtus.say(f"proc {os.getpid()}")
                figures = dtus.line(10.0)
                fds_max = max(fds_max, int(figures["fds"]))
                threads_max = max(threads_max, threading.active_count())
                rss_max = max(rss_max, figures["rss"])
                if contested_at is None and port_stats(port).get("contested", 0):
                    contested_at = time.monotonic()
                if dropped is None and now >= drop_at:
                    dropped = (now, link_ups(drivers[0]))
                    dtus.say("drop 0")
                elif dropped is not None and redial is None and link_ups(
                        drivers[0]) > dropped[1]:
                    redial = time.monotonic() - dropped[0]
            attack_s = time.monotonic() - t0
            rate = (cycles(drivers, bystanders) - c0) / attack_s
            cpu = (cpu_seconds() - cpu0) / attack_s
            logs = counter.figures()
            after = port_stats(port)
            said = attacker.stop(signal.SIGTERM, 15.0).strip().splitlines()
            out["attacker"] = json.loads(said[-1]) if said else {}
            final_wrong = []
            for k, drv in enumerate(drivers):
                for name, item in drv.snapshot()["items"].items():
                    value = item.get("value")
                    if item.get("status") == "Ok" and value != expected(k)[name]:
                        final_wrong.append(f"{name} = {value!r} in the final snapshot")
    finally:
        if attacker is not None:
            attacker.stop(signal.SIGTERM)
        if dtus is not None:
            dtus.stop()
        if case.nofile:
            resource.setrlimit(resource.RLIMIT_NOFILE, limit)
    fds_after = settle(fd_count, fds0)
    threads_after = settle(threading.active_count, threads0)
    wrong = checker.wrong - wrong0 + len(final_wrong)
    wrong_after_contest = (sum(1 for t in checker.wrong_at if t > contested_at)
                           if contested_at is not None else None)
    out.update({
        "seconds": round(attack_s, 1),
        "fds": {"before": fds0, "max": fds_max, "afterStop": fds_after},
        "threads": {"before": threads0, "max": threads_max, "afterStop": threads_after},
        "rssMb": {"start": round(rss_start, 1), "max": round(rss_max, 1)},
        "cpu": round(cpu, 3),
        "logs": logs,
        "listener": delta(after, before),
        "rate": round(rate, 2),
        "rateRatio": round(rate / quiet_rate, 3) if quiet_rate else 0.0,
        "redialSeconds": None if redial is None else round(redial, 2),
        "wrong": wrong,
        "wrongAfterContested": wrong_after_contest,
        "wrongExamples": (checker.examples + final_wrong)[:5],
        "targetReason": checker.reasons.get("d1", ""),
    })
    out["failures"] = bounds(case, out)
    return out


def bounds(case: Case, r: dict[str, Any]) -> list[str]:
    failures = []
    if case.displaces_target:
        if r["wrongAfterContested"] is None:
            failures.append(f"{r['wrong']} wrong values and the id never became contested")
        elif r["wrongAfterContested"]:
            failures.append(f"{r['wrongAfterContested']} wrong values after the id was "
                            "contested")
    elif r["wrong"]:
        failures.append(f"{r['wrong']} wrong values")
    if r["rateRatio"] < MIN_RATE:
        failures.append(f"polling rate {100 * r['rateRatio']:.0f} % of quiet")
    logs = r["logs"]
    limit = LOG_BASE + LOG_PER_S * r["seconds"]
    if logs["lines"] > limit:
        failures.append(f"{logs['lines']} log lines (at most {limit:.0f})")
    if logs["longest"] > MAX_LINE:
        failures.append(f"a log line of {logs['longest']} characters")
    if logs["hexBytes"] > MAX_HEX:
        failures.append(f"{logs['hexBytes']} bytes hex-dumped in one line")
    if r["fds"]["afterStop"] > r["fds"]["before"]:
        failures.append(f"{r['fds']['afterStop'] - r['fds']['before']} fds leaked")
    if r["threads"]["afterStop"] > r["threads"]["before"]:
        failures.append(f"{r['threads']['afterStop'] - r['threads']['before']} threads leaked")
    return failures


# -- the report ----------------------------------------------------------------------------


def human(n: float) -> str:
    for unit, size in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(n) >= size:
            return f"{n / size:.3g}{unit}"
    return f"{n:.0f}" if float(n).is_integer() else f"{n:.3g}"


def table(results: list[dict[str, Any]]) -> str:
    head = ("| case | attacker: dials / closed or reset by us / sent (polled: requests it got) "
            "| fds max | threads max | RSS MB | CPU s/s quiet -> attacked "
            "| log lines (longest, hex bytes) | listener counters "
            "| bystander rate | redial s | wrong | result |")
    rows = [head, "|" + "---|" * 12]
    for r in results:
        if "error" in r:
            rows.append(f"| {r['case']} | error: {r['error']} |" + " |" * 10)
            continue
        a = r.get("attacker") or {}
        counters = ", ".join(f"{k} {human(v)}" for k, v in sorted(r["listener"].items())
                             if v and k not in GAUGES)
        logs = r["logs"]
        wrong = str(r["wrong"])
        if r["wrongAfterContested"] is not None:
            wrong += f" ({r['wrongAfterContested']} after contested)"
        polled = a.get("requests_answered", 0) + a.get("polled", 0)
        refused = a.get("closed_by_peer", 0) + a.get("errors", {}).get("ECONNRESET", 0)
        rows.append(
            f"| {r['case']} | {human(a.get('dials', 0))} / {human(refused)} / "
            f"{human(a.get('bytes_sent', 0))}B"
            + (f", polled {human(polled)}" if polled else "") + " "
            f"| {r['fds']['max']} | {r['threads']['max']} | {r['rssMb']['start']:.0f} -> "
            f"{r['rssMb']['max']:.0f} | {r['quiet']['cpu']:.2f} -> {r['cpu']:.2f} "
            f"| {human(logs['lines'])} ({human(logs['longest'])}, {logs['hexBytes']}) "
            f"| {counters or '-'} | {100 * r['rateRatio']:.0f} % "
            f"| {'-' if r['redialSeconds'] is None else r['redialSeconds']} | {wrong} "
            f"| {'ok' if not r['failures'] else 'FAIL: ' + '; '.join(r['failures'])} |")
    return "\n".join(rows)


def retable(path: str) -> int:
    """Print the table of a --json file again."""
    with open(path) as fh:
        print(table(json.load(fh)["cases"]))
    return 0


def soak(args: argparse.Namespace) -> int:
    import edgemodbus  # noqa: F401  (loaded before any figure)

    counter = LogCounter()
    top = logging.getLogger("edgemodbus")
    top.setLevel(logging.INFO)
    top.addHandler(counter)
    top.propagate = False
    if args.log_file:
        fh = logging.FileHandler(args.log_file)
        fh.setFormatter(counter.formatter)
        top.addHandler(fh)
    chosen = [c for c in cases() if not args.cases or c.name in args.cases]
    print(f"listener soak: {len(chosen)} cases, {args.quiet:.0f} s quiet + {args.seconds:.0f} s "
          f"attacked each, {DTUS} DTUs x {HR_COUNT + IR_COUNT} registers", flush=True)
    results = []
    for case in chosen:
        print(f"  {case.name}: {case.row} ...", flush=True)
        try:
            result = run_case(case, args, counter)
        except Exception as exc:  # a case that cannot run is a failure, the rest still run
            result = {"case": case.name, "row": case.row, "error": str(exc),
                      "failures": [str(exc)]}
        results.append(result)
        print("    " + ("ok" if not result["failures"] else "FAILED: "
                        + "; ".join(result["failures"])), flush=True)
    print()
    print(table(results))
    print()
    print(f"Bounds: wrong values 0; bystander polling rate >= {100 * MIN_RATE:.0f} % of quiet; "
          f"log records while attacked <= {LOG_BASE} + {LOG_PER_S:g}/s, lines <= {MAX_LINE} "
          f"characters, <= {MAX_HEX} bytes hex-dumped per line; no fd or thread left after "
          "the drivers stop.")
    if args.json:
        with open(args.json, "w") as fh_json:
            json.dump({"bounds": {"minRate": MIN_RATE, "logBase": LOG_BASE,
                                  "logPerSecond": LOG_PER_S, "maxLine": MAX_LINE,
                                  "maxHexBytes": MAX_HEX},
                       "seconds": args.seconds, "quiet": args.quiet, "cases": results},
                      fh_json, indent=1)
    failed = [r["case"] for r in results if r["failures"]]
    print(f"listener soak: {'FAILED: ' + ', '.join(failed) if failed else 'passed'}")
    return 1 if failed else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="attacked, per case")
    parser.add_argument("--quiet", type=float, default=5.0, help="quiet window, per case")
    parser.add_argument("--quick", action="store_true", help="6 s attacked, 3 s quiet")
    parser.add_argument("--cases", type=lambda s: [c for c in s.split(",") if c],
                        default=[], help="comma-separated: " + ",".join(c.name for c in cases()))
    parser.add_argument("--json", default="", help="write every figure to this file")
    parser.add_argument("--log-file", default="", help="also write the edgemodbus log here")
    parser.add_argument("--table", default="", metavar="JSON",
                        help="print the table of an earlier --json file and exit")
    parser.add_argument("--serve-dtus", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--template", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve_dtus:
        return serve_dtus(args)
    if args.table:
        return retable(args.table)
    if args.quick:
        args.seconds, args.quiet = 6.0, 3.0
    unknown = set(args.cases) - {c.name for c in cases()}
    if unknown:
        parser.error(f"unknown cases {sorted(unknown)}")
    return soak(args)


if __name__ == "__main__":
    sys.exit(main())
