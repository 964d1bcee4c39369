"""Issue 5: the whole driver, 10,000 tags on 10 slaves over RTU-over-TCP.

Client CPU (this process, all threads: time.process_time) per tag read, with the slaves
played by our simulator in its own process, against references measured in the same run
on the same slave and the same block list:

* the floor (the "bare-libmodbus floor" of the targets in bench/gate.py): a bare loop
  issuing the driver's block reads through libmodbus's own ``modbus_read_registers``
  (``Context.read_libmodbus``: its send, then a select() and a read() per phase of the
  reply), no decoding;
* our bare reader, reported beside it and not gated: the same loop through our own C
  transaction (``Context.read``: csrc/emb_io.c ``emb_read`` over csrc/emb_rtu.c, which
  the driver's engine calls), no decoding: what the driver adds to its own reader;
* pymodbus 3.16.1's sync client doing the same block reads plus
  ``convert_from_registers`` for every item.

The references run ON THE LINE WORKER (a job submitted while the drivers are attached,
so polling pauses meanwhile), alternating with windows of driver polling: same thread,
same moment, same slave.  Each figure is the best of its windows (the least disturbed
on a shared machine); the median of the ratios of adjacent windows is shown as well.
The line is kept busy (readCycle 10 ms: every cycle overruns), like the floor's loop.

The driver is measured (a) with 1% and (b) with 100% of the values changing per cycle
(a :class:`FlipMover` per changing item, or per block); the changed fraction is taken
from ``stats()["valuesChanged"]``, not assumed.  The memory test reports RSS growth per
configured tag for 100,000 tags; it runs in a fresh process so that earlier tests do not
hide allocations.  Nothing here asserts a speed: the figures go to the table and to
``benchmark.extra_info``, and the headline ratios (the paired medians of (a) / floor,
(b) / floor and pymodbus / (a), and KB per tag) to the gate, whose targets are those of
issue 13 (bench/gate.py).

EDGEMODBUS_BENCH_PROFILE=1 adds a cProfile of the line worker during (a) and (b).
"""

from __future__ import annotations

import cProfile
import gc
import io
import multiprocessing
import os
import pstats
import socket
import statistics
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

import pytest
from pymodbus import FramerType
from pymodbus.client import ModbusTcpClient

import edgemodbus as em
from bench import gate
from bench.conftest import QUICK, cpu_seconds, report, scale
from bench.slave_process import Range, SimulatorProcess
from edgemodbus._ffi import Context
from edgemodbus.datatypes import Area, ItemStatus
from edgemodbus.line.endpoint import TcpEndpoint
from edgemodbus.line.worker import LineWorker

SLAVES = list(range(1, 11))
TAGS_PER_SLAVE = 1000
BLOCK = 120  # maxBlockReadRegisterCount
PROFILE = os.environ.get("EDGEMODBUS_BENCH_PROFILE") == "1"
DT = ModbusTcpClient.DATATYPE
T = TypeVar("T")

# -- the tags ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Tag:
    """One configured tag and how the pymodbus reference decodes the same registers."""

    name: str
    offset: int  # holding register
    registers: int
    config: dict[str, Any]
    datatype: Any  # pymodbus DATATYPE
    word_order: Literal["big", "little"] = "big"
    bit: int | None = None  # bit of the register
    boolean: bool = False  # whole register as a Boolean
    scale: float = 1.0


