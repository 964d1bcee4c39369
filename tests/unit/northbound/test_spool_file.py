"""The spool's file (spool/file.py): its size stays within maxBytes (the database and its
WAL, measured on disk), a damaged file is moved aside and a new spool started, someone
else's database is refused untouched, a FIFO or a device is a field error; on a full
disk (a 2 MB tmpfs) appends fail cleanly and acknowledgements still succeed."""

from __future__ import annotations

import os
import random
import sqlite3
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.northbound.mqtt.spool import (
    MIN_FILE_BYTES,
    Message,
    Spool,
    SpoolError,
    file_bound,
    path_problem,
)
from tests.tmpfs import fill, small_tmpfs


def msg(n: int, size: int = 100) -> Message:
    return Message(f"d{n % 3}", f"t/d{n % 3}", str(n).encode().rjust(size, b"0"), 1, False)


def disk_bytes(path: Path) -> int:
    """The spool's files as the kernel sees them (independent of the spool's own
    measure): the database, its -wal and -shm."""
    return sum(os.stat(p).st_size for p in (path, Path(f"{path}-wal"), Path(f"{path}-shm"))
               if p.exists())


@pytest.mark.parametrize("max_bytes", [MIN_FILE_BYTES, 256_000, 1_000_000])
def test_the_file_stays_within_max_bytes_while_rows_come_and_go(
        tmp_path: Path, max_bytes: int) -> None:
    """Before: the WAL alone grew to about 4 MB (1000 pages before a checkpoint) for a
    spool bounded at 256 kB, and deleted rows never gave their pages back."""
    path = tmp_path / "spool.db"
    rng = random.Random(max_bytes)
    largest = 0
    with Spool(path, max_bytes=max_bytes, max_age_s=1e9) as spool:
        n = 0
        for step in range(600):
            size = rng.choice([10, 100, 1000, 3000])
            spool.append([msg(n + k, size) for k in range(rng.randint(1, 40))])
            n += 40
            if step % 7 == 0:  # the broker acknowledges some, oldest first
                spool.ack(m.id for m in spool.next_batch(rng.randint(1, 60)))
            largest = max(largest, disk_bytes(path))
            assert spool.file_bytes() == disk_bytes(path)
        stats = spool.stats()
        assert stats["droppedSize"] > 0  # the bound was reached
        assert stats["fileBytes"] <= max_bytes
    assert largest <= max_bytes, (largest, max_bytes)


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 50_000_000), st.sampled_from([1024, 2048, 4096]))
def test_the_split_of_the_bound_fits_in_it(max_bytes: int, page_size: int) -> None:
    bound = file_bound(max_bytes, page_size)
    assert bound.limit == max(max_bytes, MIN_FILE_BYTES)
    assert bound.max_pages * page_size + bound.wal_bytes <= bound.limit
    assert bound.wal_pages >= 4 and bound.max_pages >= 8


def test_a_larger_file_from_before_is_shrunk_to_the_new_bound(tmp_path: Path) -> None:
    path = tmp_path / "spool.db"
    with Spool(path, max_bytes=4_000_000, max_age_s=1e9) as spool:
        spool.append([msg(n, 1000) for n in range(3000)])
        before = spool.stats()["stored"]
    assert disk_bytes(path) > 2_000_000
    with Spool(path, max_bytes=200_000, max_age_s=1e9) as spool:
        assert disk_bytes(path) <= 200_000
        kept = spool.next_batch(10_000)
        assert kept and kept[-1].payload == msg(2999, 1000).payload  # the newest kept
        assert spool.stats()["droppedSize"] == before - len(kept)


def make_spool(path: Path, n: int = 200) -> None:
    with Spool(path, max_bytes=10_000_000, max_age_s=1e9) as spool:
        spool.append([msg(k, 500) for k in range(n)])


