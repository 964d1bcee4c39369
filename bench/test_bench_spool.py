"""What the store-and-forward spool costs: 10,000 tags with 1% changing per
cycle, i.e. 100 messages a cycle, each kept in SQLite and deleted when acknowledged.

Live QoS 1 path: per cycle one ``append(100 messages, claimed=True)`` and one
``ack(100 ids)`` (two commits), against the same bookkeeping in memory (a dict of
claimed messages: what the sender keeps anyway); in batch mode the same changes are 10
messages (one per device).  Outage path: 10 simulated minutes of
cycles appended (60,000 messages), then replayed in batches of 500 (``next_batch`` +
``ack``) until empty.  CPU seconds of this process (SQLite writes through the page
cache; ``synchronous: "full"`` adds an fsync per commit, shown beside it).

Reported, not gated: the ratio to an in-memory dict is large and noisy by nature (a dict
costs next to nothing); what matters is the cost per message in absolute terms, beside
the few microseconds paho's publish() costs a message.
"""

from __future__ import annotations

import itertools
from pathlib import Path

from bench.conftest import cpu_seconds, report, scale
from edgemodbus.northbound.mqtt.spool import Message, Spool

PER_CYCLE = 100  # 1% of 10,000 tags
PAYLOAD = b'{"value":12345,"status":"Ok","updateTs":1700000000000,"errorReason":null}'


def cycle_messages(cycle: int) -> list[Message]:
    return [Message(f"dev{i % 10}", f"edgemodbus/dev{i % 10}/tag{(cycle + i * 100) % 10000}",
                    PAYLOAD, 1, False) for i in range(PER_CYCLE)]


def batched_messages(cycle: int) -> list[Message]:
    """Batch mode: one message per device and cycle holding its 10 changes."""
    body = b'{"ts":1700000000000,"values":{' + b",".join(
        b'"tag%d":%d' % (n, cycle) for n in range(10)) + b'},"status":{}}'
    return [Message(f"dev{d}", f"edgemodbus/dev{d}", body, 1, False) for d in range(10)]


def live_on_disk(path: Path, cycles: int, synchronous: str, batched: bool = False) -> float:
    """CPU seconds per cycle."""
    make = batched_messages if batched else cycle_messages
    batches = [make(c) for c in range(cycles)]
    with Spool(path, max_bytes=1 << 30, max_age_s=86_400, synchronous=synchronous) as spool:
        start = cpu_seconds()
        for batch in batches:
            ids = spool.append(batch, claimed=True)
            spool.ack(ids)
        return (cpu_seconds() - start) / cycles


def live_in_memory(cycles: int) -> float:
    """CPU seconds per cycle."""
    batches = [cycle_messages(c) for c in range(cycles)]
    counter = itertools.count(1)
    inflight: dict[int, Message] = {}
    start = cpu_seconds()
    for batch in batches:
        ids = [next(counter) for _ in batch]
        inflight.update(zip(ids, batch, strict=True))
        for i in ids:
            del inflight[i]
    return (cpu_seconds() - start) / cycles


def outage_and_replay(path: Path, cycles: int) -> tuple[float, float]:
    batches = [cycle_messages(c) for c in range(cycles)]
    with Spool(path, max_bytes=1 << 30, max_age_s=86_400) as spool:
        start = cpu_seconds()
        for batch in batches:
            spool.append(batch)
        appended = cpu_seconds()
        replayed = 0
        while claimed := spool.next_batch(500):
            replayed += spool.ack(m.id for m in claimed)
        done = cpu_seconds()
        assert replayed == cycles * PER_CYCLE and spool.pending_count() == 0
    n = cycles * PER_CYCLE
    return (appended - start) / n, (done - appended) / n


def test_spool_cost_per_message(tmp_path: Path) -> None:
    cycles = scale(600, 100)
    memory = min(live_in_memory(cycles) for _ in range(3))
    normal = min(live_on_disk(tmp_path / f"n{r}.db", cycles, "normal") for r in range(3))
    full = live_on_disk(tmp_path / "full.db", scale(100, 20), "full")
    batched = min(live_on_disk(tmp_path / f"b{r}.db", cycles, "normal", batched=True)
                  for r in range(3))
    outage, replay = outage_and_replay(tmp_path / "outage.db", cycles)
    us = 1e6
    report(f"spool CPU, 10,000 tags, {PER_CYCLE} changes a cycle ({cycles} cycles)", [
        ("per item, QoS 1 in flight in memory (dict)", memory * us, "us/cycle"),
        ("per item, spool append+ack (normal)", normal * us, "us/cycle"),
        ("per item, spool append+ack (full)", full * us, "us/cycle"),
        ("batch mode (10 msgs), spool append+ack", batched * us, "us/cycle"),
        ("ratio per item normal / in memory", normal / memory, "x"),
        ("per item, spool per message (normal)", normal / PER_CYCLE * us, "us/msg"),
        ("outage: append, not claimed", outage * us, "us/msg"),
        ("replay: next_batch(500) + ack", replay * us, "us/msg"),
        ("replay capacity", 1 / replay, "msgs/s of CPU"),
    ])
    assert normal > 0 and replay > 0