# A group of 20 tags, 31 registers (33 with the string), repeated: what a meter or a PLC
# map looks like.  (type, format, registers, extra config, pymodbus datatype, word order)
_GROUP: list[tuple[str, str | None, int, dict[str, Any], Any, Literal["big", "little"]]] = [
    ("Int16", None, 1, {}, DT.INT16, "big"),
    ("Int16", None, 1, {"dataMultiplier": 0.1, "convertedDataType": "Float"}, DT.INT16, "big"),
    ("UInt16", None, 1, {}, DT.UINT16, "big"),
    ("Int32", "CDAB", 2, {}, DT.INT32, "little"),
    ("Float", "ABCD", 2, {}, DT.FLOAT32, "big"),
    ("Int16", None, 1, {}, DT.INT16, "big"),
    ("UInt16", None, 1, {}, DT.UINT16, "big"),
    ("Int32", "CDAB", 2, {}, DT.INT32, "little"),
    ("Float", "ABCD", 2, {}, DT.FLOAT32, "big"),
    ("Double", "ABCD", 4, {}, DT.FLOAT64, "big"),
    ("Int16", None, 1, {}, DT.INT16, "big"),
    ("UInt16", None, 1, {}, DT.UINT16, "big"),
    ("Bit", None, 1, {}, DT.UINT16, "big"),
    ("Int32", "CDAB", 2, {}, DT.INT32, "little"),
    ("Float", "ABCD", 2, {}, DT.FLOAT32, "big"),
    ("Int16", None, 1, {}, DT.INT16, "big"),
    ("UInt16", None, 1, {}, DT.UINT16, "big"),
    ("Boolean", None, 1, {}, DT.UINT16, "big"),
    ("Float", "ABCD", 2, {}, DT.FLOAT32, "big"),
    ("UInt32", "ABCD", 2, {}, DT.UINT32, "big"),  # a String of 4 registers in 1 group of 5
]


def make_tags(slave: int, count: int = TAGS_PER_SLAVE) -> list[Tag]:
    """``count`` tags of one slave, contiguous from holding register 0."""
    tags: list[Tag] = []
    offset = 0
    for k in range(count):
        group, pos = divmod(k, len(_GROUP))
        kind, fmt, regs, extra, datatype, order = _GROUP[pos]
        name = f"s{slave}_t{k}"
        bit: int | None = None
        scale_ = float(extra.get("dataMultiplier", 1.0))
        if pos == len(_GROUP) - 1 and group % 5 == 0:
            kind, fmt, regs, extra, datatype, order = "String", None, 4, {}, DT.STRING, "big"
        config: dict[str, Any] = {"name": name, "deviceDataType": kind, **extra}
        if kind == "Bit":
            bit = 3
            config.update(deviceDataType="Boolean", address=f"3:{offset}.{bit}")
        else:
            config["address"] = f"3:{offset}"
        if fmt is not None:
            config["dataFormat"] = fmt
        if kind == "String":
            config.update(quantity=regs, encoding="latin-1")
        tags.append(Tag(name, offset, regs, config, datatype, order, bit,
                        kind == "Boolean", scale_))
        offset += regs
    return tags


def device_dict(port: int, slave: int, tags: list[Tag], read_cycle: int = 10) -> dict[str, Any]:
    return {
        "organization": {"deviceCode": f"bench{slave}"},
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
            "slaveId": slave, "readCycle": read_cycle, "readTimeout": 1000,
            "byteTimeout": 200, "maxBlockReadRegisterCount": BLOCK, "dataFormat": "ABCD",
        },
        "addressList": [t.config for t in tags],
    }


def initial_registers(slave: int, tags: list[Tag]) -> list[tuple[int, Area, int, list[int]]]:
    """Booleans start at 0 (so that a flip changes them), strings as ASCII text."""
    writes: list[tuple[int, Area, int, list[int]]] = []
    for t in tags:
        if t.boolean:
            writes.append((slave, Area.HOLDING_REGISTER, t.offset, [0]))
        elif t.datatype is DT.STRING:
            text = f"S{t.offset:07d}".encode()
            regs = [text[i] << 8 | text[i + 1] for i in range(0, 2 * t.registers, 2)]
            writes.append((slave, Area.HOLDING_REGISTER, t.offset, regs))
    return writes


# -- the line under test --------------------------------------------------------------------


