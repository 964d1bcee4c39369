"""Soak test (`make soak`, not in CI): many slaves on one line with mixed faults.

Our simulator runs in a child process (its CPU and memory are not ours) with --slaves
slaves (default 10) on one RTU-over-TCP line.  Each slave misbehaves on a random 1-5 %
of its replies (rate drawn per slave): the reply is dropped, its CRC or a data byte is
corrupted, the byte count is wrong, another slave id answers, it comes after the
response timeout (within the settle window), it is truncated, garbage follows or
precedes it, a random frame replaces it, or the connection is closed.

One DriverModbusRtu per slave (all sharing the line, as on RS-485) polls registers,
input registers, coils and discrete inputs whose values never change: every register
holds default_register(slave, address), a value unique to (slave, address), so a value
from another request (another block, another slave, a late reply) differs from it.  The
address_updated_callback checks every reported value against that formula.

Prints progress every --report-every seconds and a summary: reads, faults injected,
faults detected, values from the wrong request (must be 0), memory growth, fd and thread
counts.  Exit status 1 if any wrong value was reported, nothing was read, or fds or
threads leaked once the drivers were stopped.

    python tools/soak.py --seconds 600
    python tools/soak.py --seconds 20 --self-check   # the wrong-value check itself works:
        # slaves answer with another request's reply, which must be caught
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import random
import resource
import select
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

# Fault kinds: (weight, the simulator knob counted in Slave.stats()["faults"]).
KINDS: dict[str, tuple[float, str]] = {
    "drop": (2, "drop_every"),
    "crc": (2, "corrupt_crc_every"),
    "corrupt-data": (1, "corrupt_data_every"),
    "wrong-byte-count": (2, "wrong_byte_count_every"),
    "answer-as-other": (2, "answer_as"),
    "late-reply": (1, "delay"),
    "truncate": (2, "truncate_every"),
    "garbage-after": (1, "trailing_garbage"),
    "noise-before": (1, "noise_before"),
    "random-frame": (1, "random_reply_count"),
    "close": (0.5, "close_every"),
    # --self-check only: the slave answers with its last reply to another request of the
    # same function and size, which RTU cannot tell apart (no transaction id); proves
    # that the soak's wrong-value check catches such a value
    "stale-reply": (1, "stale_reply"),
}
DEFAULT_KINDS = [k for k in KINDS if k != "stale-reply"]

# Items of each slave: (area, first address, count, data type); far enough apart to be
# separate read blocks (default maxMergeAddressGap 10).  Three holding blocks of the same
# size, read one after the other: a stale reply to one of them passes every check
# libmodbus makes (slave id, function, byte count) when taken as the answer to the next,
# which is the hazard the settle window exists for.
LAYOUT = [
    ("hr", 0, 10, "UInt16"),
    ("hr", 40, 1, "Int32"),
    ("hr", 300, 10, "UInt16"),
    ("hr", 400, 10, "UInt16"),
    ("ir", 100, 10, "UInt16"),
    ("coil", 0, 16, "Boolean"),
    ("di", 8, 16, "Boolean"),
]


# -- the simulator side (child process) ---------------------------------------------------


def serve(args: argparse.Namespace) -> int:
    """Run the simulator with faulty slaves; print {"port": N}, then answer "stats"
    lines on stdin with the simulator's stats as JSON; stop at EOF."""
    from edgemodbus import sim as simulator
    from edgemodbus.sim import server

    base = simulator.Slave
    rng = random.Random(args.seed)
    kinds = args.kinds
    weights = [KINDS[k][0] for k in kinds]
    timeout = args.read_timeout_ms / 1000
    defaults = simulator.Faults()
    made: list[Any] = []  # the FaultySlaves, in slave id order

    class FaultySlave(base):  # type: ignore[misc, valid-type]
        """A slave that arms one fault knob for one reply, at a random rate."""

        def __init__(self, slave_id: int, size: int = simulator.DEFAULT_SIZE) -> None:
            super().__init__(slave_id, size)
            self.rate = rng.uniform(args.min_rate, args.max_rate)
            self.sent: dict[bytes, tuple[bytes, bytes]] = {}  # (fc, count) -> (request, reply)
            self.stale = 0
            made.append(self)

        def _handle(self, raw: bytes, *a: Any, **kw: Any) -> Any:
            if rng.random() >= self.rate:
                actions = super()._handle(raw, *a, **kw)
                if "stale-reply" in kinds and actions and isinstance(actions[-1][1], bytes):
                    self.sent[raw[1:2] + raw[4:6]] = (raw, actions[-1][1])
                return actions
            kind = rng.choices(kinds, weights)[0]
            knob = KINDS[kind][1]
            if knob == "stale_reply":
                actions = super()._handle(raw, *a, **kw)
                request, reply = self.sent.get(raw[1:2] + raw[4:6], (raw, b""))
                if request != raw and actions:
                    self.stale += 1
                    actions[-1] = (actions[-1][0], reply)
                return actions
            f = self.faults
            if knob.endswith("_every"):
                value: Any = 1
            elif knob == "answer_as":
                value = rng.choice([s for s in range(1, args.slaves + 2) if s != self.slave_id])
            elif knob == "delay":
                # by default after the response timeout and before the settle window (one
                # more timeout) ends: the settle rule (docs/architecture.md) says such a
                # reply is never taken
                value = rng.uniform(*args.late) * timeout
            elif knob == "random_reply_count":
                value = 1
            else:
                value = rng.randbytes(rng.randint(1, 8))
            setattr(f, knob, value)
            try:
                return super()._handle(raw, *a, **kw)
            finally:
                setattr(f, knob, getattr(defaults, knob))

    server.Slave = FaultySlave  # type: ignore[misc]  # Simulator.add_slave makes ours
    sim = simulator.Simulator(slaves=range(1, args.slaves + 1), size=1000, seed=args.seed)
    server.Slave = base  # type: ignore[misc]
    port = sim.serve_tcp("127.0.0.1", 0)
    print(json.dumps({"port": port, "rates": {s.slave_id: s.rate for s in made}}),
          flush=True)
    try:
        for line in sys.stdin:
            if line.strip() == "stats":
                stats = sim.stats()
                for s in made:
                    if s.stale:
                        stats["slaves"][s.slave_id]["faults"]["stale_reply"] = s.stale
                print(json.dumps(stats), flush=True)
    finally:
        sim.stop()
    return 0


