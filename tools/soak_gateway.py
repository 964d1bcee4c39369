"""Gateway soak (`make soak-gateway`, not in CI): the gateway service under the faults of
issue #25, one case per row of its table, run through its public CLI (``python -m
edgemodbus.gateway``) in a child process whose costs /proc shows (tests/gateway_proc.py).

Three bystander devices (slaves 1-3 of a pymodbus peer, rtu-over-tcp, readCycle 100 ms)
are polled throughout; device 1 is served as unit 1 by the gateway's Modbus TCP server
and every device is exported on /metrics.  A case may set up more first (its ``prep``:
a mosquitto, a 2 MB tmpfs, a device of its own on the bystanders' line, a fleet of DTUs
that dial in, which are then its bystanders).  Per case, with a fresh gateway:

1. a quiet window (--quiet seconds), once the case is ``ready``: the bystanders' polling
   rate (requests the peer answered per second, or the polls /metrics counts answered),
   each bystander's own, and the gateway's CPU;
2. the fault for --seconds (the case's ``attack``), sampled every 0.2 s: CPU (process,
   and its busiest thread: a spinning loop), highest RSS, fds and threads, the log lines
   written and the longest, tracebacks, the bystanders' polling rate relative to the
   quiet window (all of them, and the worst one);
3. the fault ends; the case's ``recover`` check must pass within RECOVER_S (a master
   served, a scrape answered, the process alive; every value at the subscriber), the
   fds and threads are looked at again, then SIGTERM: exit status 0; the case's
   ``verdict`` looks at what it left (a file moved aside, births, replies, values).

A case is a :class:`Case` (tools/soak_gw_base.py) in a list of tools/soak_cases_*.py;
add a row by adding one.  Bounds (exit status 1 when a case breaks one): the busiest
thread's CPU below the case's ``max_thread_cpu`` (MAX_THREAD_CPU: no spin; a flood's
own cost is reported, not bounded), log lines at most LOG_BASE + LOG_PER_S x seconds
(+ ``log_per_event`` per event of the attack), none longer than MAX_LINE characters, no
traceback, the bystanders' rate and the worst bystander's at least the case's
``min_rate`` of the quiet one (MIN_RATE; FLOOD_RATE, a half, for floods of jobs on their
line), threads at most the case's ``extra_threads`` over the quiet window meanwhile
(MAX_EXTRA_THREADS; the loop's job-thread cap for a job flood there) and none more
after, fds back to the quiet figure after (MAX_EXTRA_FDS), recovery, no failed read of
a bystander (timeouts, CRC or protocol errors in /metrics: "values lost"), exit status 0.
A :class:`StartCase` (tools/soak_cases_config.py) is a hostile folder the gateway must
refuse at start: exit 2 with one short line naming the field, files untouched.

    python tools/soak_gateway.py --seconds 20
    python tools/soak_gateway.py --quick --cases metrics-slowloris --json out.json
    python tools/soak_gateway.py --quick --cases spool-disk-full --keep /tmp/soak  # logs
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from tests.gateway_proc import GatewayProcess, cpu_share, device_file, write_json
from tests.peers import PymodbusSlave, free_port
from tools.soak_cases_config import StartCase, run_start_case, start_cases
from tools.soak_cases_line import line_cases
from tools.soak_cases_loop import loop_cases
from tools.soak_cases_north import north_cases
from tools.soak_gw_base import (
    DEVICES,
    LINES_PER_KIND,
    LOG_BASE,
    LOG_PER_S,
    LOG_WINDOW_S,
    MAX_LINE,
    RECOVER_S,
    Case,
    Prep,
    Run,
    answered_each,
    failed_reads,
    requests,
    sample,
    scraped,
    served,
    server_cases,
    worst_ratio,
)

MAX_EXTRA_FDS = 4  # fds after the fault over the quiet figure (a reconnect in flight)
PEER_UNITS = (1, 2, 3, 4)  # 1-3 the bystanders; 4 a slave for the cases' own jobs


def cases() -> list[Case | StartCase]:
    return [*server_cases(), *north_cases(), *line_cases(), *loop_cases(), *start_cases()]


def per_second(before: dict[str, int] | None, after: dict[str, int] | None,
               span: float) -> dict[str, float]:
    if before is None or after is None:
        return {}
    return {code: (after[code] - before[code]) / span for code in after}


def merged(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """``extra`` over ``base``, section by section (serve units appended)."""
    out = dict(base)
    for key, value in extra.items():
        if key == "serve" and isinstance(value, dict):
            serve = dict(out.get("serve", {}))
            units = [*serve.get("units", []), *value.get("units", [])]
            serve.update({k: v for k, v in value.items() if k != "units"}, units=units)
            out["serve"] = serve
        else:
            out[key] = value
    return out


def run_case(case: Case, seconds: float, quiet: float, workdir: Path) -> dict[str, Any]:
    conf = workdir / case.name
    conf.mkdir()
    serve_port, metrics_port = free_port(), free_port()
    with ExitStack() as stack:
        peer = stack.enter_context(PymodbusSlave(
            "rtu-over-tcp", units=PEER_UNITS, size=200, response_delay=case.peer_delay))
        prep = Prep(conf, workdir, stack, peer)
        if case.prep is not None:
            case.prep(prep)
        for unit in range(1, DEVICES + 1):
            write_json(conf / f"dev{unit}.json", device_file(peer.port, unit, f"dev{unit}"))
        for stem, data in prep.devices.items():
            write_json(conf / f"{stem}.json", data)
        write_json(conf / "gateway.json", merged({
            "metrics": {"port": metrics_port},
            "serve": {"listen": f"127.0.0.1:{serve_port}",
                      "maxConnections": case.serve_max_connections, "idleTimeoutS": 600,
                      "units": [{"unitId": 1, "device": "dev1"}]}}, prep.gateway))
        gw = stack.enter_context(
            GatewayProcess(conf, workdir / f"{case.name}.log", nofile=case.nofile))
        run = Run(conf, serve_port, metrics_port, gw, peer, extras=prep.extras,
                  bystanders=prep.bystanders)

        def polled() -> int:
            count = requests(peer) if case.polled is None else case.polled(run)
            if count is None:
                raise SystemExit(f"{case.name}: the bystanders' polls cannot be counted "
                                 f"(the exporter does not answer):\n{gw.log[-2000:]}")
            return count
        deadline = time.monotonic() + 30
        while not (served(run) and scraped(run)):
            if time.monotonic() > deadline or not gw.alive():
                raise SystemExit(f"{case.name}: the gateway did not start:\n{gw.log}")
            time.sleep(0.1)
        while case.ready is not None and not case.ready(run):
            if time.monotonic() > deadline + 60 or not gw.alive():
                raise SystemExit(f"{case.name}: not ready for its quiet window:\n{gw.log}")
            time.sleep(0.1)
        count, each = polled(), answered_each(run)
        failed_before = failed_reads(run)
        q_first, q_last, _ = sample(gw, quiet)
        quiet_rate = (polled() - count) / (q_last.at - q_first.at)
        quiet_each = per_second(each, answered_each(run), q_last.at - q_first.at)
        log_at = len(gw.log)
        # each bystander's rate from just before the fault to just after it (a scrape
        # may not be answered inside the window: the fd limit cases)
        each, each_at = answered_each(run), time.monotonic()
        with case.attack(run, seconds):
            count = polled()
            first, last, peak = sample(gw, seconds)
            rate = (polled() - count) / (last.at - first.at)
        each_after = answered_each(run)
        while each_after is None and time.monotonic() - last.at < RECOVER_S and gw.alive():
            time.sleep(0.2)
            each_after = answered_each(run)
        attacked_each = per_second(each, each_after, time.monotonic() - each_at)
        lines = gw.log[log_at:].splitlines()
        started = time.monotonic()
        recovered = None
        while time.monotonic() - started < RECOVER_S and gw.alive():
            if case.recover(run):
                recovered = time.monotonic() - started
                break
            time.sleep(0.2)
        # threads and fds back to the quiet figure (the loop engine's job threads end
        # after IDLE_SECONDS without a job)
        after = gw.usage() if gw.alive() else None
        while (after is not None and time.monotonic() - started < RECOVER_S
               and (after.threads > q_last.threads or after.fds > q_last.fds + MAX_EXTRA_FDS)):
            time.sleep(0.2)
            after = gw.usage() if gw.alive() else None
        failed_after = failed_reads(run) if gw.alive() else None
        rc = gw.stop() if gw.alive() else gw.proc.returncode if gw.proc else None
        verdict = case.verdict(run) if case.verdict is not None else []
    span = last.at - first.at
    figures = {
        "case": case.name, "row": case.row, "nofile": case.nofile,
        "cpuQuiet": round((q_last.cpu - q_first.cpu) / (q_last.at - q_first.at), 3),
        "cpuAttacked": round((last.cpu - first.cpu) / span, 3),
        "threadCpu": round(cpu_share(first, last)[1], 3),
        "rssKiB": [q_last.rss_kib, peak.rss_kib], "fds": [q_last.fds, peak.fds],
        "fdsAfter": None if after is None else after.fds,
        "threads": [q_last.threads, peak.threads],
        "threadsAfter": None if after is None else after.threads, "logLines": len(lines),
        "longestLine": max((len(ln) for ln in lines), default=0),
        "tracebacks": sum("Traceback" in ln for ln in lines),
        "quietRate": round(quiet_rate, 2),
        "bystanderRate": round(rate / quiet_rate, 3) if quiet_rate else 0.0,
        "worstBystander": round(worst_ratio(quiet_each, attacked_each), 3),
        "minRate": case.min_rate, "maxThreadCpu": case.max_thread_cpu,
        "extraThreads": case.extra_threads,
        "recoveredS": None if recovered is None else round(recovered, 2), "exit": rc,
        "valuesLost": (None if failed_before is None or failed_after is None
                       else failed_after - failed_before),
        **run.notes,
    }
    figures["maxLogLines"] = int(
        LOG_BASE + LOG_PER_S * seconds + case.log_per_event * figures.get("events", 0)
        + case.log_kinds * LINES_PER_KIND * (math.ceil(seconds / LOG_WINDOW_S) + 1))
    figures["failures"] = check(figures) + verdict
    return figures


def check(f: dict[str, Any]) -> list[str]:
    bad = []
    if f["threadCpu"] > f["maxThreadCpu"]:
        bad.append(f"thread CPU {f['threadCpu']} > {f['maxThreadCpu']}")
    if f["valuesLost"] != 0:
        bad.append(f"values lost: {f['valuesLost']}")
    if f["logLines"] > f["maxLogLines"]:
        bad.append(f"{f['logLines']} log lines")
    if f["longestLine"] > MAX_LINE:
        bad.append(f"a log line of {f['longestLine']} characters")
    if f["tracebacks"]:
        bad.append(f"{f['tracebacks']} tracebacks")
    if f["bystanderRate"] < f["minRate"]:
        bad.append(f"bystander polling at {f['bystanderRate']:.0%} of the quiet rate")
    if f["worstBystander"] < f["minRate"]:
        bad.append(f"a bystander polled at {f['worstBystander']:.0%} of its quiet rate")
    if f["threads"][1] > f["threads"][0] + f["extraThreads"]:
        bad.append(f"threads {f['threads'][0]} -> {f['threads'][1]}")
    if f["threadsAfter"] is not None and f["threadsAfter"] > f["threads"][0]:
        bad.append(f"threads after the fault {f['threadsAfter']} (quiet {f['threads'][0]})")
    if f["fdsAfter"] is not None and f["fdsAfter"] > f["fds"][0] + MAX_EXTRA_FDS:
        bad.append(f"fds after the fault {f['fdsAfter']} (quiet {f['fds'][0]})")
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
            f" | {r['fds'][0]} -> {r['fds'][1]} -> {r['fdsAfter']} | "
            f"{r['threads'][0]} -> {r['threads'][1]} -> {r['threadsAfter']} | "
            f"{r['logLines']} ({r['longestLine']}) | {r['bystanderRate']:.0%} of "
            f"{r['quietRate']}/s (worst {r['worstBystander']:.0%}) | {r['valuesLost']} | "
            f"{r['recoveredS']} s | {'; '.join(r['failures']) or 'ok'} |")
    return "\n".join(out)


def start_table(rows: list[dict[str, Any]]) -> str:
    head = ("| case | exit | seconds | RSS MiB | log lines (longest) | log bytes | "
            "the line | result |")
    out = [head, "|" + "---|" * 8]
    for r in rows:
        line = r["line"].replace("|", "\\|")
        out.append(
            f"| {r['case']} | {r['exit']} | {r['seconds']} | {r['rssKiB'] / 1024:.0f} | "
            f"{r['logLines']} ({r['longestLine']}) | {r['logBytes']} | {line} | "
            f"{'; '.join(r['failures']) or 'ok'} |")
    return "\n".join(out)


NOTES = ("scrapes", "scrapesFailed", "slowestScrapeS", "events", "attackerErrors")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="fault window per case")
    parser.add_argument("--quiet", type=float, default=5.0, help="quiet window per case")
    parser.add_argument("--cases", default="", help="comma-separated case names")
    parser.add_argument("--quick", action="store_true", help="6 s faults, 3 s quiet")
    parser.add_argument("--json", type=Path, default=None, help="write every figure here")
    parser.add_argument("--keep", type=Path, default=None,
                        help="work in this (new) folder and keep it: the logs")
    args = parser.parse_args(argv)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # its client's retry lines
    if args.quick:
        args.seconds, args.quiet = 6.0, 3.0
    chosen = [c for c in cases() if not args.cases or c.name in args.cases.split(",")]
    if not chosen:
        parser.error(f"--cases {args.cases!r}: known: {', '.join(c.name for c in cases())}")
    rows, starts = [], []
    if args.keep is not None:
        args.keep.mkdir(parents=True)
    with (contextlib.nullcontext(str(args.keep)) if args.keep is not None
          else tempfile.TemporaryDirectory(prefix="soak-gateway-")) as tmp:
        for case in chosen:
            print(f"{case.name}: {case.row} ...", file=sys.stderr, flush=True)
            if isinstance(case, StartCase):
                starts.append(run_start_case(case, Path(tmp)))
            else:
                rows.append(run_case(case, args.seconds, args.quiet, Path(tmp)))
    if rows:
        print(table(rows))
    if starts:
        print(start_table(starts))
    for r in rows:
        notes = {k: r[k] for k in r if k in NOTES or k.startswith("x_")}
        if notes:
            print(f"{r['case']}: {json.dumps(notes)}")
    if args.json is not None:
        args.json.write_text(json.dumps(rows + starts, indent=1))
    return 1 if any(r["failures"] for r in rows + starts) else 0


if __name__ == "__main__":
    sys.exit(main())