@dataclass
class Line:
    """The simulator process, the tags and configs of its 10 slaves, and the driver's
    read plan (taken from ``read_plan()``), which the references read too."""

    sim: SimulatorProcess
    tags: dict[int, list[Tag]]
    configs: dict[int, em.DeviceConfig]
    blocks: list[tuple[int, int, int, list[Tag]]]  # slave, start, count, tags in it

    @property
    def n_tags(self) -> int:
        return sum(len(t) for t in self.tags.values())


@pytest.fixture(scope="module")
def line() -> Iterator[Line]:
    with SimulatorProcess(SLAVES, size=2000) as sim:
        tags = {s: make_tags(s) for s in SLAVES}
        sim.set_registers([w for s in SLAVES for w in initial_registers(s, tags[s])])
        configs = {s: em.load_device_config(device_dict(sim.port, s, tags[s])) for s in SLAVES}
        by_name = {t.name: t for ts in tags.values() for t in ts}
        blocks: list[tuple[int, int, int, list[Tag]]] = []
        with Drivers(configs) as drivers:
            for s, drv in zip(SLAVES, drivers.drivers, strict=True):
                for b in drv.read_plan():
                    assert b["function"] == 3
                    blocks.append((s, b["start"], b["count"], [by_name[n] for n in b["items"]]))
        yield Line(sim, tags, configs, blocks)


class Drivers:
    """One DriverModbusRtu per config, all on the same endpoint (one line worker);
    started on enter once every item has been read, stopped on exit."""

    def __init__(self, configs: dict[int, em.DeviceConfig]) -> None:
        self.configs = configs
        self.drivers: list[em.DriverModbusRtu] = []

    def __enter__(self) -> Drivers:
        try:
            for cfg in self.configs.values():
                drv = em.DriverModbusRtu()
                self.drivers.append(drv)
                assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            self.wait_cycles(2, timeout=60)
            for cfg in self.configs.values():
                bad = [i.name for i in cfg.address_list if i.status is not ItemStatus.OK]
                assert not bad, f"items not Ok: {bad[:5]}"
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        for drv in self.drivers:
            drv.stop_device()

    def totals(self) -> tuple[int, int]:
        """(tag reads, values changed) so far, summed over the drivers."""
        reads = changed = 0
        for drv in self.drivers:
            st = drv.stats()
            reads += st["cycles"] * drv.data_item_count
            changed += st["valuesChanged"]
        return reads, changed

    def wait_cycles(self, n: int, timeout: float) -> None:
        """Until every driver has completed ``n`` more cycles."""
        start = [d.stats().get("cycles", 0) for d in self.drivers]
        deadline = time.monotonic() + timeout
        while any(d.stats().get("cycles", 0) < c + n
                  for d, c in zip(self.drivers, start, strict=True)):
            if time.monotonic() > deadline:
                raise AssertionError(f"drivers did not complete {n} cycles in {timeout} s")
            time.sleep(0.05)  # poll: until n cycles (deadline above)

    @property
    def line(self) -> LineWorker:
        """The one line worker the drivers share."""
        port = next(iter(self.configs.values())).communication.tcp_port
        lines = [b for b in em.DriverModbusRtu.registry.lines()
                 if isinstance(b.endpoint, TcpEndpoint) and b.endpoint.port == port]
        assert len(lines) == 1, lines
        return lines[0]

    def on_worker(self, fn: Callable[[], T]) -> T:
        """Run ``fn`` on the line worker: polling pauses meanwhile, and the references
        run on the same thread as the driver, between two of its windows."""
        return self.line.submit(lambda _link: fn()).result(120)


# -- measurements -----------------------------------------------------------------------------


@dataclass
class Window:
    """CPU seconds spent on ``tag_reads`` tag reads (``changed`` of them new values)."""

    cpu: float
    tag_reads: int
    changed: int = 0

    @property
    def us_per_tag(self) -> float:
        return self.cpu / self.tag_reads * 1e6

    @property
    def changed_fraction(self) -> float:
        return self.changed / self.tag_reads