# -- the driver side ---------------------------------------------------------------------


def rss_kb(pid: int | str = "self") -> int:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def fd_count() -> int:
    return len(os.listdir("/proc/self/fd"))


def cpu_seconds() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


class Simulator:
    """The child process and its little stdin/stdout protocol."""

    def __init__(self, args: argparse.Namespace) -> None:
        cmd = [sys.executable, os.path.abspath(__file__), "--serve", "--slaves",
               str(args.slaves), "--seed", str(args.seed), "--min-rate", str(args.min_rate),
               "--max-rate", str(args.max_rate), "--read-timeout-ms", str(args.read_timeout_ms),
               "--late", ",".join(map(str, args.late)), "--log-level", args.log_level,
               "--kinds", ",".join(args.kinds)]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True)
        hello = self._line(15.0)
        self.port: int = hello["port"]
        self.rates: dict[str, float] = hello["rates"]

    def _line(self, timeout: float) -> dict[str, Any]:
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            self.stop()
            raise RuntimeError("soak: the simulator process did not answer")
        result: dict[str, Any] = json.loads(line)
        return result

    def stats(self) -> dict[str, Any]:
        assert self.proc.stdin is not None
        self.proc.stdin.write("stats\n")
        self.proc.stdin.flush()
        return self._line(10.0)

    def stop(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for pipe in (self.proc.stdin, self.proc.stdout):
            if pipe is not None and not pipe.closed:
                pipe.close()


def expected_values(slave: int) -> dict[str, object]:
    """Item name -> the value the formula gives (what the slave really holds)."""
    from edgemodbus.sim import default_bit, default_register

    values: dict[str, object] = {}
    for area, first, count, dtype in LAYOUT:
        for a in range(first, first + count):
            name = f"s{slave}.{area}{a}"
            if dtype == "Boolean":
                values[name] = default_bit(slave, a)
            elif dtype == "Int32":
                raw = default_register(slave, a) << 16 | default_register(slave, a + 1)
                values[name] = raw - (1 << 32) if raw & 0x8000_0000 else raw
            else:
                values[name] = default_register(slave, a)
    return values


def device_config(args: argparse.Namespace, port: int, slave: int) -> Any:
    import edgemodbus as em

    items = [
        {"name": f"s{slave}.{area}{a}", "address": f"{area}:{a}", "deviceDataType": dtype}
        for area, first, count, dtype in LAYOUT
        for a in range(first, first + count)
    ]
    return em.load_device_config({
        "organization": {"deviceCode": f"soak{slave}"},
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
            "slaveId": slave, "readTimeout": args.read_timeout_ms, "byteTimeout": 50,
            "readCycle": args.cycle_ms, "connectTimeout": 1000, "reconnectInterval": 200,
            "maxBackoff": 2000,
        },
        "addressList": items,
    })


