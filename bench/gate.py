"""The benchmark gate: every headline ratio of a benchmark run against its target and a
gate limit, in one table, and a failed session when a ratio is past its limit.

A benchmark calls :func:`record` (``record("gil.busy_vs_quiet", 0.93)``), which looks up
the target and the limit in :data:`GATES`, the one place where they are kept, and hands
them to :func:`ratio`, the primitive (``ratio(name, value, target, limit, better)``).
bench/conftest.py prints :func:`summary` at the end of the session and fails the session
when :func:`failures` is not empty (see :class:`Recorder` for the rules).

Ratios are measured against a baseline taken in the same run (the machines are shared
and noisy), so a limit is the target plus a margin for noise: a ratio between its target
and its limit is shown as missing its target but does not fail the run.  Nothing here
does I/O: the unit tests (tests/unit/test_bench_gate.py) drive it with plain values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

Better = Literal["lower", "higher"]


def _check_sides(name: str, target: float, limit: float, better: Better) -> None:
    """A limit lies on the lenient side of its target (or on it)."""
    if better not in ("lower", "higher"):
        raise ValueError(f"{name}: better must be 'lower' or 'higher', not {better!r}")
    if (better == "lower" and limit < target) or (better == "higher" and limit > target):
        raise ValueError(f"{name}: gate limit {limit} is stricter than target {target} "
                         f"({better} is better)")


def _bound(better: Better, value: float) -> str:
    return f"{'<=' if better == 'lower' else '>='} {value:g}"


@dataclass(frozen=True)
class Gate:
    """What one recorded figure should be (``target``) and how far it may stray before the
    run fails (``limit``, on the lenient side of the target)."""

    target: float
    limit: float
    better: Better
    unit: str
    label: str

    def __post_init__(self) -> None:
        _check_sides(self.label, self.target, self.limit, self.better)


# The gates, one per headline figure (issue 13 gives the targets and suggests the limits).
GATES: dict[str, Gate] = {
    # bench/test_bench_driver.py, CPU per tag read with 1% of the values changing, over the
    # bare-libmodbus floor (median of paired windows).  Issue 13: at most the floor itself.
    # NOT MET: 1.4-1.7 with the C engine (2.06-2.5 before it, same runs); 0.97-1.53 since
    # the fault policy runs in C and a round's passes reach Python together (1.54 before,
    # 2026-11-27); what is left is the Python cost of each changed item (set it, call
    # back; docs/performance.md).  Issue 26 lowers the target to 0.8; 1.36 (quick) with
    # the table CRC and writes in one C call, 2026-11-27.  All of that against our own
    # reader (Context.read), mislabelled "bare libmodbus".  Since 2026-11-27 the floor is
    # libmodbus's modbus_read_registers (Context.read_libmodbus), as issue 26 states, and
    # our reader makes 4 system calls per reply to libmodbus's 7 (0.78-0.86 of its CPU,
    # reported beside the floor, not gated): NOT MET, 1.08-1.71 (quick), 1.24-1.25
    # (full); the rest is the driver's Python per changed block (docs/performance.md
    # "What still costs").  The limit guards against falling back to a Python step per
    # block, not the target.  With the every-item path by slices (2026-11-27, issue 26):
    # NOT MET, 1.15-1.34 (quick, six runs; 1.11-1.31 before, same runs): unchanged, as
    # a changed block holds one or two changed items here; Python is a fifth of the
    # worker, the engine's C costs 1.5x the bare reader per block (docs/performance.md
    # "The Python per changed block").  Measured on the worker's thread alone (2026-11-27)
    # the engine's C is 7% of it: the engine costs ~4.3 us a block over the bare reader's
    # ~10, of which ~1.3 Python, ~0.8 our C (the decode), ~2 kernel for the same 4
    # calls.  The decode now skips the items whose registers did not move: NOT MET,
    # 1.16-1.31, median 1.21 (quick, seven runs; 1.18-1.61, median 1.27 before, same
    # runs, alternating): within the spread (docs/performance.md "The engine's own cost
    # per block").
    "driver.few_changes_vs_floor": Gate(
        0.8, 2.0, "lower", "x", "driver CPU/tag, 1% change / bare libmodbus"),
    # The same with every value changing and reported.  Issue 13: at most 1.6x the floor.
    # NOT MET: 2.3-2.6 (3.8-3.9 before the engine); 1.8-2.8 with the faults in C (2.7-2.8
    # before, 2026-11-27); issue 26: at most 1.2 (2.33 quick, as above); against
    # libmodbus's reads since 2026-11-27 (as above): NOT MET, 1.81-2.67 (quick), 2.71-3.14
    # (full, load average 6 on the 2-core machine), the Python of every changed item; a
    # regression guard as above.  A block whose items all changed is stored by slices
    # and its Float32s made a run at a time (2026-11-27): NOT MET, 1.65-2.58 (quick, six
    # runs; 2.19-2.81 before, same runs), 0.34-0.41 us per tag against 0.43-0.50.  With
    # the decode of unmoved items skipped (2026-11-27; with every value moving the plan
    # decodes all without comparing, 3% more decode instructions): NOT MET, 1.07-2.08
    # (quick, seven runs; 1.45-2.29 before, same runs).
    "driver.every_value_vs_floor": Gate(
        1.2, 3.2, "lower", "x", "driver CPU/tag, all change / bare libmodbus"),
    # pymodbus' CPU per tag read (sync client + convert_from_registers) over ours with 1%
    # changing.  Issue 13: at least 8x cheaper than pymodbus.  The driver runs at about the
    # bare-libmodbus floor, so this ratio is pymodbus' over libmodbus' own, which depends on
    # the machine: 9-11x where a block read cost 21-32 us, 3.8-5.0x on 2026-11-23 when the
    # floor was 1.9-2.6 us/tag (6-8x the earlier figure, pymodbus' only 2x; cause not
    # found: no change of ours in that path) while the driver stayed 1.1-1.2x the floor.
    # Below 3x is a regression; our own code's is caught first by
    # driver.few_changes_vs_floor.  Issue 26: at least 10x (9.2 quick, as above); with the
    # floor libmodbus's reads and the reader at 4 system calls per reply (2026-11-27):
    # 7.2-11.4 (quick), 9.8-9.9 (full).  With the every-item path by slices
    # (2026-11-27): 5.6-10.7 (quick, six runs at load average 4-7; 5.2-10.2 before, same
    # runs): (a) did not move, the spread is pymodbus' and the floor's.  With the decode
    # of unmoved items skipped: 6.0-10.3 (quick, seven runs; 6.6-10.5 before, same runs).
    "driver.pymodbus_vs_few_changes": Gate(
        10.0, 3.0, "higher", "x", "pymodbus CPU/tag / driver, 1% change"),
    # The same bench, (a): how often the line worker came back from the engine to Python
    # per round of its 10 slaves (each pass has changes).  Issue 26: at most once per
    # round, however many devices share the line (10 before: one per device's pass; 1.8
    # with a 5 ms handover; 1.0-1.2 since passes are handed over per round).
    "driver.entries_per_round": Gate(
        1.0, 1.5, "lower", "", "Python entries per round of a line's devices, 1% change"),
    # bench/test_bench_line.py: client CPU per 125-register transaction on the line worker
    # over pymodbus' sync client.  Issue 2: at most a third; half is the noise margin.
    "line.worker_vs_pymodbus": Gate(
        0.33, 0.5, "lower", "x", "CPU per transaction / pymodbus"),
    # bench/test_bench_mqtt.py: CPU per tag read with MQTT QoS 0 publishing (mode
    # "per-item": a message per update) over MQTT off.  Issue 8: at most 1.5x.  NOT MET
    # since issue 15 took out the hand-built PUBLISH packets (1.27x) for paho's public
    # publish(): 1.1-2.0x, paho's own cost per message; mode "batch" (below) is the
    # answer for CPU.  The limit guards against a regression beyond that, not the target.
    "mqtt.qos0_on_vs_off": Gate(
        1.5, 3.0, "lower", "x", "CPU/tag read, MQTT per-item QoS 0 on / off"),
    # The same in mode "batch" (a message per device and cycle).  Issue 15: at most 1.2x
    # at QoS 0 and 1.5x at QoS 1; the limits add a third for noise, as above.  Measured
    # (median of six rounds) 1.07-1.19 and 1.16-1.47, once 1.50 and 1.30: single rounds
    # spread 0.76-1.57 on the shared VM, where the rate polled without MQTT itself varied
    # from 300,000 to 730,000 tag reads/s between runs.
    "mqtt.batch_qos0_on_vs_off": Gate(
        1.2, 1.6, "lower", "x", "CPU/tag read, MQTT batch QoS 0 on / off"),
    "mqtt.batch_qos1_on_vs_off": Gate(
        1.5, 2.0, "lower", "x", "CPU/tag read, MQTT batch QoS 1 on / off"),
    # bench/test_bench_console.py: CPU per tag read with the web console enabled and
    # idle over the console disabled (issue 29: costs the polling nothing when nobody
    # looks; 5 % allowed), the limit adds a margin for the shared machine's noise.
    "console.idle_vs_off": Gate(
        1.05, 1.15, "lower", "x", "CPU/tag read, console idle / off"),
    # bench/test_bench_driver.py: RSS growth per configured and polled tag (configs plus
    # drivers; 100,000 tags on 100 devices of one address list, as a template's devices,
    # 10,000 in quick mode).  Issue 26: at most 0.45 KB (issue 13: 0.7).  Met: 0.358 KB
    # at 100,000 tags (366-367 B, three runs), 0.385 before a device's codec plan became
    # one allocation and an item's time and reason one shared pair; 0.31 KB in quick
    # mode.  Devices of shuffled address lists (nothing shared; reported, not gated):
    # 503 B (0.49 KB; 678 before the caches' keys were packed).  Where each byte goes:
    # docs/item-store.md, "Memory".  The limit is the target plus a tenth for noise at
    # 100,000 tags.
    "memory.kb_per_tag": Gate(
        0.45, 0.55, "lower", "KB/tag", "memory per tag (config + driver)"),
    # bench/test_bench_stream.py: our CPU per tag read of a DTU fleet whose DTUs send a
    # heartbeat every second, and of one whose edge MCUs push a one-register wrapped
    # report per cycle, over the same fleet with plain RTU frames, same run (100 DTUs x
    # 100 tags, readCycle 250 ms).  Issue 26: at most 1.1x (1.83x with a heartbeat every
    # 5 s when such lines stepped in Python).  Measured with 20 DTUs
    # (EDGEMODBUS_BENCH_QUICK=1) on the 2-core VM, load average 6 / 13-300 from other jobs:
    # heartbeats 0.65-0.91 / 0.82-1.35 (0.85-1.07 before): no wake-up and no Python per
    # heartbeat, they are skipped when the next request goes out.  Wrapped 0.94-1.15 /
    # 1.23-1.85 (1.88-2.83 when each report came back to Python, EV_REPORTS/EV_INPUT, and
    # was decoded there, about 40 us a report): the engine applies reports in C
    # (csrc/emb_report.c) and such a fleet runs no Python at all.  NOT MET in substance:
    # in those runs the plain phase cost 0.53-0.66 us per tag, 0.33-0.43 measured alone,
    # and the same fleet with its reports switched on and off in one phase puts a report
    # per cycle at +0.10-0.17 us per tag (1.3-1.45x plain): a report that comes between
    # two polls still wakes its line's thread (a ppoll return and a recv).  Reading
    # reports only with the next poll would hold them up to a cycle (docs/dtu.md "What a
    # wrapped report costs").  The limit guards against the step per block coming back,
    # not the target; tests/integration/test_stream_engine.py guards the C path itself.
    # Since DTUs run on the loop by default the plain fleet is on a loop thread and the
    # wrapped one (engine "auto" keeps wrapped DTUs on a line thread, where reports are
    # applied in C) on line threads: 2.5 quick (2026-11-27); with the wrapped fleet on
    # the loop too, where each report still goes to Python, 3.44.
    "stream.heartbeat_vs_plain": Gate(
        1.1, 1.5, "lower", "x", "CPU/tag read, DTU heartbeats / plain"),
    "stream.wrapped_vs_plain": Gate(
        1.1, 3.5, "lower", "x", "CPU/tag read, wrapped + report per cycle / plain"),
    # The same bench: the frame trace at DEBUG (every frame formatted by a handler, to
    # /dev/null) over no trace, connect mode.  Issue 26: at most 1.5x.  Measured 1.38-1.62
    # (2.75 with 100 DTUs when the engine came back after every pass, before the ring was
    # drained a quarter full or a second old); about 7 us a frame is the logging module's.
    "line.trace_vs_none": Gate(
        1.5, 2.5, "lower", "x", "CPU/tag read, frame trace at DEBUG / none"),
    # bench/test_bench_dtu.py: our CPU per tag read in listen mode (DTUs dialled in) over
    # the same fleet polled in connect mode (one TCP line per DTU), same run.  Listen mode
    # should cost no more than connect mode; 1.5x is the noise margin.
    "dtu.listen_vs_connect": Gate(
        1.0, 1.5, "lower", "x", "CPU/tag read, DTU listen / connect mode"),
    # bench/test_bench_connect_scale.py: our CPU per tag read with N RTU-over-TCP
    # endpoints in connect mode on the loop engine over the same endpoints on a thread
    # each (each engine in a fresh process), same run.  Issue 27: the same per-link
    # costs, so 1.0; the limit is loose (noise of a shared 2-core machine).
    "connect.loop_vs_thread_cpu": Gate(
        1.0, 1.5, "lower", "x", "CPU/tag read, connect mode, loop / thread engine"),
    # bench/test_bench_gil.py: polling rate beside one CPU-bound Python thread over the
    # quiet rate (median of paired windows).  Issue 13: at least 0.8.  On a 2-core machine
    # the spinner, the simulator and the line worker share two cores: a spinner in a
    # process of its own (no GIL) allows 0.55-0.65 there, so the limit is 0.3 (0.08
    # before the engine) and the GIL's own share is gated below.
    "gil.busy_vs_quiet": Gate(
        0.8, 0.3, "higher", "x", "cycles/s beside a CPU-bound thread / quiet"),
    # The same beside the thread over beside a spinning process of its own (same CPU
    # demand, no GIL shared): the slowdown the GIL alone makes.  About 0.12 before the
    # engine; target 0.9, limit 0.6 (runs on a loaded machine spread +-0.3).
    "gil.thread_vs_process": Gate(
        0.9, 0.6, "higher", "x", "cycles/s beside a thread / beside a process"),
    # bench/test_bench_write_latency.py: from write_address() to the write reaching the
    # slave, in transaction times of a slow line mid-cycle (90th percentile).  Issue 13:
    # within one transaction (the one in flight); gate 2.
    "write.latency_p90_transactions": Gate(
        1.0, 2.0, "lower", "txn", "write_address -> request at slave (p90)"),
    # bench/test_bench_serial.py, a baud-paced serial line (tests/paced_relay.py) with a
    # pymodbus slave: our CPU per 125-register read over libmodbus's own receive path
    # (modbus_read_registers, a wake-up per byte) on the same line, median of paired
    # windows.  Issue 13: at most 0.3 ms where libmodbus took 5.8 ms at 9600 baud and
    # 3.2 ms at 115200, hence the targets 0.3/5.8 = 0.052 and 0.3/3.2 = 0.094.  On the
    # shared 2-core VM ours took 0.26-0.51 ms (a single wake-up from a sleep costs ~0.1 ms
    # of CPU there), libmodbus 3.7-7.7 ms at 9600 and 1.05-2.4 ms at 115200, where the
    # relay hands over about two bytes per wake-up: ratios 0.05-0.11 and 0.12-0.27 (0.38
    # once, the machine saturated).  The limits stand clear of that noise and still catch
    # the regression that matters: a reader that wakes for every byte again costs about
    # what libmodbus costs (ratio ~1).
    "serial.cpu_vs_libmodbus_9600": Gate(
        0.052, 0.3, "lower", "x", "serial 9600: CPU/read, ours / libmodbus"),
    "serial.cpu_vs_libmodbus_115200": Gate(
        0.094, 0.6, "lower", "x", "serial 115200: CPU/read, ours / libmodbus"),
    # The same bench, wire efficiency, our share: the wire's minimum for a read (request
    # and reply frames at one character time per byte, plus t3.5) over that minimum plus
    # the silence we keep before a request beyond t3.5 (lower quartile), all the master
    # decides (the slave's latency and the relay's hops are the rig's; the raw figure,
    # minimum / transaction time, is reported beside it: 99 % and 93-97 % at 9600 baud,
    # 86-96 % and 68-84 % at 115200).  Issue 13: keep 97-100 % with 125-register blocks
    # and 93-98 % with 10.  Measured 0.998-0.999 and 0.987-0.994 at 9600, 0.96-0.987 and
    # 0.86-0.95 at 115200 (our silence: t3.5 + 0.25-0.6 ms as the relay sees it, two
    # socat hops and the relay's wake-up included; the median up to +2.2 ms with the
    # machine saturated).  Limits: 0.9, and 0.85 / 0.75 for 10-register blocks; at 115200
    # that still fails a t3.5 taken from the wrong baud rate (+1.9 ms: 0.7) or a reader
    # that returns over a millisecond late.
    "serial.wire_125regs_9600": Gate(
        0.97, 0.9, "higher", "x", "serial 9600: wire efficiency (ours), 125 registers"),
    "serial.wire_10regs_9600": Gate(
        0.93, 0.85, "higher", "x", "serial 9600: wire efficiency (ours), 10 registers"),
    "serial.wire_125regs_115200": Gate(
        0.97, 0.9, "higher", "x", "serial 115200: wire efficiency (ours), 125 registers"),
    "serial.wire_10regs_115200": Gate(
        0.93, 0.75, "higher", "x", "serial 115200: wire efficiency (ours), 10 registers"),
    # bench/test_bench_forward.py: the latency forward mode adds over a direct read of the
    # same 125 registers on an idle line (median of paired differences), in transaction
    # times.  Issue 16: at most one transaction; the gate is the target itself (measured
    # well below it, see the bench's report).
    "forward.added_transactions": Gate(
        1.0, 1.0, "lower", "txn", "forward latency added over a direct read"),
    # bench/test_bench_serve.py: 10 TCP masters reading 125 registers in serve mode, the
    # gateway's server against a pymodbus TCP server with the same map (same run, medians
    # of alternating rounds).  CPU per reply: pymodbus' over ours; replies per second:
    # ours over pymodbus'.  Issue 16 sets no figure; measured on the shared 2-core VM:
    # 10.8-12.4 us against 85-112 us of CPU per reply (7.9-9.0x), 22,700-27,000 against
    # 4,200-6,200 replies/s (4.4-5.4x; ours bounded by the masters' process sharing the
    # cores).  Targets 8x and 3x; the
    # limits (4x, 1.5x) catch a reply path that returns to Python per request.
    # bench/test_bench_connections.py: 4 slaves behind one Modbus TCP endpoint answering in
    # 50 ms, the time for N cycles of each over 1 connection / over 4 (docs/links.md).
    # Target: the number of connections; 2.5 leaves room for a loaded 2-core machine.
    "connections.four_vs_one": Gate(
        4.0, 2.5, "higher", "x", "cycle rate, 4 connections / 1 (50 ms slaves)"),
    "serve.pymodbus_cpu_vs_ours": Gate(
        8.0, 4.0, "higher", "x", "serve: CPU/reply, pymodbus server / gateway"),
    "serve.rps_vs_pymodbus": Gate(
        3.0, 1.5, "higher", "x", "serve: replies/s, gateway / pymodbus server"),
    # bench/test_bench_dtu_5000.py: 5,000 DTUs x 20 tags (quick: 300) dialled in to one
    # listen port, on the loop engine (the default) in a process of its own; issue 27's
    # targets (docs/scale.md "5,000 DTUs on both engines").  Threads: at most 8 plus one
    # per serial line (none here); measured 4 (main, two loop threads, the listener).
    "dtu_fleet.loop_threads": Gate(
        8, 8, "lower", "threads", "5,000 DTUs, loop engine: threads of the process"),
    # RSS per DTU, its 20 tags, config and driver included.  NOT MET: 35.8 kB at 5,000,
    # 34.1-35.8 at 300 (2026-11-27, after slots on the per-line objects and no copy of
    # the parameters; 43.3-43.9 and 42.1-43.6 before; the thread engine 54.8 and 44-52):
    # config 5-7, started driver 17, link and values 12 (docs/scale.md "Memory per DTU"
    # says where it goes and what is left).  The limit is about the thread engine's
    # figure: a loop that costs as much memory as a thread per DTU fails.
    "dtu_fleet.loop_rss_kb_per_dtu": Gate(
        20.0, 55.0, "lower", "kB", "5,000 DTUs, loop engine: RSS per DTU (its tags included)"),
    # CPU per DTU per second (our process, all threads, 5 s cycle).  Issue 27: at most
    # the thread engine's 16.5-18 us of its issue; measured 6.6 and 9.3 at 5,000 (quiet,
    # saturated machine), 8.8-13.2 at 300 (the thread engine 7.2, 9.3 and 7.6-12.6);
    # the limit is the upper figure.
    "dtu_fleet.loop_cpu_us_per_dtu_s": Gate(
        16.5, 18.0, "lower", "us/s", "5,000 DTUs, loop engine: CPU per DTU per second"),
    # Seconds from the fleet's first dial to every value Ok, and from the reset of every
    # connection to every value Ok again through a new link (issue 27: 120 s and 60 s;
    # measured 2.6-5.8 s and 8.3-19.6 s at 5,000, quiet and saturated: a redialled DTU
    # is read at its next due time, up to one 5 s cycle after it is back).  The limits
    # are the targets.
    "dtu_fleet.loop_to_all_ok_s": Gate(
        120.0, 120.0, "lower", "s", "5,000 DTUs, loop engine: first dial to every value Ok"),
    "dtu_fleet.loop_redial_to_all_ok_s": Gate(
        60.0, 60.0, "lower", "s", "5,000 DTUs, loop engine: all reset to every value Ok again"),
    # The loop engine's CPU per DTU per second over the thread engine's, each in a fresh
    # process of the same run: 0.91 and 1.0 at 5,000, 0.69-1.27 at 300 on a loaded
    # machine; the limit leaves room for that noise.
    "dtu_fleet.loop_vs_thread_cpu": Gate(
        1.0, 1.5, "lower", "x", "5,000 DTUs: CPU per DTU, loop engine / thread engine"),
    # bench/test_bench_bulk_start.py: the gateway service's CPU per device started (a
    # folder of listen-mode DTU files of one 20-tag template, loop engine) over the CPU
    # per file of reading and decoding the same files (json.loads), same process.
    # Target: the 5,000 devices in 2 s, 0.4 ms each, over the reference's 16 us
    # per file on the development machine.  NOT MET: 43-49 measured (500 and 5,000
    # devices, load average 5-8, 2026-11-27; about 110 before the bulk start, from the
    # base's 8.9 s of CPU for 5,000); the limit is that plus the shared machine's noise
    # (53-69 were seen at load average 10-30) and catches a second validation, a
    # round trip per line or a thread per device coming back.
    "bulk.gateway_start_vs_read": Gate(
        25.0, 75.0, "lower", "x", "gateway start CPU per device / read+decode per file"),
    # bench/test_bench_fleet.py: the gateway processes' CPU per DTU per second, three
    # instances behind HAProxy (every instance with every device file, a third of the
    # DTUs each) over one lone gateway with the same DTUs, same run.  Issue 28: the fleet
    # costs what one process costs, per DTU (target 1.0).  NOT MET: 1.5-2.9 quick (300
    # DTUs, thread engine, 1 s cycle) and 2.94 full (3,000, loop engine, 6 s cycle),
    # 2026-11-27: each instance paid for every device file, held or not (an idle
    # instance with 3,000 files: 4.5-5.7% of a core, the lone gateway polling them all:
    # 5.5%).  Statuses are events now and a scrape exports only the held devices: the
    # idle instance 2.8% (5.7% before, same session); full 2.49 (13.1 / 32.7 us) against
    # 2.43 (19.7 / 47.9 us) for the code before in the same session: a third less CPU
    # per DTU for both, the ratio unchanged; quick 1.6-2.5.  The rest is the lines of
    # DTUs held elsewhere retrying their connect (line/loop.py; docs/deploy.md "What
    # the fleet costs").  The limit is not the target: 3.5
    # fails an instance that costs more than a lone gateway with the whole fleet (3.0
    # plus this machine's noise), e.g. lines of DTUs held elsewhere that poll or spin.
    "fleet.cpu_three_vs_one": Gate(
        1.0, 3.5, "lower", "x", "fleet CPU/DTU/s, 3 instances / 1 gateway"),
    # bench/test_bench_cli_startup.py: whole-process wall time over `python -c pass` in
    # the same rounds (median of interleaved rounds).  Issue 29: `import edgemodbus` at
    # most 60 ms and `edgemodbus read` at most 100 ms, over an interpreter start of about
    # 12 ms: 5x and 8.3x.  Import: 1.0-1.05 with the lazy package (about 20x when it built
    # the config models and the driver at import); the limit is the target.  Read: the
    # one-shot read (cli/oneshot.py: no pydantic, config models, driver or line worker)
    # measured 7.0-8.4x at load average 5-7 (75-181 ms; the polled read 21x in the same
    # rounds, 16-20x quiet before); the limit is that plus the shared machine's noise,
    # and catches the config models or the driver coming back onto the read path
    # (tests/unit/cli/test_oneshot.py and test_lazy_imports.py check that precisely).
    "cli.import_vs_pass": Gate(
        5.0, 5.0, "lower", "x", "python -c 'import edgemodbus' / python -c pass"),
    "cli.read_vs_pass": Gate(
        8.3, 12.0, "lower", "x", "edgemodbus read (simulator) / python -c pass"),
}


@dataclass(frozen=True)
class Ratio:
    """One recorded figure with the target and the gate limit it was recorded against."""

    name: str
    value: float
    target: float
    limit: float
    better: Better

    def _within(self, bound: float) -> bool:
        if not math.isfinite(self.value):
            return False  # a failed measurement (nan, inf) never passes
        return self.value <= bound if self.better == "lower" else self.value >= bound

    @property
    def meets_target(self) -> bool:
        return self._within(self.target)

    @property
    def past_limit(self) -> bool:
        return not self._within(self.limit)


@dataclass
class Recorder:
    """The figures of one session.  A figure past its limit fails the session; a gate of
    :data:`GATES` that no benchmark recorded is shown as missing, and fails the session
    only when every gate is required (``make bench`` and ``make bench-quick`` run every
    benchmark: a missing figure there means a benchmark was skipped or lost its record)."""

    ratios: dict[str, Ratio] = field(default_factory=dict)

    def ratio(self, name: str, value: float, target: float, limit: float,
              better: Better = "lower") -> Ratio:
        """Record ``value`` under ``name`` (once per session)."""
        _check_sides(name, target, limit, better)
        if name in self.ratios:
            raise ValueError(f"bench gate: {name!r} recorded twice")
        recorded = Ratio(name, float(value), target, limit, better)
        self.ratios[name] = recorded
        return recorded

    def record(self, name: str, value: float, gates: Mapping[str, Gate]) -> Ratio:
        """Record ``value`` against the target and limit of ``gates[name]``."""
        gate = gates.get(name)
        if gate is None:
            raise KeyError(f"bench gate: no gate named {name!r} (add it to bench/gate.py)")
        return self.ratio(name, value, gate.target, gate.limit, gate.better)

    def failures(self, gates: Mapping[str, Gate], require_all: bool) -> list[str]:
        """Why the session fails (empty: it passes)."""
        problems = [
            f"{r.name} = {r.value:.3g} is past its gate limit "
            f"({_bound(r.better, r.limit)}; target {_bound(r.better, r.target)})"
            for r in self.ratios.values() if r.past_limit
        ]
        if require_all:
            problems += [f"{name} was not recorded (benchmark skipped or failed)"
                         for name in gates if name not in self.ratios]
        return problems

    def summary(self, gates: Mapping[str, Gate], require_all: bool) -> list[str]:
        """The table: every gate and every recorded figure, then the verdict."""
        names = [*gates, *(n for n in self.ratios if n not in gates)]
        rows = [("figure", "value", "target", "gate", "unit", "")]
        for name in names:
            r = self.ratios.get(name)
            gate = gates.get(name)
            unit = gate.unit if gate is not None else ""
            if r is None:
                assert gate is not None
                rows.append((name, "-", _bound(gate.better, gate.target),
                             _bound(gate.better, gate.limit), unit, "MISSING (not recorded)"))
                continue
            status = ("ok" if r.meets_target
                      else "FAIL: past the gate" if r.past_limit
                      else "misses target (within gate)")
            rows.append((name, f"{r.value:.3g}", _bound(r.better, r.target),
                         _bound(r.better, r.limit), unit, status))
        widths = [max(len(row[i]) for row in rows) for i in range(5)]
        lines = [
            f"{row[0]:<{widths[0]}}  {row[1]:>{widths[1]}}  {row[2]:>{widths[2]}}  "
            f"{row[3]:>{widths[3]}}  {row[4]:<{widths[4]}}  {row[5]}".rstrip()
            for row in rows
        ]
        labels = [f"  {name}: {gates[name].label}" for name in names if name in gates]
        problems = self.failures(gates, require_all)
        verdict = (["bench gate: FAILED"] + [f"  {p}" for p in problems] if problems
                   else ["bench gate: passed"])
        return [*lines, "", *labels, "", *verdict]


RECORDER = Recorder()
"""The session's figures (benchmarks run in the pytest process)."""


def ratio(name: str, value: float, target: float, limit: float,
          better: Better = "lower") -> Ratio:
    """Record a figure with an explicit target and limit (prefer :func:`record`)."""
    return RECORDER.ratio(name, value, target, limit, better)


def record(name: str, value: float) -> Ratio:
    """Record a figure against its gate in :data:`GATES`."""
    return RECORDER.record(name, value, GATES)
