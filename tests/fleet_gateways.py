"""Gateway instances of a dial-in fleet for the tests and the bench (docs/deploy.md): each
instance ``python -m edgemodbus.gateway`` in a child process (tests/gateway_proc.py) with
a folder of its own holding the same device files but for ``listenPort`` (on separate
hosts the folder is one), ``EDGEMODBUS_INSTANCE`` set as the systemd template unit sets
it, and its /metrics port.  Each DTU ``n`` (id :func:`dtu_id`) has a slave whose ``hr:0``
holds :func:`value_of` ``n``, a value no other DTU has, so a value from the wrong DTU
shows.

The timings scale with the fleet (:class:`Timing`): one Python simulator process answers
every DTU and the instances share the machine, so at thousands of DTUs the scan rate, the
reply timeout and the dial rate are sized for it (the tests say what they wait for with
deadlines that grow with the size too)."""

from __future__ import annotations

import os
import re
import time
from collections.abc import Callable, Mapping
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tests.gateway_proc import GatewayProcess, scrape, write_json
from tests.peers import free_port
from tests.waiting import wait_for

INSTANCES = ("gw-1", "gw-2", "gw-3")
INSTANCE_ENV = "EDGEMODBUS_INSTANCE"
BASE = 1000  # DTU n's hr:0 holds BASE + n


def dtu_id(n: int) -> str:
    return f"FL{n:06d}"  # 8 bytes: the documented hash of the first 8 bytes


def value_of(n: int) -> int:
    return (BASE + n) & 0xFFFF


@dataclass(frozen=True)
class Timing:
    """What a fleet of ``dtus`` DTUs is polled and dialled with.

    ``read_cycle`` keeps the whole fleet at most about 1,000 requests a second (two blocks
    per device) above 1,000 DTUs: the simulator is one Python thread; ``read_timeout``
    grows with it (a reply queued behind a thousand others on a loaded machine);
    ``dial_rate``: the fleet dials in about 15 s (at least 100 a second), so the DTUs of
    a killed instance (a third) redial in about 5 s."""

    dtus: int

    @property
    def read_cycle(self) -> int:
        return max(1000, 2 * self.dtus)

    @property
    def read_timeout(self) -> int:
        return max(1000, self.dtus)

    @property
    def dial_rate(self) -> float:
        return max(100.0, self.dtus / 15)

    @property
    def load_timeout(self) -> float:
        """Seconds for an instance to load every device file (17 ms each with the loop
        engine, three instances starting together on a 2-core machine; about 70 ms
        with the thread engine, a thread per file)."""
        return 60 + self.dtus / 10

    @property
    def settle_timeout(self) -> float:
        """Seconds for every DTU to dial, register and report a first cycle."""
        return 60 + 2 * self.dtus / self.dial_rate + 3 * self.read_cycle / 1000


def device(n: int, port: int, timing: Timing, extra_items: int = 0,
           engine: str | None = None) -> dict[str, Any]:
    """DTU ``n``'s device file on listen port ``port``: items ``v`` (hr:0, its own
    value) and ``w`` (hr:100, written by the tests), and ``c`` (hr:1) with
    ``extra_items``.  Every DTU dials from 127.0.0.1 here, as a carrier NAT makes a
    site's DTUs share one address: ``maxUnregisteredPerSource`` is the port's cap."""
    comm: dict[str, Any] = {
        "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
        "registration": "text", "dtuId": dtu_id(n), "registrationTimeout": 5000,
        "maxUnregisteredPerSource": 512, "slaveId": 1, "readCycle": timing.read_cycle,
        "readTimeout": timing.read_timeout, "reconnectInterval": 500}
    if engine:
        comm["engine"] = engine
    items = [{"name": "v", "address": "hr:0", "deviceDataType": "UInt16"},
             {"name": "w", "address": "hr:100", "deviceDataType": "UInt16"}]
    if extra_items:
        items.append({"name": "c", "address": "hr:1", "deviceDataType": "UInt16"})
    return {"organization": {"deviceCode": f"m{n}"}, "communication": comm,
            "addressList": items}


def paced(cond: Callable[[], object], every: float = 0.5) -> Callable[[], object]:
    """``cond`` called at most once per ``every`` seconds (for wait_for, which polls every
    10 ms): a scrape of an instance's /metrics is about 6 kB per device, and polling it
    flat out would load the instances it measures."""
    last = [-every]

    def run() -> object:
        wait = last[0] + every - time.monotonic()
        if wait > 0:
            time.sleep(wait)  # pacing: a condition checked every `every` s, not flat out
        last[0] = time.monotonic()
        return cond()

    return run