class Checker:
    """address_updated_callback: every reported Ok value must be the formula's."""

    def __init__(self, expected: dict[str, object]) -> None:
        self.expected = expected
        self.reports = 0
        self.invalid = 0
        self.wrong = 0
        self.examples: list[str] = []
        self.lock = threading.Lock()

    def __call__(self, item: Any) -> None:
        from edgemodbus.datatypes import ItemStatus

        with self.lock:
            self.reports += 1
            if item.status is not ItemStatus.OK:
                self.invalid += 1
                return
            want = self.expected[item.name]
            if item.value != want or type(item.value) is not type(want):
                self.wrong += 1
                if len(self.examples) < 10:
                    self.examples.append(f"{item.name} = {item.value!r}, expected {want!r}")


def totals(drivers: list[Any]) -> tuple[Counter[str], dict[str, Any]]:
    """Device counters summed over the drivers, and the (shared) line's counters."""
    total: Counter[str] = Counter()
    line: dict[str, Any] = {}
    for drv in drivers:
        st = drv.stats()
        line = st.get("line", line)
        for key in ("requests", "responses", "timeouts", "crcErrors", "protocolErrors",
                    "retries", "cycles", "failedCycles"):
            total[key] += int(st.get(key, 0))
        total["exceptions"] += sum(st.get("exceptions", {}).values())
    return total, line


def detected(total: Counter[str], line: dict[str, Any]) -> int:
    return (total["timeouts"] + total["crcErrors"] + total["protocolErrors"]
            + total["exceptions"] + int(line.get("linkErrors", 0)))


def injected(stats: dict[str, Any]) -> Counter[str]:
    knob_kind = {knob: kind for kind, (_w, knob) in KINDS.items()}
    count: Counter[str] = Counter()
    for slave in stats["slaves"].values():
        for knob, n in slave["faults"].items():
            count[knob_kind.get(knob, knob)] += n
    return count


@contextmanager
def running(args: argparse.Namespace, port: int, checker: Checker) -> Iterator[list[Any]]:
    import edgemodbus as em

    drivers: list[Any] = []
    try:
        for slave in range(1, args.slaves + 1):
            cfg = device_config(args, port, slave)
            drv = em.DriverModbusRtu()
            drv.address_updated_callback = checker
            if not drv.start_device(cfg.organization, cfg.communication, cfg.address_list):
                raise RuntimeError(f"soak: slave {slave} did not start")
            drivers.append(drv)
        yield drivers
    finally:
        for drv in drivers:
            drv.stop_device()


