"""Cases of `make soak-gateway` for the line's scheduling and its worker (issue #25's
rows "line scheduling" and "line worker"): jobs that SCADA masters put on the
bystanders' line (forwards to a live slave taking 10 ms, FC06 to a served unit,
forwards to a dead slave, a Sparkplug DCMD storm) must leave the bystanders at least
half their quiet polling rate; a device whose host name cannot be a host is told why
while the others are polled, and a forward to it is answered 0B at once."""

from __future__ import annotations

import os
import re
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from tools.soak_cases_north import dcmd_storm, sparkplug_broker
from tools.soak_gw_base import (
    FLOOD_RATE,
    Attack,
    Case,
    Prep,
    Run,
    own_device,
    served_and_scraped,
)

DEAD = 7  # a slave id the peer does not answer
FORWARD_UNIT, WRITE_UNIT, DEAD_UNIT, BAD_UNITS = 4, 5, 7, (8, 9)
LONG_LABEL = "p" * 64 + ".example"


def forward_prep(prep: Prep) -> None:
    own_device(prep)
    prep.gateway["serve"] = {"units": [{"unitId": FORWARD_UNIT, "forward": "dev4"}]}


def write_prep(prep: Prep) -> None:
    own_device(prep)
    prep.gateway["serve"] = {"units": [{"unitId": WRITE_UNIT, "device": "dev4"}]}


def dead_prep(prep: Prep) -> None:
    own_device(prep, DEAD, "dev7", readTimeout=700)
    prep.gateway["serve"] = {"units": [{"unitId": DEAD_UNIT, "forward": "dev7",
                                        "timeoutMs": 700}]}


def bad_host_prep(prep: Prep) -> None:
    own_device(prep, 8, "dev8", tcpHost="plc..local")
    own_device(prep, 9, "dev9", tcpHost=LONG_LABEL)
    prep.gateway["serve"] = {"units": [{"unitId": u, "forward": f"dev{u}"}
                                       for u in BAD_UNITS]}


class Master:
    """A pymodbus TCP master of the gateway's server that counts what it got: answers,
    exception codes, failures, and its slowest answer."""

    def __init__(self, port: int) -> None:
        from pymodbus.client import ModbusTcpClient

        self.client: Any = ModbusTcpClient("127.0.0.1", port=port, timeout=3, retries=0)
        self.answers = 0
        self.exceptions: dict[int, int] = {}
        self.failed = 0
        self.slowest = 0.0

    def ask(self, request: Callable[[Any], Any]) -> None:
        if not self.client.connected and not self.client.connect():
            self.failed += 1
            time.sleep(0.1)
            return
        started = time.monotonic()
        try:
            reply = request(self.client)
        except Exception:
            self.failed += 1
            self.client.close()
            return
        self.slowest = max(self.slowest, time.monotonic() - started)
        if reply.isError():
            code = int(getattr(reply, "exception_code", -1))
            self.exceptions[code] = self.exceptions.get(code, 0) + 1
        else:
            self.answers += 1

    def close(self) -> None:
        self.client.close()


@contextmanager
def masters(run: Run, n: int, request: Callable[[Any], Any]) -> Iterator[None]:
    """``n`` masters asking ``request`` back-to-back (a closed loop each) while the
    fault window lasts; their counts are the case's notes."""
    stop = threading.Event()
    them = [Master(run.serve_port) for _ in range(n)]

    def loop(master: Master) -> None:
        while not stop.is_set() and run.gw.alive():
            master.ask(request)

    threads = [threading.Thread(target=loop, args=(m,), name=f"soak-master-{i}")
               for i, m in enumerate(them)]
    for thread in threads:
        thread.start()
    try:
        yield
    finally:
        stop.set()
        for thread in threads:
            thread.join()
        for master in them:
            master.close()
        exceptions: dict[str, int] = {}
        for master in them:
            for code, count in master.exceptions.items():
                exceptions[f"{code:02X}"] = exceptions.get(f"{code:02X}", 0) + count
        run.notes.update(
            x_answers=sum(m.answers for m in them), x_exceptions=exceptions,
            x_failed=sum(m.failed for m in them),
            x_slowestS=round(max(m.slowest for m in them), 3))