def measure_driver(drivers: Drivers, seconds: float) -> Window:
    """Process CPU and tag reads over ``seconds`` of polling (the main thread sleeps)."""
    reads0, changed0 = drivers.totals()
    cpu0 = cpu_seconds()
    time.sleep(seconds)  # pacing: the window measured
    cpu1 = cpu_seconds()
    reads1, changed1 = drivers.totals()
    return Window(cpu1 - cpu0, reads1 - reads0, changed1 - changed0)


def entries_per_round(drivers: Drivers, seconds: float) -> float:
    """How often the line worker came back from the engine to Python (its ``_dispatch``,
    counted for the bench's worker) per round of the line's devices (their cycles over
    ``seconds``, divided by how many they are).  The target: once per round with
    changes."""
    worker = drivers.line
    cls = type(worker)  # (a line worker has __slots__: its class's method is wrapped)
    calls = [0]
    dispatch = cls._dispatch

    def counted(self: Any, *args: Any) -> None:
        if self is worker:
            calls[0] += 1
        dispatch(self, *args)

    start = [drv.stats()["cycles"] for drv in drivers.drivers]
    cls._dispatch = counted  # type: ignore[method-assign]
    try:
        time.sleep(seconds)  # pacing: the window counted
    finally:
        cls._dispatch = dispatch  # type: ignore[method-assign]
    cycles = sum(drv.stats()["cycles"] - c for drv, c in zip(drivers.drivers, start,
                                                                 strict=True))
    return calls[0] / (cycles / len(drivers.drivers)) if cycles else float("inf")


def _connect(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=5)
    sock.settimeout(None)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def measure_bare(line: Line, passes: int, reader: Literal["libmodbus", "ours"]) -> Window:
    """The driver's block list read in a bare loop (a Context on a socket of its own, as
    the line worker opens it), nothing decoded: through libmodbus's own
    ``modbus_read_registers`` (``reader="libmodbus"``, the floor) or through our C
    transaction (``"ours"``, ``Context.read``).  ``passes`` is made odd: with the warm-up
    pass every block is read an even number of times, so the values the driver reads
    next have flipped as usual."""
    passes |= 1
    sock = _connect(line.sim.port)
    ctx = Context.on_socket(sock.fileno(), f"bare {reader}", mbap=False)
    try:
        ctx.set_timeouts(1.0, 0.2)
        plan = [(s, start, count) for s, start, count, _ in line.blocks]
        if reader == "libmodbus":
            read_libmodbus = ctx.read_libmodbus

            def one_pass() -> None:
                for s, start, count in plan:
                    read_libmodbus(s, start, count)
        else:
            read = ctx.read

            def one_pass() -> None:
                for s, start, count in plan:
                    read(s, 3, start, count)

        one_pass()  # warm-up
        cpu0 = cpu_seconds()
        for _ in range(passes):
            one_pass()
        return Window(cpu_seconds() - cpu0, passes * line.n_tags)
    finally:
        ctx.close()
        sock.close()


def measure_floor(line: Line, passes: int) -> Window:
    """The floor: the block list through libmodbus's ``modbus_read_registers``."""
    return measure_bare(line, passes, "libmodbus")


def measure_reader(line: Line, passes: int) -> Window:
    """Our bare reader: the block list through ``Context.read`` (csrc/emb_io.c)."""
    return measure_bare(line, passes, "ours")


def _pymodbus_decoder(tag: Tag) -> Callable[[Sequence[int]], object]:
    convert = ModbusTcpClient.convert_from_registers
    datatype, order = tag.datatype, tag.word_order
    if tag.bit is not None:
        bit = tag.bit
        return lambda regs: bool(convert(regs, DT.UINT16) >> bit & 1)  # type: ignore[operator]
    if tag.boolean:
        return lambda regs: bool(convert(regs, DT.UINT16))
    if datatype is DT.STRING:
        return lambda regs: convert(regs, DT.STRING, string_encoding="latin-1")
    if tag.scale != 1.0:
        factor = tag.scale
        return lambda regs: convert(regs, datatype, order) * factor  # type: ignore[operator]
    return lambda regs: convert(regs, datatype, order)


