"""The spool's file on disk: where it may be kept, how large it may grow, and what is
done with a file that cannot be read (spool/__init__.py says the policy).

The bound is on the file, not on the rows: SQLite keeps a database file and, in WAL
mode, a ``-wal`` file beside it.  :class:`FileBound` splits ``maxBytes`` between the two:
the WAL is checkpointed every few pages (``wal_autocheckpoint``) and truncated back to
its share (``journal_size_limit``), and the database may not grow past the rest
(``max_page_count``: an insert that needs more pages fails with SQLITE_FULL, and the
spool drops its oldest rows to make room).
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import time
from pathlib import Path
from typing import NamedTuple

from ....config.files import mode_kind

PAGE_SIZE = 4096
WAL_FRAME = PAGE_SIZE + 24  # a WAL frame: the page and its 24-byte header
WAL_HEADER = 32
MIN_FILE_BYTES = 65_536
"""The smallest file bound: a spool needs a few pages for SQLite's own structures."""

SQLITE_HEADER = b"SQLite format 3\x00"
SCHEMA_VERSION = 1
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
_TOTALS = ("SELECT COUNT(*), COALESCE(SUM(size), 0), "
           "(SELECT ts FROM messages ORDER BY id LIMIT 1) FROM messages")


class SpoolError(RuntimeError):
    """The spool file cannot be used (missing folder, not a spool, used by another
    process, closed, the disk full or failing); the message names the path."""


class SpoolUnavailable(SpoolError):
    """The spool cannot be opened for now: its disk is full or failing (the sender
    keeps messages in memory and tries again)."""


class Unreadable(Exception):
    """The file is damaged (SQLite says corrupt, or not a database): moved aside."""


IOERR, CORRUPT, FULL, NOTADB = 10, 11, 13, 26  # SQLite's primary result codes


def error_code(exc: sqlite3.Error) -> int:
    return int(getattr(exc, "sqlite_errorcode", 0) or 0) & 0xFF




class FileBound(NamedTuple):
    """How ``max_bytes`` of file is shared between the database and its WAL."""

    limit: int  # database + WAL, bytes (at least MIN_FILE_BYTES)
    wal_pages: int  # wal_autocheckpoint: checkpoint once the WAL holds this many frames
    wal_bytes: int  # journal_size_limit: the WAL is truncated back to this after a reset
    max_pages: int  # max_page_count of the database
    page_size: int