def forward_flood(unit: int) -> Attack:
    """Two masters forwarding reads to ``unit`` back-to-back."""
    return lambda run, seconds: masters(run, 2, lambda c: c.read_holding_registers(
        0, count=2, device_id=unit))


def write_flood(unit: int) -> Attack:
    """Two masters writing FC06 to served ``unit`` back-to-back."""
    count = [0]

    def write(client: Any) -> Any:
        count[0] = (count[0] + 1) & 0xFFFF
        return client.write_register(0, count[0], device_id=unit)
    return lambda run, seconds: masters(run, 2, write)


def dead_flood(unit: int) -> Attack:
    """One master forwarding to ``unit`` (a dead slave) back-to-back."""
    return lambda run, seconds: masters(run, 1, lambda c: c.read_holding_registers(
        0, count=2, device_id=unit))


def bad_host_flood(run: Run, seconds: float) -> Any:
    unit = iter(lambda: BAD_UNITS[int(time.monotonic() * 10) % 2], None)
    return masters(run, 1, lambda c: c.read_holding_registers(
        0, count=2, device_id=next(unit)))


def answered_at_once(run: Run) -> list[str]:
    """Every forward to a device whose host cannot be a host answered at once: 0A where
    its file was refused at load (no such device: gateway path unavailable, Modbus
    Application Protocol 1.1b3 section 7), 0B where a device runs and cannot connect;
    a line names each host and why."""
    bad = []
    codes = set(run.notes.get("x_exceptions", {}))
    if run.notes.get("x_answers") or not codes or not codes <= {"0A", "0B"}:
        bad.append(f"forwards answered {run.notes.get('x_answers')} times, exceptions "
                   f"{run.notes.get('x_exceptions')}: not 0A/0B alone")
    if run.notes.get("x_slowestS", 0.0) > 0.5:
        bad.append(f"the slowest 0B took {run.notes['x_slowestS']} s")
    for code, host in (("dev8", "plc..local"), ("dev9", LONG_LABEL)):
        if not run.gw.lines(rf"tcpHost '{re.escape(host)}': is not a host name"):
            bad.append(f"no line says why {code}'s tcpHost is refused")
    return bad


def line_cases() -> list[Case]:
    return [
        Case("line-forward-loop", "line scheduling: two masters forwarding in a closed "
             "loop to a live slave taking 10 ms", forward_flood(FORWARD_UNIT), served_and_scraped,
             prep=forward_prep, min_rate=FLOOD_RATE, peer_delay=0.01, max_thread_cpu=1.0),
        Case("line-fc06-flood", "line scheduling: two masters writing FC06 to a served "
             "unit back-to-back", write_flood(WRITE_UNIT), served_and_scraped, prep=write_prep,
             min_rate=FLOOD_RATE, max_thread_cpu=1.0),
        Case("line-dead-forward", "line scheduling: one master forwarding back-to-back "
             "to a dead slave (timeout 0.7 s)", dead_flood(DEAD_UNIT), served_and_scraped,
             prep=dead_prep, min_rate=FLOOD_RATE, max_thread_cpu=1.0,
             ready=lambda run: bool(run.gw.lines(r"dev7: \w+ -> Offline"))),
        Case("line-dcmd-storm", "line scheduling: a Sparkplug DCMD storm to a device on "
             "the bystanders' line", dcmd_storm("dev4"), served_and_scraped,
             prep=sparkplug_broker, min_rate=FLOOD_RATE, max_thread_cpu=1.0,
             log_kinds=3),  # writes confirmed, refused (06: line busy), polling delayed
        Case("worker-bad-host", 'line worker: "tcpHost": "plc..local" and a 64-character '
             "label, forwards to both", bad_host_flood, served_and_scraped,
             prep=bad_host_prep, verdict=answered_at_once, max_thread_cpu=1.0,
             log_per_event=0),
    ]
