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

from ....line.log_limit import LogLimiter
from .file import (
    FULL,
    PAGE_SIZE,
    SpoolError,
    Unreadable,
    error_code,
    file_bound,
    file_bytes,
    looks_like_sqlite,
    move_aside,
    open_db,
    path_problem,
)
from .rows import SYNCHRONOUS, Message, Stored, message_size

log = logging.getLogger("edgemodbus.mqtt.spool")

_COLUMNS = "id, device, topic, payload, qos, retain, ts"
_TRIES = 5  # appends that make room for themselves before giving up
_SCAN = 512  # rows read per step when looking for the oldest rows to drop or send
_PARAMS = 500  # ids per DELETE ... IN (...) statement (SQLite allows 32766)


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
        self.bound = file_bound(max_bytes)
        self.moved_aside: str | None = None  # where an unreadable file was moved
        self._max_pages = 0  # max_page_count in force (the bound's, or the disk's)
        try:
            self._db, totals, self.bound = open_db(self.path, self.bound, synchronous)
        except Unreadable as exc:  # damaged: keep its bytes aside, start a new one
            what = "damaged" if looks_like_sqlite(self.path) else "not an SQLite file"
            try:
                self.moved_aside = move_aside(self.path)
            except OSError as err:
                raise SpoolError(f"spool {self.path!r}: unreadable ({exc}) and cannot be "
                                 f"moved aside: {err.strerror or err}") from None
            log.error("spool %s: unreadable, %s (%s): moved aside to %s, a new spool "
                      "started (what it held is not replayed)", self.path, what, exc,
                      self.moved_aside)
            try:
                self._db, totals, self.bound = open_db(self.path, self.bound, synchronous)
            except Unreadable as again:  # pragma: no cover - a fresh file is readable
                raise SpoolError(f"spool {self.path!r}: {again}") from None
        self._count, self._bytes, self._oldest_ts = totals
        self._max_pages = self.bound.max_pages
        if self._count:
            log.info("spool %s: %d messages (%d bytes) kept from before, replayed first",
                     self.path, self._count, self._bytes)
        with self._lock:
            self._shrink()
            self._fit_file()

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
        with self._lock:
            self._fit_disk()
            extra = 0  # bytes of the oldest rows to drop first: the file is at its bound
            for _ in range(_TRIES):
                try:
                    ids = self._append(rows, now, claimed, extra)
                    break
                except SpoolError as exc:
                    if not self._at_bound(exc, rows):
                        raise  # the disk is full or failing: the caller keeps them
                    if self._max_pages < self.bound.max_pages:  # the disk's bound
                        raise SpoolError(f"spool {self.path!r}: full: its disk leaves it "
                                         f"{self._max_pages * PAGE_SIZE} bytes (room "
                                         "kept for acknowledgements)") from None
                    # the database reached max_page_count: make room as maxBytes does
                    extra = max(4 * extra, sum(r[6] for r in rows) // 4, 2 * PAGE_SIZE)
            else:
                raise SpoolError(f"spool {self.path!r}: full (no room made by dropping "
                                 "the oldest messages: the disk refuses)")
            self._fit_file()
            self._limiter.flush()  # a summary of drops, once its interval is over
        return ids

    def _append(self, rows: list[tuple[str, str, bytes, int, int, float, int]], now: float,
                claimed: bool, extra: int) -> list[int]:
        """One try of :meth:`append` (inside the lock): ``extra`` more bytes of the oldest
        rows (then of the batch's oldest) dropped first."""
        with self._transaction() as db:
            self._expire(now)
            incoming = sum(r[6] for r in rows)
            over = max(0, self._bytes + incoming - self.max_bytes) + extra
            skipped = 0
            # the batch alone is too big (for maxBytes, or for the file): its oldest go
            while rows[skipped:] and (incoming > self.max_bytes
                                      or over > self._bytes):
                incoming -= rows[skipped][6]
                over -= rows[skipped][6]
                skipped += 1
            if skipped:
                self._dropped("droppedSize", skipped, "size")
                rows = rows[skipped:]
            if over > 0:
                self._drop_oldest(over)
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
                self._fit_file()
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
        with self._lock:
            self._fit_file()
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
        """What the stored messages count against ``maxBytes`` (their rows).  The file
        is larger (SQLite's pages, the WAL): :meth:`file_bytes`."""
        with self._lock:
            return self._bytes

    def file_bytes(self) -> int:
        """The bytes the database and its WAL take on disk: at most
        ``max(maxBytes, 64 KiB)`` whenever no call is under way (a transaction larger
        than the WAL's share may pass it until its commit)."""
        return file_bytes(self.path)

    def stats(self) -> dict[str, int]:
        """Counters (appended, acked, released, droppedSize, droppedAge) and gauges
        (stored, pending, inflight, bytes, fileBytes), camelCase for stats() and Prometheus."""
        with self._lock:
            out = dict(self.counts)
            out.update(stored=self._count, pending=self._count - len(self._inflight),
                       inflight=len(self._inflight), bytes=self._bytes,
                       fileBytes=file_bytes(self.path))
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
        totals = (self._count, self._bytes, self._oldest_ts)
        try:
            db.execute("BEGIN IMMEDIATE")
            yield db
            db.execute("COMMIT")
        except BaseException as exc:
            with contextlib.suppress(sqlite3.Error):
                if db.in_transaction:
                    db.execute("ROLLBACK")
            self.counts, self._inflight, self._cursor = saved
            self._count, self._bytes, self._oldest_ts = totals
            if isinstance(exc, sqlite3.Error):
                raise SpoolError(f"spool {self.path!r}: {exc}") from exc
            raise

    def _at_bound(self, exc: SpoolError, rows: list[tuple[str, str, bytes, int, int,
                                                          float, int]]) -> bool:
        """True when ``exc`` is SQLITE_FULL because the database could not grow past
        max_page_count by the pages ``rows`` need (the file bound, not the disk)."""
        cause = exc.__cause__
        if not isinstance(cause, sqlite3.Error) or error_code(cause) != FULL:
            return False
        try:
            pages = self._db.execute("PRAGMA page_count").fetchone()[0]
        except sqlite3.Error:
            return False
        need = 2 * sum(r[6] for r in rows) // self.bound.page_size + 4
        return bool(pages + need >= self._max_pages)

    def _fit_disk(self) -> None:
        """The database may grow only as far as its file system leaves room for a WAL
        and a checkpoint besides it (2 WAL shares free): an append that needs more is
        refused as on a full disk (the sender keeps it in memory), while
        acknowledgements and checkpoints still find room.  Lowers (or raises again, up to the bound)
        max_page_count; SQLite keeps it at least the current page count."""
        bound = self.bound
        try:
            vfs = os.statvfs(os.path.dirname(os.path.abspath(self.path)))
        except OSError:
            return
        capacity = file_bytes(self.path) + vfs.f_bavail * vfs.f_frsize
        frame = bound.page_size + 24
        wal_pages = max(4, min(bound.wal_pages, capacity // 8 // frame))
        room = capacity - 3 * (32 + wal_pages * frame)
        pages = max(8, min(bound.max_pages, room // bound.page_size))
        if pages != self._max_pages:
            try:
                self._db.execute(f"PRAGMA wal_autocheckpoint={wal_pages}")
                self._db.execute(f"PRAGMA journal_size_limit={32 + wal_pages * frame}")
                self._max_pages = self._db.execute(
                    f"PRAGMA max_page_count={pages}").fetchone()[0]
            except sqlite3.Error:
                return
            if self._max_pages < bound.max_pages:
                self._limiter.event(logging.WARNING, "spool size limited by the disk",
                                    self.path, "spool %s: limited to %d bytes by the free "
                                    "space of its disk (maxBytes %d)", self.path,
                                    self._max_pages * bound.page_size, self.max_bytes)

    def _shrink(self) -> None:
        """At open: a database larger than its share of the bound (kept from a run with
        a larger maxBytes) loses its oldest rows until what is left fits in half of it,
        then is vacuumed.  SpoolError when the disk refuses."""
        try:
            pages = self._db.execute("PRAGMA page_count").fetchone()[0]
            if pages <= self.bound.max_pages:
                return
            keep = self.bound.max_pages * self.bound.page_size // 4  # rows take ~2x
            if self._bytes > keep:
                with self._transaction():
                    self._drop_oldest(self._bytes - keep)
            self._db.execute("VACUUM")
        except sqlite3.Error as exc:
            raise SpoolError(f"spool {self.path!r}: larger than maxBytes "
                             f"{self.max_bytes} and cannot be shrunk: {exc}") from None
        log.warning("spool %s: larger than maxBytes %d: shrunk to %d bytes", self.path,
                    self.max_bytes, file_bytes(self.path))

    def _fit_file(self) -> None:
        """After a commit: when the database and its WAL together exceed the bound,
        checkpoint and truncate the WAL (its pages are in the database by then, which
        max_page_count keeps within its share).  A failure is logged: the WAL is
        checkpointed again after the next commit."""
        if file_bytes(self.path) <= self.bound.limit:
            return
        try:
            self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        except sqlite3.Error as exc:
            self._limiter.event(logging.WARNING, "WAL checkpoints failed", self.path,
                                "spool %s: WAL checkpoint failed: %s", self.path, exc)

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