def metric(text: str, name: str, labels: str = "") -> float | None:
    """The value of the sample ``name{labels}`` (``labels`` as Prometheus writes them,
    e.g. ``instance="gw-1"``), or None."""
    found = re.search(rf"^{re.escape(name)}(?:\{{{re.escape(labels)}\}})? (\S+)$", text, re.M) \
        if labels else re.search(rf"^{re.escape(name)}(?:\{{[^}}]*\}})? (\S+)$", text, re.M)
    return float(found.group(1)) if found else None


def held(port: int) -> int | None:
    """The instance's edgemodbus_dtu_held, or None when /metrics does not answer."""
    try:
        text = scrape(port, timeout=5)
    except OSError:
        return None
    value = metric(text, "edgemodbus_dtu_held")
    return None if value is None else int(value)


class Fleet:
    """The instances' folders, ports and processes.  ``gateway`` is merged into every
    instance's gateway file; ``names``: the instances (a lone gateway: one, and
    ``fleet=False`` leaves the ``fleet`` section out)."""

    def __init__(self, tmp: Path, broker: int, dtus: int, *,
                 names: tuple[str, ...] = INSTANCES, fleet: bool = True,
                 gateway: Mapping[str, Any] | None = None,
                 mqtt: Mapping[str, Any] | None = None, extra_items: int = 0,
                 engine: str | None = None) -> None:
        self.dtus, self.names = dtus, names
        self.timing = Timing(dtus)
        self.listen = {name: free_port() for name in names}
        self.metrics = {name: free_port() for name in names}
        self.dirs: dict[str, Path] = {}
        for name in names:
            folder = tmp / name
            folder.mkdir()
            conf: dict[str, Any] = {
                "gatewayId": "fleet",
                "mqtt": {"port": broker, "reconnectMin": 100, "reconnectMax": 1000,
                         "statusCheckInterval": 200, **(mqtt or {})},
                "metrics": {"host": "127.0.0.1", "port": self.metrics[name]},
                **(gateway or {})}
            if fleet:
                conf["fleet"] = {"loadBalancers": ["127.0.0.1"]}
            write_json(folder / "gateway.json", conf)
            for n in range(dtus):
                write_json(folder / f"m{n}.json",
                           device(n, self.listen[name], self.timing, extra_items, engine))
            self.dirs[name] = folder
        self.procs: dict[str, GatewayProcess] = {}

    def start(self, stack: ExitStack, ready: str = r"MQTT connected") -> None:
        """Start every instance, then wait until each logged ``ready``, answers on
        /metrics and has loaded every device file (its listen port knows every DTU id:
        a DTU that dials an instance still loading is refused as unknown)."""
        before = os.environ.get(INSTANCE_ENV)
        try:
            for name in self.names:
                os.environ[INSTANCE_ENV] = name  # as the systemd unit's %i; inherited
                proc = GatewayProcess(self.dirs[name], self.dirs[name] / "gateway.log",
                                      nofile=4 * self.dtus + 256)
                self.procs[name] = stack.enter_context(proc)
        finally:
            if before is None:
                os.environ.pop(INSTANCE_ENV, None)
            else:
                os.environ[INSTANCE_ENV] = before
        for name, proc in self.procs.items():
            proc.wait_log(ready, timeout=60)
            port = self.metrics[name]

            def loaded(port: int = port) -> bool:
                return self.loaded(port)

            wait_for(paced(loaded), timeout=self.timing.load_timeout,
                     what=f"{name} loading its {self.dtus} device files")

    def loaded(self, port: int) -> bool:
        """The instance's listen port knows every DTU id."""
        try:
            text = scrape(port, timeout=5)
        except OSError:
            return False
        return metric(text, "edgemodbus_dtu_listener_dtus") == self.dtus

    def live(self) -> dict[str, GatewayProcess]:
        return {name: proc for name, proc in self.procs.items() if proc.alive()}

    def held_by(self) -> dict[str, int]:
        """edgemodbus_dtu_held of each live instance."""
        return {name: held(self.metrics[name]) or 0 for name in self.live()}


def fleet_engine() -> str | None:
    """``FLEET_ENGINE`` (thread or loop) for the larger runs; unset: the default."""
    return os.environ.get("FLEET_ENGINE") or None