def settle_count(fn: Any, target: int, seconds: float = 3.0) -> int:
    """fn() once it is back to target (closing sockets and threads may lag a little)."""
    deadline = time.monotonic() + seconds
    value = fn()
    while value > target and time.monotonic() < deadline:
        time.sleep(0.05)
        value = fn()
    return int(value)


def soak(args: argparse.Namespace) -> int:
    import edgemodbus  # noqa: F401  (loaded before the baseline: its memory is not growth)

    sim = Simulator(args)
    expected: dict[str, object] = {}
    for slave in range(1, args.slaves + 1):
        expected.update(expected_values(slave))
    checker = Checker(expected)
    fds0, threads0, rss0 = fd_count(), threading.active_count(), rss_kb()
    rates = ", ".join(f"{float(r) * 100:.1f}" for r in sim.rates.values())
    print(f"soak: {args.slaves} slaves on 127.0.0.1:{sim.port} (simulator pid "
          f"{sim.proc.pid}), fault rates % {rates}; {args.seconds:.0f} s, cycle "
          f"{args.cycle_ms} ms, timeout {args.read_timeout_ms} ms; fds {fds0}, threads "
          f"{threads0}", flush=True)
    start = time.monotonic()
    cpu0 = cpu_seconds()
    warm_at = start + min(30.0, args.seconds / 10)
    warm: tuple[int, int, int] | None = None
    try:
        with running(args, sim.port, checker) as drivers:
            next_report = start + args.report_every
            while (now := time.monotonic()) < start + args.seconds:
                time.sleep(min(0.5, start + args.seconds - now))
                now = time.monotonic()
                if warm is None and now >= warm_at:
                    warm = (rss_kb(), fd_count(), threading.active_count())
                if now >= next_report:
                    next_report += args.report_every
                    total, line = totals(drivers)
                    print(f"  {now - start:6.0f} s: reads {total['requests']}, faults detected "
                          f"{detected(total, line)}, wrong values {checker.wrong}, rss "
                          f"{rss_kb() / 1024:.1f} MB, fds {fd_count()}", flush=True)
            elapsed = time.monotonic() - start
            cpu = cpu_seconds() - cpu0
            rss_end, fds_end, threads_end = rss_kb(), fd_count(), threading.active_count()
            total, line = totals(drivers)
            snapshots = [drv.snapshot() for drv in drivers]
        fds_after = settle_count(fd_count, fds0)
        threads_after = settle_count(threading.active_count, threads0)
        sim_stats = sim.stats()
        sim_rss = rss_kb(sim.proc.pid)
    finally:
        sim.stop()

    final_wrong: list[str] = []
    for snap in snapshots:
        for name, item in snap["items"].items():
            value = item.get("value")
            if value is not None and value != expected[name]:
                final_wrong.append(f"{name} = {value!r} in the final snapshot")
    faults = injected(sim_stats)
    warm = warm or (rss0, fds0, threads0)
    growth = (rss_end - warm[0]) / 1024
    reads = total["requests"]
    ok_replies = total["responses"] - total["crcErrors"] - total["protocolErrors"]
    print()
    print("soak summary")
    print(f"  duration            {elapsed:.0f} s, {args.slaves} slaves, "
          f"{len(expected)} items, {total['cycles']} device cycles")
    print(f"  reads               {reads} requests ({reads / elapsed:.0f}/s), "
          f"{ok_replies} good replies, {checker.reports} item reports")
    print(f"  faults injected     {sum(faults.values())}: "
          + ", ".join(f"{k} {n}" for k, n in sorted(faults.items(), key=lambda kv: -kv[1])))
    print(f"  faults detected     {detected(total, line)}: timeouts {total['timeouts']}, "
          f"crc {total['crcErrors']}, protocol {total['protocolErrors']}, exceptions "
          f"{total['exceptions']}, link errors {line.get('linkErrors', 0)} "
          f"(reconnects {line.get('reconnects', 0)}, discarded bytes "
          f"{line.get('discardedBytes', 0)}); retries {total['retries']}, failed cycles "
          f"{total['failedCycles']}, Invalid reports {checker.invalid}")
    must = "must be > 0: self-check" if args.self_check else "must be 0"
    print(f"  wrong values        {checker.wrong + len(final_wrong)} ({must})")
    for example in (checker.examples + final_wrong)[:10]:
        print(f"                      {example}")
    print(f"  memory (RSS)        start {rss0 / 1024:.1f} MB, after warm-up "
          f"{warm[0] / 1024:.1f} MB, end {rss_end / 1024:.1f} MB: growth {growth:+.1f} MB "
          f"after warm-up; simulator process {sim_rss / 1024:.1f} MB")
    print(f"  fds                 start {fds0}, running {warm[1]} -> {fds_end}, after stop "
          f"{fds_after}")
    print(f"  threads             start {threads0}, running {warm[2]} -> {threads_end}, "
          f"after stop {threads_after}")
    print(f"  driver CPU          {cpu:.1f} s ({100 * cpu / elapsed:.1f} % of one core)")
    failures = []
    if args.self_check:
        if not checker.wrong:
            failures.append("self-check: stale replies were injected but no wrong value seen")
    elif checker.wrong or final_wrong:
        failures.append("values from the wrong request")
    if reads == 0 or ok_replies == 0:
        failures.append("nothing was read")
    if fds_after > fds0:
        failures.append(f"{fds_after - fds0} fds leaked")
    if threads_after > threads0:
        failures.append(f"{threads_after - threads0} threads leaked")
    print(f"soak: {'FAILED: ' + ', '.join(failures) if failures else 'passed'}")
    return 1 if failures else 0