@pytest.mark.parametrize("damage", ["garbage", "truncated", "header", "pages"])
def test_a_damaged_spool_is_moved_aside_and_a_new_one_started(
        tmp_path: Path, damage: str, caplog: pytest.LogCaptureFixture) -> None:
    """Before: SpoolError at open, so the gateway exited 2 (no polling, no server)."""
    path = tmp_path / "spool.db"
    make_spool(path)
    data = path.read_bytes()
    if damage == "garbage":
        path.write_bytes(random.Random(1).randbytes(len(data)))
    elif damage == "truncated":
        path.write_bytes(data[: len(data) // 3])
    elif damage == "header":
        path.write_bytes(data[:50])
    else:  # the b-tree pages overwritten, the header intact
        path.write_bytes(data[:4096] + b"\xff" * (len(data) - 4096))
    damaged = path.read_bytes()
    with Spool(path, max_bytes=1_000_000, max_age_s=1e9) as spool:
        assert spool.moved_aside is not None
        aside = Path(spool.moved_aside)
        assert aside.name.startswith("spool.db.corrupt-")
        assert aside.read_bytes() == damaged  # nothing destroyed
        assert spool.stats()["stored"] == 0
        assert spool.append([msg(1)]) == [1]  # a working spool
    assert any("moved aside" in r.getMessage() and str(aside) in r.getMessage()
               for r in caplog.records if r.levelname == "ERROR")


def test_an_empty_file_is_a_new_spool(tmp_path: Path) -> None:
    path = tmp_path / "spool.db"
    path.write_bytes(b"")
    with Spool(path, max_bytes=1_000_000, max_age_s=1e9) as spool:
        assert spool.moved_aside is None and spool.append([msg(1)]) == [1]


def test_someone_elses_database_is_refused_and_left_untouched(tmp_path: Path) -> None:
    """A valid SQLite database that is not a spool (the path points at another
    program's file) must not be renamed from under its owner: refused, naming it."""
    path = tmp_path / "app.db"
    db = sqlite3.connect(path)
    db.execute("CREATE TABLE users (name TEXT)")
    db.execute("INSERT INTO users VALUES ('ada')")
    db.commit()
    db.close()
    before = path.read_bytes()
    with pytest.raises(SpoolError, match=r"app\.db.*not a spool file.*users"):
        Spool(path, max_bytes=1_000_000, max_age_s=1e9)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["app.db"]


def test_a_fifo_or_a_device_is_refused_without_opening_it(tmp_path: Path) -> None:
    """Before: a FIFO raised sqlite3's OperationalError "disk I/O error" (a traceback),
    a device a SpoolError saying the same.  Now path_problem says what it is."""
    fifo = tmp_path / "spool.db"
    os.mkfifo(fifo)
    assert "is a FIFO, not a regular file" in (path_problem(fifo) or "")
    with pytest.raises(SpoolError, match=r"spool\.db.*is a FIFO"):
        Spool(fifo, max_bytes=1_000_000, max_age_s=1e9)
    assert "is a character device" in (path_problem("/dev/null") or "")


@pytest.fixture
def full_disk(tmp_path: Path) -> Iterator[Path]:
    """A 2 MB tmpfs (skipped where mounting is not permitted), unmounted after."""
    with small_tmpfs(tmp_path) as mount:
        yield mount


def test_a_spool_larger_than_its_disk_keeps_room_for_acks(full_disk: Path) -> None:
    """maxBytes 100 MB on a 2 MB tmpfs.  Before: the WAL took the whole disk, every
    write failed, acks too, so the spool never shrank.  Now the database stops growing
    while its disk still has room for a WAL and a checkpoint: appends are refused
    (SpoolError: the sender keeps them in memory), acknowledgements shrink it, and
    appends go on in the room they freed."""
    path = full_disk / "spool.db"
    with Spool(path, max_bytes=100_000_000, max_age_s=1e9) as spool:
        with pytest.raises(SpoolError, match=r"spool\.db.*full: its disk"):
            for n in range(0, 20_000, 20):
                spool.append([msg(n + k, 200) for k in range(20)])
        stats = spool.stats()
        assert stats["droppedSize"] == 0 and stats["stored"] > 2000, stats
        assert disk_bytes(path) <= 2 * 1024 * 1024
        batch = spool.next_batch(1000)
        assert spool.ack(m.id for m in batch) == 1000
        assert spool.stats()["stored"] == stats["stored"] - 1000
        assert len(spool.append([msg(k, 200) for k in range(500)])) == 500


def test_a_disk_filled_by_someone_else_refuses_appends_with_a_spool_error(
        full_disk: Path) -> None:
    path = full_disk / "spool.db"
    with Spool(path, max_bytes=100_000_000, max_age_s=1e9) as spool:
        spool.append([msg(n, 200) for n in range(50)])
        fill(full_disk)
        with pytest.raises(SpoolError, match=r"spool\.db.*full"):
            for n in range(200):
                spool.append([msg(n, 3000) for n in range(20)])
        (full_disk / "filler").unlink()
        assert len(spool.append([msg(1)])) == 1  # works again once there is room


def test_a_read_only_file_system_is_named_as_such(full_disk: Path) -> None:
    """Before: "its directory ... is not writable by this process (uid 0)", which
    sends a root operator looking for permissions."""
    path = full_disk / "spool.db"
    make_spool(path, 3)
    subprocess.run(["mount", "-o", "remount,ro", str(full_disk)], check=True)
    try:
        assert "is on a read-only file system" in (path_problem(path) or "")
        with pytest.raises(SpoolError, match="read-only file system"):
            Spool(path, max_bytes=1_000_000, max_age_s=1e9)
    finally:
        subprocess.run(["mount", "-o", "remount,rw", str(full_disk)], check=True)