def file_bound(max_bytes: int, page_size: int = PAGE_SIZE) -> FileBound:
    """The split of ``max_bytes`` (raised to :data:`MIN_FILE_BYTES`): an eighth for the
    WAL (4 to 256 pages), the rest for the database."""
    limit = max(max_bytes, MIN_FILE_BYTES)
    frame = page_size + 24
    wal_pages = max(4, min(256, limit // 8 // frame))
    wal_bytes = WAL_HEADER + wal_pages * frame
    return FileBound(limit, wal_pages, wal_bytes, max(8, (limit - wal_bytes) // page_size),
                     page_size)


def file_bytes(path: str) -> int:
    """The bytes the spool takes on disk: the database file and its ``-wal`` (the
    ``-shm`` index is not written in exclusive locking mode)."""
    total = 0
    for name in (path, path + "-wal"):
        with contextlib.suppress(FileNotFoundError):
            total += os.stat(name).st_size
    return total




def path_problem(path: str | os.PathLike[str]) -> str | None:
    """Why a spool cannot be kept at ``path``, or None: its folder must exist and be
    writable by this process, and the path must be a regular file or not exist yet (on
    a FIFO or a device SQLite fails with a bare "disk I/O error")."""
    target = Path(path)
    folder = target.parent
    if target.is_dir():
        return "is a directory; give the path of a file in it (e.g. spool.db)"
    if not folder.is_dir():
        return f"its directory {str(folder)!r} does not exist"
    if not os.access(folder, os.W_OK | os.X_OK):
        with contextlib.suppress(OSError):
            if os.statvfs(folder).f_flag & os.ST_RDONLY:
                return f"its directory {str(folder)!r} is on a read-only file system"
        return (f"its directory {str(folder)!r} is not writable by this process "
                f"(uid {os.geteuid()})")
    try:
        kind = mode_kind(os.stat(target).st_mode)
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"cannot be examined: {exc.strerror or exc}"
    if kind is not None:
        return f"is {kind}, not a regular file; give the path of a file (e.g. spool.db)"
    if not os.access(target, os.R_OK | os.W_OK):
        return f"not readable and writable by this process (uid {os.geteuid()})"
    return None


def looks_like_sqlite(path: str) -> bool:
    """True when the file starts with SQLite's header (a database, maybe damaged)."""
    try:
        with open(path, "rb") as file:
            return file.read(len(SQLITE_HEADER)) == SQLITE_HEADER
    except OSError:
        return False


def move_aside(path: str, clock_time: float | None = None) -> str:
    """Rename an unreadable spool (and its ``-wal``/``-shm``) to
    ``<path>.corrupt-<UTC time>``, never deleting a byte; the new name.  OSError when
    the folder refuses."""
    when = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(clock_time))
    target = f"{path}.corrupt-{when}"
    n = 1
    while os.path.exists(target):  # two in one second: keep both
        n += 1
        target = f"{path}.corrupt-{when}-{n}"
    os.rename(path, target)
    for suffix in ("-wal", "-shm"):
        if os.path.exists(path + suffix):
            os.rename(path + suffix, target + suffix)
    return target


def open_db(path: str, bound: FileBound, synchronous: str
        ) -> tuple[sqlite3.Connection, tuple[int, int, float | None], FileBound]:
    """Open (or create) the file and read its totals; :class:`_Unreadable` when it
    is damaged, :class:`SpoolError` when it is someone else's (see spool/__init__.py
    for why one is moved aside and the other refused) or cannot be opened."""
    where = f"spool {path!r}"
    db = sqlite3.connect(path, timeout=0, isolation_level=None,
                         check_same_thread=False)
    try:
        db.execute("PRAGMA locking_mode=EXCLUSIVE")
        version = db.execute("PRAGMA user_version").fetchone()[0]
        tables = {name for (name,) in db.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table'")}
        ours = {"messages", "sqlite_sequence"}
        if version not in (0, SCHEMA_VERSION):
            raise SpoolError(f"{where}: schema version {version}, this edgemodbus "
                             f"reads version {SCHEMA_VERSION}; refused, not touched")
        if (version == 0 and tables) or (version == SCHEMA_VERSION
                                         and "messages" not in tables) \
                or not tables <= ours:
            raise SpoolError(f"{where}: not a spool file: an SQLite database with "
                             f"tables {sorted(tables)}; refused, not touched (give "
                             "the path of a file of its own)")
        if version == 0:
            db.execute(f"PRAGMA page_size={PAGE_SIZE}")  # before the first table
        if db.execute("PRAGMA journal_mode=WAL").fetchone()[0] != "wal":
            raise SpoolError(f"{where}: SQLite refused WAL mode")
        db.execute(f"PRAGMA synchronous={synchronous.upper()}")
        db.execute(f"PRAGMA wal_autocheckpoint={bound.wal_pages}")
        db.execute(f"PRAGMA journal_size_limit={bound.wal_bytes}")
        db.execute("BEGIN IMMEDIATE")  # takes the exclusive lock now, not later
        if version == 0:
            db.execute(_SCHEMA)
            db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        db.execute("COMMIT")
        totals = db.execute(_TOTALS).fetchone()  # reads every row: damage shows
        page_size = db.execute("PRAGMA page_size").fetchone()[0]
        if page_size != PAGE_SIZE:  # a file made with another page size
            bound = file_bound(bound.limit, page_size)
        db.execute(f"PRAGMA max_page_count={bound.max_pages}")
    except sqlite3.DatabaseError as exc:
        db.close()
        if error_code(exc) in (CORRUPT, NOTADB):
            raise Unreadable(str(exc)) from None
        if "locked" in str(exc):
            raise SpoolError(f"{where}: in use by another process (or another "
                             "spool in this one)") from None
        if error_code(exc) in (IOERR, FULL):
            raise SpoolUnavailable(f"{where}: cannot be opened: {exc}") from None
        raise SpoolError(f"{where}: cannot be opened: {exc}") from None
    except BaseException:
        db.close()
        raise
    return db, totals, bound