def measure_pymodbus(line: Line, passes: int) -> Window:
    """The same block reads with pymodbus' sync client, every item converted
    (``passes`` made odd as in :func:`measure_floor`)."""
    passes |= 1
    client = ModbusTcpClient("127.0.0.1", port=line.sim.port, framer=FramerType.RTU, timeout=2)
    assert client.connect()  # type: ignore[no-untyped-call]
    try:
        plan = [
            (s, start, count,
             [(t.offset - start, t.offset - start + t.registers, _pymodbus_decoder(t))
              for t in tags])
            for s, start, count, tags in line.blocks
        ]

        def one_pass() -> None:
            for s, start, count, items in plan:
                regs = client.read_holding_registers(start, count=count, device_id=s).registers
                for lo, hi, decode in items:
                    decode(regs[lo:hi])

        one_pass()  # warm-up (and a check that every item decodes)
        cpu0 = cpu_seconds()
        for _ in range(passes):
            one_pass()
        return Window(cpu_seconds() - cpu0, passes * line.n_tags)
    finally:
        client.close()  # type: ignore[no-untyped-call]


def flip_ranges(line: Line, fraction: float) -> list[Range]:
    """Movers making ``fraction`` of the tags change on every read: one tag in each run
    of 1/fraction (at a varying position, so of every type), or every block whole."""
    if fraction >= 1:
        return [(s, Area.HOLDING_REGISTER, start, count) for s, start, count, _ in line.blocks]
    every = round(1 / fraction)
    return [
        (s, Area.HOLDING_REGISTER, t.offset, t.registers)
        for s, tags in line.tags.items()
        for k, t in enumerate(tags)
        if k % every == (7 * (k // every) + s) % every
    ]


def profile_worker(drivers: Drivers, seconds: float) -> str:
    """cProfile (thread CPU time) of the line worker, enabled on it through a submitted
    job.  Profiling inflates Python's share; read it for where, not for how much."""
    prof = cProfile.Profile(time.thread_time)
    drivers.on_worker(prof.enable)
    time.sleep(seconds)  # pacing: the window profiled
    drivers.on_worker(prof.disable)
    out = io.StringIO()
    stats = pstats.Stats(prof, stream=out)
    stats.sort_stats("tottime").print_stats(20)
    return out.getvalue()


# -- the benchmark ----------------------------------------------------------------------------

SCENARIOS = (("a", 0.01), ("b", 1.0))


@pytest.mark.timeout(300)
def test_driver_cpu_per_tag(line: Line, benchmark: Any) -> None:
    repeats = scale(4, 2)
    window = 2.0 if not QUICK else 0.6
    passes = scale(25, 5)  # ~20 ms of line time per pass
    pym_passes = scale(9, 3)
    runs: dict[str, list[Window]] = {"floor": [], "reader": [], "pymodbus": [], "a": [],
                                     "b": []}
    entries: list[float] = []  # Python entries per round, in (a)
    pairs: dict[str, list[float]] = {"a": [], "b": [], "pym_a": [], "reader": [],
                                     "a_reader": []}
    profiles: dict[str, str] = {}
    try:
        for key, fraction in SCENARIOS:
            line.sim.flip(flip_ranges(line, fraction))
            with Drivers(line.configs) as drivers:
                for _ in range(repeats):
                    # the references run on the line worker, between two driver windows
                    floor = drivers.on_worker(lambda: measure_floor(line, passes))
                    ours = measure_driver(drivers, window)
                    reader = drivers.on_worker(lambda: measure_reader(line, passes))
                    pym = drivers.on_worker(lambda: measure_pymodbus(line, pym_passes))
                    runs["floor"].append(floor)
                    runs["reader"].append(reader)
                    runs[key].append(ours)
                    runs["pymodbus"].append(pym)
                    pairs[key].append(ours.us_per_tag / floor.us_per_tag)
                    pairs["reader"].append(reader.us_per_tag / floor.us_per_tag)
                    if key == "a":
                        pairs["pym_a"].append(pym.us_per_tag / ours.us_per_tag)
                        pairs["a_reader"].append(ours.us_per_tag / reader.us_per_tag)
                if key == "a":
                    entries.append(entries_per_round(drivers, window))
                if PROFILE:
                    profiles[key] = profile_worker(drivers, window)
                if key == "a":  # something for pytest-benchmark to record: a floor pass
                    benchmark.pedantic(lambda: drivers.on_worker(lambda: measure_floor(line, 1)),
                                       rounds=scale(5, 2), iterations=1)
    finally:
        line.sim.flip([])

    def best(key: str) -> Window:
        return min(runs[key], key=lambda w: w.us_per_tag)

    floor, reader, pym = best("floor"), best("reader"), best("pymodbus")
    a, b = best("a"), best("b")
    changed_a = statistics.mean(w.changed_fraction for w in runs["a"])
    changed_b = statistics.mean(w.changed_fraction for w in runs["b"])
    n_blocks = len(line.blocks)
    per_block = line.n_tags / n_blocks
    info: dict[str, Any] = {
        "tags": line.n_tags,
        "blocks": n_blocks,
        "tags_per_block": per_block,
        "floor_us_per_tag": floor.us_per_tag,
        "floor_us_per_block": floor.us_per_tag * per_block,
        "reader_us_per_tag": reader.us_per_tag,
        "reader_us_per_block": reader.us_per_tag * per_block,
        "ratio_reader_floor": reader.us_per_tag / floor.us_per_tag,
        "paired_median_ratio_reader_floor": statistics.median(pairs["reader"]),
        "paired_median_ratio_a_reader": statistics.median(pairs["a_reader"]),
        "pymodbus_us_per_tag": pym.us_per_tag,
        "a_us_per_tag": a.us_per_tag,
        "b_us_per_tag": b.us_per_tag,
        "a_changed_fraction": changed_a,
        "b_changed_fraction": changed_b,
        "ratio_a_floor": a.us_per_tag / floor.us_per_tag,
        "ratio_b_floor": b.us_per_tag / floor.us_per_tag,
        "ratio_pymodbus_a": pym.us_per_tag / a.us_per_tag,
        "ratio_pymodbus_b": pym.us_per_tag / b.us_per_tag,
        "paired_median_ratio_a_floor": statistics.median(pairs["a"]),
        "paired_median_ratio_b_floor": statistics.median(pairs["b"]),
        "paired_median_ratio_pymodbus_a": statistics.median(pairs["pym_a"]),
        "a_python_entries_per_round": min(entries),
        "a_tag_reads": sum(w.tag_reads for w in runs["a"]),
        "b_tag_reads": sum(w.tag_reads for w in runs["b"]),
        "all_us_per_tag": {k: [round(w.us_per_tag, 4) for w in v] for k, v in runs.items()},
    }
    benchmark.extra_info.update(info)
    report(
        f"client CPU per tag read: {line.n_tags} tags on 10 slaves, {n_blocks} blocks of "
        f"<= {BLOCK} registers, RTU over TCP (best of {len(runs['floor'])} / {repeats})",
        [
            ("floor: bare libmodbus (modbus_read_registers) block reads, no decoding",
             floor.us_per_tag, "us/tag"),
            ("  the same, per block read", info["floor_us_per_block"], "us/block"),
            ("our bare reader (Context.read, csrc/emb_io.c), no decoding",
             reader.us_per_tag, "us/tag"),
            ("  the same, per block read", info["reader_us_per_block"], "us/block"),
            ("our bare reader / floor", info["ratio_reader_floor"], "x"),
            ("    median of paired windows (not gated)",
             info["paired_median_ratio_reader_floor"], "x"),
            ("pymodbus 3.16.1 reads + convert_from_registers", pym.us_per_tag, "us/tag"),
            ("(a) driver, 1% of values change", a.us_per_tag, "us/tag"),
            ("    changed per tag read (valuesChanged)", 100 * changed_a, "%"),
            ("(b) driver, all values change", b.us_per_tag, "us/tag"),
            ("    changed per tag read (valuesChanged)", 100 * changed_b, "%"),
            ("(a) / floor", info["ratio_a_floor"], "x"),
            ("    median of paired windows (gated)", info["paired_median_ratio_a_floor"], "x"),
            ("(b) / floor", info["ratio_b_floor"], "x"),
            ("    median of paired windows (gated)", info["paired_median_ratio_b_floor"], "x"),
            ("(a) / our bare reader, median of paired windows (not gated)",
             info["paired_median_ratio_a_reader"], "x"),
            ("pymodbus / (a)", info["ratio_pymodbus_a"], "x"),
            ("    median of paired windows (gated)", info["paired_median_ratio_pymodbus_a"], "x"),
            ("pymodbus / (b)", info["ratio_pymodbus_b"], "x"),
            ("(a) Python entries per round of the 10 slaves (gated)",
             info["a_python_entries_per_round"], ""),
        ],
    )
    gate.record("driver.few_changes_vs_floor", info["paired_median_ratio_a_floor"])
    gate.record("driver.every_value_vs_floor", info["paired_median_ratio_b_floor"])
    gate.record("driver.pymodbus_vs_few_changes", info["paired_median_ratio_pymodbus_a"])
    gate.record("driver.entries_per_round", info["a_python_entries_per_round"])
    for key, text in profiles.items():
        print(f"\n--- cProfile of the line worker, scenario ({key}) ---\n{text}")


# -- memory ---------------------------------------------------------------------------------


def _rss() -> int:
    gc.collect()
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _start_and_read(configs: list[em.DeviceConfig], timeout: float) -> list[em.DriverModbusRtu]:
    """Start a driver per config and wait until every item has been read once."""
    drivers: list[em.DriverModbusRtu] = []
    try:
        for cfg in configs:
            drv = em.DriverModbusRtu()
            drivers.append(drv)
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        _wait(lambda: all(i.status is ItemStatus.OK for c in configs for i in c.address_list),
              timeout)
    except BaseException:
        for drv in drivers:
            drv.stop_device()
        raise
    return drivers


def _shuffled_tags(slave: int, count: int) -> list[Tag]:
    """``make_tags``' tags in an order of the slave's own (seeded), laid out again from
    register 0: devices whose address lists share no read plan and few compiled blocks
    (the gated figure's devices share both: one address list, distinct names)."""
    import random
    from dataclasses import replace

    tags = make_tags(slave, count)
    random.Random(slave).shuffle(tags)
    laid: list[Tag] = []
    offset = 0
    for t in tags:
        address = f"3:{offset}" if t.bit is None else f"3:{offset}.{t.bit}"
        laid.append(replace(t, offset=offset, config={**t.config, "address": address}))
        offset += t.registers
    return laid


def _memory_child(port: int, slaves: list[int], tags_per_slave: int, shuffled: bool = False,
                  trace: bool = False) -> dict[str, Any]:
    """In a fresh process: RSS growth for configuring, starting and reading every tag;
    ``trace``: the top allocation sites of each phase instead (tracemalloc: its own
    bookkeeping inflates the RSS, so the figures of such a run are not gated)."""
    import tracemalloc

    tags_of = _shuffled_tags if shuffled else make_tags
    # first, a small device of the same kinds of tags: imports and one-off caches
    warm = [em.load_device_config(device_dict(port, slaves[0], make_tags(slaves[0], 40)))]
    for drv in _start_and_read(warm, 30):
        drv.stop_device()
    if trace:
        tracemalloc.start()
    snaps = [tracemalloc.take_snapshot()] if trace else []
    rss0 = _rss()
    configs = [
        em.load_device_config(device_dict(port, s, tags_of(s, tags_per_slave), read_cycle=1000))
        for s in slaves
    ]
    rss1 = _rss()
    snaps += [tracemalloc.take_snapshot()] if trace else []
    drivers = _start_and_read(configs, 120)
    rss2 = _rss()
    snaps += [tracemalloc.take_snapshot()] if trace else []
    for drv in drivers:
        drv.stop_device()
    tags = len(slaves) * tags_per_slave
    out: dict[str, Any] = {"tags": tags, "config": rss1 - rss0, "running": rss2 - rss1}
    if trace:
        tracemalloc.stop()
        out["sites"] = {phase: _top_sites(snaps[k], snaps[k + 1], tags)
                        for k, phase in enumerate(("config", "running"))}
    return out


def _top_sites(before: Any, after: Any, tags: int) -> list[tuple[str, float, float]]:
    """The allocation sites that grew most between two tracemalloc snapshots: (file:line,
    bytes per tag, blocks per tag).  C allocations (libc malloc: the codec's arrays in
    cffi's ffi.new, the engine's) are not traced; RSS counts them."""
    stats = after.compare_to(before, "lineno")
    top = []
    for stat in stats[:15]:
        frame = stat.traceback[0]
        where = frame.filename.rpartition("/src/")[2] or frame.filename
        top.append((f"{where}:{frame.lineno}", stat.size_diff / tags, stat.count_diff / tags))
    return top


def _wait(cond: Callable[[], bool], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError("not every item was read in time")
        time.sleep(0.1)  # poll: until read (deadline above)


@pytest.mark.timeout(600)
def test_memory_per_tag(benchmark: Any) -> None:
    """RSS growth per tag: the gated figure (100 devices of one address list, as a
    template's devices are) and, reported only, devices of shuffled address lists."""
    n_slaves = scale(100, 10)
    slaves = list(range(1, n_slaves + 1))
    with SimulatorProcess(slaves, size=2000) as sim:
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(1, maxtasksperchild=1) as pool:  # each run in a fresh process
            m = pool.apply(_memory_child, (sim.port, slaves, TAGS_PER_SLAVE))
            apart = pool.apply(_memory_child, (sim.port, slaves, TAGS_PER_SLAVE, True))
            traced = [(label, pool.apply(_memory_child, (sim.port, slaves, TAGS_PER_SLAVE,
                                                         shuffled, True)))
                      for label, shuffled in (("one address list", False),
                                              ("shuffled address lists", True)) if PROFILE]
    tags = m["tags"]
    total = m["config"] + m["running"]
    apart_total = apart["config"] + apart["running"]
    benchmark.extra_info.update(
        tags=tags, bytes_per_tag=total / tags, config_bytes_per_tag=m["config"] / tags,
        running_bytes_per_tag=m["running"] / tags, shuffled_bytes_per_tag=apart_total / tags,
    )
    report(
        f"RSS growth per configured tag: {tags} tags on {n_slaves} slaves (fresh process)",
        [
            ("configs loaded (load_device_config)", m["config"] / tags, "B/tag"),
            ("drivers started, every item read", m["running"] / tags, "B/tag"),
            ("total (gated, in KB)", total / tags, "B/tag"),
            ("shuffled address lists: configs", apart["config"] / tags, "B/tag"),
            ("shuffled address lists: running", apart["running"] / tags, "B/tag"),
            ("shuffled address lists: total (not gated)", apart_total / tags, "B/tag"),
        ],
    )
    for label, run in traced:
        for phase, sites in run["sites"].items():
            report(f"tracemalloc, {label}, {phase}: top sites (EDGEMODBUS_BENCH_PROFILE=1)",
                   [(where, size, f"B/tag  {count:.2f} blocks/tag")
                    for where, size, count in sites])
    gate.record("memory.kb_per_tag", total / tags / 1024)
    benchmark.pedantic(lambda: None, rounds=1, iterations=1)
