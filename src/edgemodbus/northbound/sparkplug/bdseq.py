"""bdSeq, the number that pairs an edge node's NDEATH with its NBIRTH (Sparkplug 3.0): 0-255,
one more for every MQTT session, kept in ``mqtt.sparkplug.bdSeqFile`` so that a restarted
gateway does not reuse the number of the session whose will the broker may still
deliver.  The gateway keeps it by default (settings.py: ``$STATE_DIRECTORY`` or the
gateway file's folder); a library caller without a file starts at 0 in each process.

The file is ours and says so: a first line :data:`MAGIC`, then the number.  An existing
file that is anything else (``gateway.json`` given by mistake) is refused, never
overwritten; a bare number 0-255 (what earlier versions wrote) and an empty file are
taken as ours.  Writes are atomic: a temporary file beside it, fsync, rename, fsync of
the folder, so a crash leaves the old number or the new one.

A redundant pair whose two instances are one edge node (``mqtt.sparkplug.sharedByPair``,
docs/deploy.md "Redundant pair") keeps it in the pair's Redis instead
(:class:`RedisBdSeqStore`), read again before each connect: the new leader's NBIRTH then
carries the number after the old leader's, and a host that applies the spec's rule
(an NDEATH counts only with the bdSeq of the node's last NBIRTH) ignores the old
leader's late NDEATH."""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ...config import ConfigError, Problem

log = logging.getLogger("edgemodbus.sparkplug")

MAGIC = "# edgemodbus Sparkplug bdSeq"
FIELD = "mqtt.sparkplug.bdSeqFile"


def parse_bd_seq(text: str) -> int | None:
    """The bdSeq in a file's ``text``; None for an empty file; ValueError saying what was
    found when it is not one of our bdSeq files."""
    lines = text.splitlines()
    if lines and lines[0].strip() == MAGIC:
        lines = lines[1:]
        if not lines:
            raise ValueError("our header without a number")
    body = "\n".join(lines).strip()
    if not body:
        return None
    if body.isdecimal() and len(body) <= 3 and int(body) <= 255:
        return int(body)
    shown = repr(body[:40]) + (f"... ({len(text)} characters)" if len(body) > 40 else "")
    raise ValueError(f"found {shown}")


def file_problem(path: str) -> str | None:
    """Why ``path`` cannot be our bdSeq file (it exists and holds something else, or
    cannot be read), or None."""
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"cannot be read: {exc.strerror or exc}"
    try:
        parse_bd_seq(text)
    except ValueError as exc:
        return (f"exists and is not an edgemodbus bdSeq file ({exc}); give another path, "
                "or remove it if it is no longer used")
    return None


class BdSeqStore:
    """The next session's bdSeq, read from and written to an optional file."""

    shared = False  # one process uses it: read once, at start

    def leading(self) -> bool:  # (RedisBdSeqStore's: whether this instance leads)
        return True

    def __init__(self, path: str | None) -> None:
        self.path = Path(path) if path is not None else None

    def load(self) -> int:
        """The stored next bdSeq, 0 without a file; ConfigError (naming the field, the
        path and what was found) when the file is not ours or cannot be read."""
        if self.path is None:
            return 0
        problem = file_problem(str(self.path))
        if problem is not None:
            raise ConfigError([Problem(FIELD, str(self.path), problem)])
        try:
            value = parse_bd_seq(self.path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return 0
        except (OSError, ValueError) as exc:  # changed since the check
            raise ConfigError([Problem(FIELD, str(self.path), str(exc))]) from None
        return 0 if value is None else value

    def save(self, value: int) -> None:
        """Keep ``value`` as the next session's bdSeq (atomically); a failure is logged,
        not raised (publishing goes on, the number is then only kept in memory)."""
        if self.path is None:
            return
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
            try:
                os.write(fd, f"{MAGIC}\n{value}\n".encode())
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, self.path)
            folder = os.open(self.path.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
            try:
                os.fsync(folder)
            finally:
                os.close(folder)
        except OSError as exc:
            log.warning("%s: cannot keep bdSeq %d: %s", self.path, value, exc.strerror or exc)
            with contextlib.suppress(OSError):
                tmp.unlink()


_SAVE_IF_OURS = """
local v = redis.call('GET', KEYS[1])
if v == false or (string.match(v, '^%d%d?%d?$') and tonumber(v) <= 255) then
  redis.call('SET', KEYS[1], ARGV[1])
  return false
end
return v
"""
"""Set the key only while it is absent or holds a bdSeq (the check and the write in one
atomic script); else return what it holds."""


def redis_bd_seq(key: str, raw: Any) -> int | None:
    """The bdSeq a Redis value holds (None: no value); ValueError naming the key and
    (a short prefix of) what was found for anything else (the key prefix of another
    application?): only the ASCII digits of 0-255, as :meth:`RedisBdSeqStore.save`
    writes them."""
    if raw is None:
        return None
    text = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw)
    if 0 < len(text) <= 3 and text.isascii() and text.isdigit() and int(text) <= 255:
        return int(text)
    shown = repr(text[:40]) + (f"... ({len(text)} characters)" if len(text) > 40 else "")
    raise ValueError(f"Redis key {key} holds {shown}, not a bdSeq 0-255; it is left as "
                     "it is: delete it, or give the pair another keyPrefix")


class RedisBdSeqStore:
    """The next session's bdSeq of an edge node that a redundant pair shares, in the
    pair's Redis (``client``: the lease's, gateway/lease.py) under ``key``; read before
    each connect (:attr:`shared`: the other instance may have used numbers since);
    ``leading``: whether this instance holds the pair's lease now (a session that paho
    opens again after it lost it is left at once).  Like the bdSeq file, the key is
    ours only while it holds a bdSeq: anything else is refused with what was found and
    never overwritten (the write checks it in the same atomic script)."""

    shared = True

    def __init__(self, client: Any, key: str, leading: Callable[[], bool]) -> None:
        self.client = client
        self.key = key
        self.leading = leading

    def load(self) -> int:
        """The stored next bdSeq (0 when none is stored); ValueError when the key holds
        anything else (the key prefix of another application?); a Redis error raises."""
        value = redis_bd_seq(self.key, self.client.get(self.key))
        return 0 if value is None else value

    def save(self, value: int) -> None:
        """Keep ``value`` as the next session's bdSeq, unless the key holds something
        that is not a bdSeq (then it is left, and an error says what it holds); a
        failure is logged, not raised (the next leader may then reuse this session's
        number, and a host would take this session's late NDEATH for the new one's)."""
        try:
            found = self.client.eval(_SAVE_IF_OURS, 1, self.key, value)
        except Exception as exc:
            log.warning("Redis %s: cannot keep bdSeq %d: %s", self.key, value, exc)
            return
        if found is not None:
            try:
                redis_bd_seq(self.key, found)
            except ValueError as exc:
                log.error("Sparkplug: bdSeq %d not kept: %s", value, exc)
