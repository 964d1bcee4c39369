"""The spool on its own (no broker): order, claims and acks, the bounds, reopening, threads,
a second user of the file, and what it refuses."""

from __future__ import annotations

import logging
import sqlite3
import threading
from pathlib import Path

import pytest

from edgemodbus.northbound.mqtt.spool import (
    ROW_OVERHEAD,
    Message,
    Spool,
    SpoolError,
    message_size,
)


class Clock:
    def __init__(self, t: float = 1_700_000_000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def msg(n: int, device: str = "d", size: int = 8) -> Message:
    return Message(device, f"t/{device}", str(n).encode().rjust(size, b"0"), 1, n % 2 == 0)


def numbers(spool: Spool) -> list[int]:
    """Every pending message's number, claimed and released again (state unchanged)."""
    got = spool.next_batch(1_000_000)
    spool.release(m.id for m in got)
    return [int(m.payload) for m in got]


@pytest.fixture
def path(tmp_path: Path) -> Path:
    return tmp_path / "spool.db"


def test_order_claims_acks_release(path: Path) -> None:
    with Spool(path, max_bytes=1 << 20, max_age_s=3600) as spool:
        ids = spool.append([msg(n, f"d{n % 3}") for n in range(10)])
        assert ids == sorted(ids) and len(set(ids)) == 10
        first = spool.next_batch(4)
        assert [int(m.payload) for m in first] == [0, 1, 2, 3]
        assert [m.device for m in first] == ["d0", "d1", "d2", "d0"]
        assert first[0].qos == 1 and first[0].retain is True and first[1].retain is False
        assert spool.stats()["inflight"] == 4 and spool.pending_count() == 6
        assert [int(m.payload) for m in spool.next_batch(3)] == [4, 5, 6]  # not 0..3 again
        assert spool.ack([first[0].id, first[2].id]) == 2
        assert spool.ack([first[0].id]) == 0  # acked already: ignored
        spool.release([first[1].id, first[3].id])  # paho refused them: back, oldest first
        assert [int(m.payload) for m in spool.next_batch(3)] == [1, 3, 7]
        live = spool.append([msg(10), msg(11)], claimed=True)  # live QoS 1: in flight
        assert [int(m.payload) for m in spool.next_batch(10)] == [8, 9]
        assert spool.next_batch(10) == []
        spool.release_all()  # a new client: everything in flight is sent again
        assert numbers(spool) == [1, 3, 4, 5, 6, 7, 8, 9, 10, 11]
        assert spool.ack(live) == 2
        stats = spool.stats()
        assert stats["appended"] == 12 and stats["acked"] == 4
        assert stats["stored"] == stats["pending"] == 8 and stats["inflight"] == 0


def test_reopen_after_close_replays_everything_stored(path: Path) -> None:
    spool = Spool(path, max_bytes=1 << 20, max_age_s=3600)
    ids = spool.append([msg(n) for n in range(6)])
    spool.next_batch(3)  # in flight when the process ends: replayed next time
    spool.ack(ids[:1])
    size = spool.size_bytes()
    spool.close()
    spool.close()  # idempotent
    with pytest.raises(SpoolError, match="closed"):
        spool.append([msg(9)])
    with Spool(path, max_bytes=1 << 20, max_age_s=3600) as again:
        assert again.pending_count() == 5 and again.size_bytes() == size
        assert numbers(again) == [1, 2, 3, 4, 5]
        newer = again.append([msg(6)])
        assert newer[0] > ids[-1]
    # emptied and closed: ids still grow (AUTOINCREMENT: an old PUBACK never hits a new row)
    with Spool(path, max_bytes=1 << 20, max_age_s=3600) as again:
        again.ack(m.id for m in again.next_batch(100))
        assert again.pending_count() == 0 and again.size_bytes() == 0
    with Spool(path, max_bytes=1 << 20, max_age_s=3600) as again:
        assert again.append([msg(7)])[0] > newer[0]


def test_size_bound_drops_the_oldest_counted_and_logged(
        path: Path, caplog: pytest.LogCaptureFixture) -> None:
    one = message_size("t/d", b"0" * 8)
    assert one == 3 + 8 + ROW_OVERHEAD
    caplog.set_level(logging.WARNING, "edgemodbus.mqtt.spool")
    with Spool(path, max_bytes=10 * one, max_age_s=3600) as spool:
        spool.append([msg(n) for n in range(8)])
        claimed = spool.next_batch(2)
        spool.append([msg(n) for n in range(8, 13)])  # 13 > 10: 0, 1, 2 go
        assert numbers(spool) == list(range(3, 13))
        assert spool.size_bytes() == 10 * one
        assert spool.ack(m.id for m in claimed) == 0  # dropped while in flight: nothing
        assert spool.stats()["droppedSize"] == 3
        # a batch larger than the bound keeps its newest messages only
        assert len(spool.append([msg(n) for n in range(100, 115)])) == 10
        assert numbers(spool) == list(range(105, 115))
        assert spool.stats()["droppedSize"] == 3 + 10 + 5
        # a message larger than the bound on its own: dropped, nothing else lost
        assert spool.append([Message("d", "t/d", b"x" * 11 * one, 0, False)]) == []
        assert numbers(spool) == list(range(105, 115))
        assert spool.stats()["droppedSize"] == 19
    dropped = [r for r in caplog.records if "dropped" in r.getMessage()]
    assert dropped and "maxBytes" in dropped[0].getMessage()
    assert len(dropped) <= 2  # rate-limited: one line, then the summary at close


def test_age_bound_drops_the_oldest(path: Path) -> None:
    clock = Clock()
    with Spool(path, max_bytes=1 << 20, max_age_s=60, clock=clock) as spool:
        spool.append([msg(0), msg(1)])
        clock.t += 30
        spool.append([msg(2)])
        clock.t += 31  # 0 and 1 are 61 s old, 2 is 31 s
        assert [int(m.payload) for m in spool.next_batch(1)] == [2]
        assert spool.stats()["droppedAge"] == 2 and spool.stats()["stored"] == 1
        clock.t += 60
        spool.append([msg(3)])  # appending expires too: 2 goes, also while in flight
        assert numbers(spool) == [3]
        assert spool.stats()["droppedAge"] == 3
        t3 = clock.t
        clock.t -= 3600  # the wall clock set back: nothing newer goes before older
        spool.append([msg(4)])
        clock.t += 61  # 4 looks 61 s old, but 3 (older) is young: both stay
        assert numbers(spool) == [3, 4] and spool.stats()["droppedAge"] == 3
        clock.t = t3 + 61
        assert spool.next_batch(5) == [] and spool.stats()["droppedAge"] == 5


def test_concurrent_appends_from_threads_keep_each_threads_order(path: Path) -> None:
    with Spool(path, max_bytes=1 << 30, max_age_s=3600) as spool:
        def produce(device: str) -> None:
            for start in range(0, 400, 20):
                spool.append([msg(n, device) for n in range(start, start + 20)])

        threads = [threading.Thread(target=produce, args=(f"d{i}",)) for i in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        got = spool.next_batch(10_000)
        assert len(got) == 1600 and len({m.id for m in got}) == 1600
        for device in ("d0", "d1", "d2", "d3"):
            assert [int(m.payload) for m in got if m.device == device] == list(range(400))
        assert spool.stats()["appended"] == 1600


def test_a_second_user_of_the_file_is_refused(path: Path) -> None:
    with Spool(path, max_bytes=1 << 20, max_age_s=3600) as spool:
        spool.append([msg(1)])
        with pytest.raises(SpoolError, match="in use by another"):
            Spool(path, max_bytes=1 << 20, max_age_s=3600)
    with Spool(path, max_bytes=1 << 20, max_age_s=3600) as again:  # free after close
        assert numbers(again) == [1]


def test_refusals_name_the_path(tmp_path: Path) -> None:
    with pytest.raises(SpoolError, match=r"nowhere.*does not exist"):
        Spool(tmp_path / "nowhere" / "s.db", max_bytes=1, max_age_s=1)
    with pytest.raises(SpoolError, match="is a directory"):
        Spool(tmp_path, max_bytes=1, max_age_s=1)
    other = tmp_path / "other.db"
    db = sqlite3.connect(other)
    db.execute("PRAGMA user_version=7")
    db.close()
    with pytest.raises(SpoolError, match=r"other\.db.*schema version 7"):
        Spool(other, max_bytes=1, max_age_s=1)
    for max_bytes, max_age_s in ((0, 1), (1, -1)):
        with pytest.raises(ValueError, match="must be > 0"):
            Spool(tmp_path / "s.db", max_bytes=max_bytes, max_age_s=max_age_s)
    with pytest.raises(ValueError, match="synchronous 'off'"):
        Spool(tmp_path / "s.db", max_bytes=1, max_age_s=1, synchronous="off")


def test_a_failed_transaction_changes_nothing(path: Path) -> None:
    """A failure inside the transaction (here: a value SQLite cannot store, after the size
    bound already dropped the oldest rows) rolls the file back, and the counters and
    claims with it."""
    one = message_size("t/d", b"0" * 8)
    with Spool(path, max_bytes=4 * one, max_age_s=3600) as spool:
        spool.append([msg(n) for n in range(4)])
        claimed = spool.next_batch(2)
        before = spool.stats()
        unstorable = Message(object(), "t/d", b"0" * 8, 0, False)  # type: ignore[arg-type]
        with pytest.raises(SpoolError, match=r"spool\.db"):
            spool.append([msg(4), unstorable])
        assert spool.stats() == before
        assert spool.ack(m.id for m in claimed) == 2  # still claimed, still there
        assert numbers(spool) == [2, 3]