def _kinds(text: str) -> list[str]:
    kinds = [k.strip() for k in text.split(",") if k.strip()]
    unknown = [k for k in kinds if k not in KINDS]
    if unknown or not kinds:
        raise argparse.ArgumentTypeError(f"unknown kinds {unknown}; known: {', '.join(KINDS)}")
    return kinds


def _pair(text: str) -> tuple[float, float]:
    lo, hi = (float(x) for x in text.split(","))
    if not 0 < lo <= hi:
        raise argparse.ArgumentTypeError("LO,HI with 0 < LO <= HI")
    return lo, hi


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=600.0)
    parser.add_argument("--slaves", type=int, default=10)
    parser.add_argument("--min-rate", type=float, default=0.01, help="fault rate, lowest")
    parser.add_argument("--max-rate", type=float, default=0.05, help="fault rate, highest")
    parser.add_argument("--cycle-ms", type=int, default=100, help="readCycle of each slave")
    parser.add_argument("--read-timeout-ms", type=int, default=150, help="readTimeout")
    parser.add_argument("--report-every", type=float, default=30.0, help="progress, seconds")
    parser.add_argument("--seed", type=int, default=None, help="fault schedule seed")
    parser.add_argument("--late", type=_pair, default=(1.15, 1.75), metavar="LO,HI",
                        help="late replies come after LO..HI x readTimeout (default 1.15,1.75: "
                        "inside the settle window)")
    parser.add_argument("--log-level", default="ERROR", help="of the edgemodbus loggers")
    parser.add_argument("--kinds", type=_kinds, default=DEFAULT_KINDS,
                        help=f"comma-separated fault kinds (default {','.join(DEFAULT_KINDS)})")
    parser.add_argument("--self-check", action="store_true",
                        help="inject only stale replies (another request's answer) and pass "
                        "only if the wrong-value check catches them")
    parser.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if not 1 <= args.slaves <= 246:
        parser.error("--slaves: 1..246")
    if args.seed is None:
        args.seed = random.randrange(1 << 30)
    if args.self_check:
        args.kinds = ["stale-reply"]
    logging.basicConfig(level=args.log_level.upper(), format="%(name)s: %(message)s")
    return serve(args) if args.serve else soak(args)


if __name__ == "__main__":
    sys.exit(main())
