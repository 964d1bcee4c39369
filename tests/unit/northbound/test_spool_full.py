"""Store-and-forward when the spool refuses writes (store_forward.py): a 2 MB tmpfs filled
by another file.  What the spool should have kept waits in a bounded memory queue (the
oldest beyond it dropped and counted), is replayed in order when the broker is back,
live data flows, errors are logged a few lines per interval, and once the disk has room
again the queue goes to the spool after the backoff."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from edgemodbus.northbound.mqtt.sender import Sender
from tests.tmpfs import fill
from tests.unit.northbound.test_spool_file import full_disk
from tests.unit.test_mqtt_sender import Client, items, make

__all__ = ["full_disk"]  # the fixture, used by name


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def numbered(n: int) -> list:  # type: ignore[type-arg]
    """One item whose value is ``n``."""
    made = items(1)
    made[0].value = n
    return made


def sent_values(client: Client) -> list[int]:
    return [json.loads(p)["values"]["t0"] for t, p, _, _ in client.sent
            if t.endswith("$batch")]


def test_an_outage_on_a_full_disk_loses_only_what_exceeds_the_memory_bound(
        full_disk: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Before: every message of the outage was lost (SpoolError logged per turn), and
    nothing reached the broker when it came back."""
    sender: Sender
    sender, outbox, dev = make("batch", qos=1, storeAndForward={
        "path": str(full_disk / "spool.db"), "memoryQueueSize": 50, "replayRatePerS": 1000})
    sender.open_spool()
    forwarder = sender.forwarder
    assert forwarder is not None
    clock = forwarder.clock = forwarder.limiter._clock = Clock()  # type: ignore[method-assign]
    caplog.set_level(logging.WARNING, "edgemodbus.mqtt")
    try:
        fill(full_disk)
        sender._connected.clear()
        outbox.set_outage(True)
        for n in range(80):  # 80 reports of an outage, one turn each
            outbox.offer_items(dev, numbered(n))
            sender.spool_outage()
            clock.t += 0.05
        stats = forwarder.stats()
        # the spool keeps what fits in the space it has, the rest waits in memory (its
        # oldest dropped beyond 50): everything accounted for
        kept = stats["memory"] + stats["stored"]
        assert kept + stats["memoryDropped"] == 80 and stats["droppedSize"] == 0, stats
        assert stats["memory"] == 50, stats
        assert outbox.counts["dropped"] == 0
        errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert 1 <= len(errors) <= 8, [r.getMessage() for r in errors]  # 3 per kind
        sender._connected.set()  # the broker is back (the disk still full)
        outbox.set_outage(False)
        client = Client()
        for _ in range(3):
            sender.pump(client)  # type: ignore[arg-type]
        got = sent_values(client)
        assert got == sorted(got) and got[-1] == 79 and len(got) == kept, got
        outbox.offer_items(dev, numbered(80))  # live: at once, behind nothing
        sender.pump(client)  # type: ignore[arg-type]
        assert sent_values(client)[-1] == 80 and forwarder.stats()["memory"] == 0
        (full_disk / "filler").unlink()  # room again: after the backoff, spooled again
        clock.t += 60
        outbox.offer_items(dev, numbered(81))
        sender.pump(client)  # type: ignore[arg-type]
        assert sent_values(client)[-1] == 81
        assert forwarder.retry_at == 0.0 and forwarder.stats()["inflight"] == 1
        for info in client.infos:
            info.done = True
        sender.pump(client)  # type: ignore[arg-type]
        assert forwarder.stats()["stored"] == 0  # the acknowledgement applied
    finally:
        sender.close_spool()
        outbox.close()


def test_memory_waits_behind_the_spool_and_goes_to_it_when_it_takes_writes_again(
        full_disk: Path) -> None:
    sender, outbox, dev = make("batch", qos=1, storeAndForward={
        "path": str(full_disk / "spool.db"), "memoryQueueSize": 1000})
    sender.open_spool()
    forwarder = sender.forwarder
    assert forwarder is not None
    clock = forwarder.clock = Clock()  # type: ignore[method-assign]
    try:
        sender._connected.clear()
        outbox.offer_items(dev, numbered(0))
        sender.spool_outage()  # spooled
        fill(full_disk)
        for n in range(1, 40):
            outbox.offer_items(dev, numbered(n))
            sender.spool_outage()
        assert forwarder.stats()["memory"] > 0
        (full_disk / "filler").unlink()
        clock.t += 60
        outbox.offer_items(dev, numbered(40))
        sender.spool_outage()  # the retry: memory into the spool, then this one
        stats = forwarder.stats()
        assert stats["memory"] == 0 and stats["stored"] == 41, stats
        sender._connected.set()
        client = Client()
        for _ in range(5):
            sender.pump(client)  # type: ignore[arg-type]
            clock.t += 1
        assert sent_values(client) == list(range(41))  # one order: spool, then memory
    finally:
        sender.close_spool()
        outbox.close()


def test_a_spool_that_cannot_be_created_on_a_full_disk_is_opened_later(
        full_disk: Path) -> None:
    """Before: SpoolError at start (ConfigError: the gateway exited 2, a restart loop
    under systemd).  Now the messages wait in memory until the disk has room."""
    fill(full_disk)
    sender, outbox, dev = make("batch", qos=1, storeAndForward={
        "path": str(full_disk / "spool.db")})
    sender.open_spool()  # no ConfigError
    forwarder = sender.forwarder
    assert forwarder is not None
    clock = forwarder.clock = Clock()  # type: ignore[method-assign]
    try:
        sender._connected.clear()
        for n in range(5):
            outbox.offer_items(dev, numbered(n))
            sender.spool_outage()
        assert forwarder.stats()["memory"] == 5
        (full_disk / "filler").unlink()
        clock.t = forwarder.retry_at + 60  # (set on the real clock, at open)
        outbox.offer_items(dev, numbered(5))
        sender.spool_outage()
        stats = forwarder.stats()
        assert stats["memory"] == 0 and stats["stored"] == 6, stats
        sender._connected.set()
        client = Client()
        sender.pump(client)  # type: ignore[arg-type]
        assert sent_values(client) == list(range(6))
    finally:
        sender.close_spool()
        outbox.close()


def test_the_retries_back_off_doubling_to_30_s(full_disk: Path) -> None:
    fill(full_disk)
    sender, outbox, dev = make("batch", qos=1, storeAndForward={
        "path": str(full_disk / "spool.db")})
    sender.open_spool()
    forwarder = sender.forwarder
    assert forwarder is not None and forwarder.failing
    clock = forwarder.clock = Clock()  # type: ignore[method-assign]
    try:
        sender._connected.clear()
        clock.t = forwarder.retry_at
        waits = []
        for n in range(8):
            outbox.offer_items(dev, numbered(n))
            sender.spool_outage()  # due: one more try, failed
            waits.append(forwarder.retry_at - clock.t)
            outbox.offer_items(dev, numbered(n))
            sender.spool_outage()  # not due: no try, straight to memory
            assert forwarder.retry_at - clock.t == waits[-1]
            clock.t = forwarder.retry_at
        assert waits == [2, 4, 8, 16, 30, 30, 30, 30]
        assert forwarder.stats()["memory"] == 16
    finally:
        sender.close_spool()
        outbox.close()
