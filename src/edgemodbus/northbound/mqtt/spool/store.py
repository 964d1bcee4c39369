"""The spool's SQLite file: messages kept in order until the broker acknowledged them.

One table, one row per message, ``id`` an AUTOINCREMENT rowid (ids grow and are never
reused, even after every row was deleted, so a late PUBACK can never delete a newer
message that got an old id).  The ``size`` column is what a row counts against
``maxBytes``: topic and payload bytes plus :data:`ROW_OVERHEAD`.  The package docstring
(``spool/__init__.py``) says when the sender appends, claims, acks and releases.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import NamedTuple

from ....line.log_limit import LogLimiter

log = logging.getLogger("edgemodbus.mqtt.spool")

SCHEMA_VERSION = 1
ROW_OVERHEAD = 32
"""Bytes a row counts beyond its topic and payload (id, device, qos, retain, time, and
SQLite's own per-row cost, roughly), so that many empty payloads still fill the bound."""

SYNCHRONOUS = ("normal", "full")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS messages (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    device TEXT NOT NULL,
    topic TEXT NOT NULL,
    payload BLOB NOT NULL,
    qos INTEGER NOT NULL,
    retain INTEGER NOT NULL,
    ts REAL NOT NULL,
    size INTEGER NOT NULL
)"""
_COLUMNS = "id, device, topic, payload, qos, retain, ts"
_TOTALS = ("SELECT COUNT(*), COALESCE(SUM(size), 0), "
           "(SELECT ts FROM messages ORDER BY id LIMIT 1) FROM messages")
_SCAN = 512  # rows read per step when looking for the oldest rows to drop or send
_PARAMS = 500  # ids per DELETE ... IN (...) statement (SQLite allows 32766)


class Message(NamedTuple):
    """One message to keep: the device it belongs to (its per-device order is kept), and
    what the sender hands paho."""

    device: str
    topic: str
    payload: bytes
    qos: int
    retain: bool


class Stored(NamedTuple):
    """A message read back from the spool: its id (what :meth:`Spool.ack` takes) and the
    wall-clock time it was appended (Unix seconds)."""

    id: int
    device: str
    topic: str
    payload: bytes
    qos: int
    retain: bool
    ts: float


class SpoolError(RuntimeError):
    """The spool file cannot be used (missing folder, not a spool, used by another
    process, closed); the message names the path."""


def path_problem(path: str | os.PathLike[str]) -> str | None:
    """Why a spool cannot be kept at ``path``, or None: its folder must exist and be
    writable by this process, and the path must not be a folder."""
    target = Path(path)
    folder = target.parent
    if target.is_dir():
        return "is a directory; give the path of a file in it (e.g. spool.db)"
    if not folder.is_dir():
        return f"its directory {str(folder)!r} does not exist"
    if not os.access(folder, os.W_OK | os.X_OK):
        return (f"its directory {str(folder)!r} is not writable by this process "
                f"(uid {os.geteuid()})")
    if target.exists() and not os.access(target, os.R_OK | os.W_OK):
        return f"not readable and writable by this process (uid {os.geteuid()})"
    return None


def message_size(topic: str, payload: bytes) -> int:
    """What one message counts against ``maxBytes``."""
    return len(topic.encode()) + len(payload) + ROW_OVERHEAD


class Spool:
    """Messages on disk, in append order, until acknowledged or dropped by the bounds.

    Thread-safe: one SQLite connection, every call under one lock.  The sender calls the
    mutating methods from the MQTT thread (so no line worker ever waits for the disk);
    :meth:`stats`, :meth:`pending_count`, :meth:`size_bytes` may be called from any
    thread (they read counters kept in memory; at worst they wait for one commit).

    ``synchronous="normal"`` (the default): a committed transaction is in the WAL file,
    i.e. in the kernel's page cache, when :meth:`append` returns; a killed process (also
    ``kill -9``, an OOM kill, a crash) loses nothing committed, because the kernel writes
    the page cache out whatever happens to the process.  A power loss or kernel panic
    may lose the last transactions (never corrupt the file: WAL rolls back to a
    committed state).  ``"full"`` fsyncs the WAL on every commit and survives power
    loss too, at the price of an fsync per append and per ack (milliseconds on an SD
    card, and flash wear).

    The file is opened in exclusive locking mode: a second process (a second gateway
    configured with the same path) gets a :class:`SpoolError` instead of replaying the
    same messages; the lock goes with the process, also after ``kill -9``.
    """

    def __init__(self, path: str | os.PathLike[str], *, max_bytes: int, max_age_s: float,
                 synchronous: str = "normal", clock: Callable[[], float] = time.time,
                 logger: logging.Logger = log) -> None:
        if max_bytes <= 0 or max_age_s <= 0:
            raise ValueError(f"max_bytes ({max_bytes}) and max_age_s ({max_age_s}) must "
                             "be > 0")
        if synchronous not in SYNCHRONOUS:
            raise ValueError(f"synchronous {synchronous!r} must be one of {SYNCHRONOUS}")
        problem = path_problem(path)
        if problem is not None:
            raise SpoolError(f"spool {str(path)!r}: {problem}")
        self.path = str(path)
        self.max_bytes = max_bytes
        self.max_age_s = max_age_s
        self._clock = clock
        self._limiter = LogLimiter(logger, interval=60.0, burst=1)
        self._lock = threading.Lock()
        self._inflight: dict[int, int] = {}  # claimed id -> size
        self._cursor = 0  # every stored row with id <= cursor is in flight
        self.counts: dict[str, int] = dict.fromkeys(
            ("appended", "acked", "released", "droppedSize", "droppedAge"), 0)
        self._closed = False
        self._count: int = 0  # rows stored
        self._bytes: int = 0  # their sizes
        self._oldest_ts: float | None = None  # the oldest row's append time
        self._db = self._open(synchronous)
        try:
            self._count, self._bytes, self._oldest_ts = self._db.execute(_TOTALS).fetchone()
        except sqlite3.Error as exc:
            self._db.close()
            raise SpoolError(f"spool {self.path!r}: cannot be read: {exc}") from None
        if self._count:
            log.info("spool %s: %d messages (%d bytes) kept from before, replayed first",
                     self.path, self._count, self._bytes)

    def _open(self, synchronous: str) -> sqlite3.Connection:
        where = f"spool {self.path!r}"
        db = sqlite3.connect(self.path, timeout=0, isolation_level=None,
                             check_same_thread=False)
        try:
            db.execute("PRAGMA locking_mode=EXCLUSIVE")
            version = db.execute("PRAGMA user_version").fetchone()[0]
            if version not in (0, SCHEMA_VERSION):
                raise SpoolError(f"{where}: schema version {version}, this edgemodbus "
                                 f"reads version {SCHEMA_VERSION}")
            if db.execute("PRAGMA journal_mode=WAL").fetchone()[0] != "wal":
                raise SpoolError(f"{where}: SQLite refused WAL mode")
            db.execute(f"PRAGMA synchronous={synchronous.upper()}")
            db.execute("BEGIN IMMEDIATE")  # takes the exclusive lock now, not later
            if version == 0:
                db.execute(_SCHEMA)
                db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
            db.execute("COMMIT")
        except sqlite3.OperationalError as exc:
            db.close()
            if "locked" in str(exc):
                raise SpoolError(f"{where}: in use by another process (or another "
                                 "spool in this one)") from None
            raise SpoolError(f"{where}: cannot be opened: {exc}") from None
        except sqlite3.DatabaseError as exc:
            db.close()
            raise SpoolError(f"{where}: not a spool file: {exc}") from None
        except BaseException:
            db.close()
            raise
        return db

    # -- the sender's calls (MQTT thread) -----------------------------------------------

    def append(self, messages: Iterable[Message], *, claimed: bool = False) -> list[int]:
        """Keep ``messages`` (one transaction: all or none); their ids, in order.

        ``claimed=True``: the caller hands them to paho right away (live QoS 1 while
        connected), so they are in flight at once and :meth:`next_batch` skips them.
        Messages that do not fit in ``maxBytes`` push out the oldest stored ones; a
        message alone larger than ``maxBytes`` (or the oldest of a batch larger than it)
        is dropped itself and gets no id (counted, logged).  :class:`SpoolError` when the
        disk refuses (full, I/O error): nothing of the batch is kept."""
        now = self._clock()
        rows = [(m.device, m.topic, bytes(m.payload), int(m.qos), int(m.retain), now,
                 message_size(m.topic, m.payload)) for m in messages]
        if not rows:
            return []
        with self._lock, self._transaction() as db:
            self._expire(now)
            incoming = sum(r[6] for r in rows)
            skipped = 0
            while incoming > self.max_bytes:  # the batch alone is too big: its oldest go
                incoming -= rows[skipped][6]
                skipped += 1
            if skipped:
                self._dropped("droppedSize", skipped, "size")
                rows = rows[skipped:]
            if self._bytes + incoming > self.max_bytes:
                self._drop_oldest(self._bytes + incoming - self.max_bytes)
            if not rows:
                return []
            db.executemany("INSERT INTO messages (device, topic, payload, qos, retain, ts,"
                           " size) VALUES (?, ?, ?, ?, ?, ?, ?)", rows)
            # AUTOINCREMENT in one transaction of the only writer: consecutive ids
            last = db.execute("SELECT seq FROM sqlite_sequence WHERE name = 'messages'"
                              ).fetchone()[0]
            ids = list(range(last - len(rows) + 1, last + 1))
            self._count += len(ids)
            self._bytes += incoming
            self.counts["appended"] += len(ids)
            if self._oldest_ts is None:
                self._oldest_ts = now
            if claimed:
                for i, row in zip(ids, rows, strict=True):
                    self._inflight[i] = row[6]
        with self._lock:
            self._limiter.flush()  # a summary of drops, once its interval is over
        return ids

    def next_batch(self, limit: int) -> list[Stored]:
        """Claim up to ``limit`` of the oldest messages that are not in flight, in id
        order (the order they were appended: global, hence per device too), after
        dropping those older than ``maxAgeS``.  They are in flight until :meth:`ack`
        or :meth:`release`."""
        if limit <= 0:
            return []
        with self._lock:
            db = self._live()
            now = self._clock()
            if self._oldest_ts is not None and self._oldest_ts < now - self.max_age_s:
                with self._transaction():
                    self._expire(now)
            taken: list[Stored] = []
            while len(taken) < limit and len(self._inflight) < self._count:
                try:
                    found = db.execute(f"SELECT {_COLUMNS}, size FROM messages WHERE id > ?"
                                       " ORDER BY id LIMIT ?", (self._cursor, _SCAN)
                                       ).fetchall()
                except sqlite3.Error as exc:
                    raise SpoolError(f"spool {self.path!r}: {exc}") from exc
                for row in found:
                    self._cursor = row[0]
                    if row[0] in self._inflight:
                        continue
                    self._inflight[row[0]] = row[7]
                    taken.append(Stored(row[0], row[1], row[2], row[3], row[4],
                                        bool(row[5]), row[6]))
                    if len(taken) == limit:
                        break
                if len(found) < _SCAN:
                    break
            self._limiter.flush()
        return taken

    def ack(self, ids: Iterable[int]) -> int:
        """The broker has them (PUBACK; for QoS 0: paho wrote them out): delete them, in
        one transaction.  Unknown ids (dropped by the bounds meanwhile, or acked
        already) are ignored.  How many were deleted."""
        wanted = list(ids)
        if not wanted:
            return 0
        with self._lock, self._transaction() as db:
            freed = deleted = 0
            for start in range(0, len(wanted), _PARAMS):
                chunk = wanted[start:start + _PARAMS]
                marks = ",".join("?" * len(chunk))
                for (size,) in db.execute(
                        f"DELETE FROM messages WHERE id IN ({marks}) RETURNING size",
                        chunk).fetchall():
                    freed += size
                    deleted += 1
            for i in wanted:
                self._inflight.pop(i, None)
            self._count -= deleted
            self._bytes -= freed
            self.counts["acked"] += deleted
            if not self._count:
                self._oldest_ts = None
                self._cursor = 0
        return deleted

    def release(self, ids: Iterable[int]) -> None:
        """Not sent after all (paho refused them): back to pending, so that
        :meth:`next_batch` returns them again, oldest first."""
        with self._lock:
            self._live()
            back = [i for i in ids if self._inflight.pop(i, None) is not None]
            if back:
                self._cursor = min(self._cursor, min(back) - 1)
                self.counts["released"] += len(back)

    def release_all(self) -> None:
        """Every message in flight back to pending (a new paho client: what the old one
        held unacknowledged is sent again, which QoS 1 allows)."""
        with self._lock:
            self._live()
            self.counts["released"] += len(self._inflight)
            self._inflight.clear()
            self._cursor = 0

    def device_tails(self) -> dict[str, int]:
        """Each device's newest stored id (at start-up: whose live messages must queue
        behind what was kept from before, to keep its order)."""
        with self._lock:
            try:
                rows = self._live().execute(
                    "SELECT device, MAX(id) FROM messages GROUP BY device").fetchall()
            except sqlite3.Error as exc:
                raise SpoolError(f"spool {self.path!r}: {exc}") from exc
        return {device: last for device, last in rows}

    # -- anyone -------------------------------------------------------------------------

    def pending_count(self) -> int:
        """Messages stored and not in flight: what :meth:`next_batch` can still return."""
        with self._lock:
            return self._count - len(self._inflight)

    def inflight_count(self) -> int:
        """Messages claimed (by :meth:`next_batch` or a claimed append), not yet acked."""
        with self._lock:
            return len(self._inflight)

    def size_bytes(self) -> int:
        """What the stored messages count against ``maxBytes``.  The file is larger
        (SQLite's pages, the WAL) and keeps its largest size until the spool empties."""
        with self._lock:
            return self._bytes

    def stats(self) -> dict[str, int]:
        """Counters (appended, acked, released, droppedSize, droppedAge) and gauges
        (stored, pending, inflight, bytes), camelCase for stats() and Prometheus."""
        with self._lock:
            out = dict(self.counts)
            out.update(stored=self._count, pending=self._count - len(self._inflight),
                       inflight=len(self._inflight), bytes=self._bytes)
        return out

    def close(self) -> None:
        """Checkpoint the WAL into the file and close (every call committed its own work
        already); further calls raise :class:`SpoolError`.  Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._limiter.flush(force=True)
            try:
                if not self._count:
                    self._db.execute("VACUUM")  # empty: give the disk space back
                self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            except sqlite3.Error as exc:  # still consistent: the WAL is replayed at open
                log.warning("spool %s: checkpoint at close failed: %s", self.path, exc)
            self._db.close()

    def __enter__(self) -> Spool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- inside the lock ----------------------------------------------------------------

    def _live(self) -> sqlite3.Connection:
        if self._closed:
            raise SpoolError(f"spool {self.path!r} is closed")
        return self._db

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction; on failure the file rolls back and so does what this
        object keeps in memory (counters, claims); sqlite3 errors become SpoolError."""
        db = self._live()
        saved = (dict(self.counts), dict(self._inflight), self._cursor)
        try:
            db.execute("BEGIN IMMEDIATE")
            yield db
            db.execute("COMMIT")
        except BaseException as exc:
            with contextlib.suppress(sqlite3.Error):
                if db.in_transaction:
                    db.execute("ROLLBACK")
            self.counts, self._inflight, self._cursor = saved
            with contextlib.suppress(sqlite3.Error):
                self._count, self._bytes, self._oldest_ts = db.execute(_TOTALS).fetchone()
            if isinstance(exc, sqlite3.Error):
                raise SpoolError(f"spool {self.path!r}: {exc}") from exc
            raise

    def _expire(self, now: float) -> None:
        """Drop the oldest rows appended before ``now - maxAgeS`` (in the open
        transaction).  Rows are visited in id order and the scan stops at the first young
        one, so a wall clock set back never drops a newer row before an older one."""
        if self._oldest_ts is None or self._oldest_ts >= now - self.max_age_s:
            return
        cutoff = now - self.max_age_s
        last, n, freed = self._scan_oldest(lambda ts, _freed: ts < cutoff)
        self._delete_through(last, n, freed, "droppedAge", "age")

    def _drop_oldest(self, need: int) -> None:
        """Drop the oldest rows until ``need`` bytes are freed (in the open transaction)."""
        last, n, freed = self._scan_oldest(lambda _ts, freed: freed < need)
        self._delete_through(last, n, freed, "droppedSize", "size")

    def _scan_oldest(self, more: Callable[[float, int], bool]) -> tuple[int, int, int]:
        """From the oldest row on, while ``more(ts, bytes freed so far)``: the last id
        taken, how many rows, how many bytes."""
        last, n, freed, after = 0, 0, 0, 0
        while True:
            rows = self._db.execute("SELECT id, ts, size FROM messages WHERE id > ? "
                                    "ORDER BY id LIMIT ?", (after, _SCAN)).fetchall()
            for row_id, ts, size in rows:
                if not more(ts, freed):
                    return last, n, freed
                last, n, freed = row_id, n + 1, freed + size
            if len(rows) < _SCAN:
                return last, n, freed
            after = rows[-1][0]

    def _delete_through(self, last: int, n: int, freed: int, counter: str,
                        why: str) -> None:
        if not n:
            return
        self._db.execute("DELETE FROM messages WHERE id <= ?", (last,))
        for i in [i for i in self._inflight if i <= last]:
            del self._inflight[i]  # dropped while in flight: its late ack finds nothing
        self._count -= n
        self._bytes -= freed
        self._cursor = max(self._cursor, last)
        oldest = self._db.execute("SELECT ts FROM messages ORDER BY id LIMIT 1").fetchone()
        self._oldest_ts = oldest[0] if oldest else None
        self._dropped(counter, n, why)

    def _dropped(self, counter: str, n: int, why: str) -> None:
        self.counts[counter] += n
        bound = (f"maxBytes {self.max_bytes}" if why == "size"
                 else f"maxAgeS {self.max_age_s:g}")
        self._limiter.event(logging.WARNING, f"drops from the spool ({bound})", self.path,
                            "spool %s: %d oldest messages dropped (%s)", self.path, n, bound)
