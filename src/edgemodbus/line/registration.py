"""How a DTU that dials in names itself: the registration settings of a listen port
(:class:`PortSettings`) and :func:`identify`, the pure rule that tells from the bytes a
new connection sent so far which configured DTU it is (the listener,
:mod:`edgemodbus.line.dtu_listener`, calls it on every segment and when a gap passes).

When a registration is complete
-------------------------------
A registration may arrive split over TCP segments ("DTU1", then "0"), so it is complete
only when it cannot grow into another id.  Heartbeats before it are skipped (and, in text
and regex mode, CR/LF/NUL).  Then, per mode:

* ``registrationLength`` N (any mode): the next N bytes are the packet, complete as soon
  as they are in (text: trailing CR/LF/NUL stripped; regex: the pattern is searched in
  them).
* text: the id ends at a byte no text id contains: CR, LF, NUL or another control byte,
  a byte that never occurs in UTF-8 (0xC0, 0xC1, 0xF5-0xFF, e.g. a wrapped frame's FF AA),
  or the configured heartbeat.  Such an end completes it at once.  Without one, bytes that
  equal a configured id are taken only after a quiet gap (:data:`QUIET_GAP`, no further
  byte) or at the registration timeout: until then they may be the beginning of a longer
  id, configured or not ("DTU1" of "DTU10", "DTU12").
* hex: ids are binary, so no byte ends one; only the heartbeat (or the fixed length) does.
  Otherwise as text: an exact match waits for the quiet gap or the timeout.
* regex: the pattern is searched only in terminated content: the bytes up to an end (as
  in text mode, line ends included so a pattern may name them), or everything after the
  quiet gap or at the timeout; never in a prefix that could still grow ("ID:1" of
  "ID:10").  Its first group, else its whole match, is the id.

A heartbeat inside a configured id does not end it (``DTU-HB-7`` with heartbeat ``HB``;
hex id ``0100A3`` with heartbeat ``00``): the configured id the bytes match is taken
first, the longest when several are (followed by an end, or alone once settled), and
only then the first end; a registration that may still grow into a configured id
containing the heartbeat waits as any prefix does.  Heartbeats before it are skipped,
unless a configured id begins with the heartbeat: then the id is tried where the bytes
begin first.  In regex mode a match before a heartbeat is held while a later end may
still name a longer configured id.  An id made of heartbeats alone is refused by the
configuration (config/listen.py).

The peer is unknown at once when, in text or hex mode, its bytes are no beginning of a
configured id or what comes before an end is not one, or when, in regex mode, a
terminated match names no configured id; also after ``registrationMaxBytes``
(:attr:`PortSettings.max_bytes`) bytes without a registration.  So an id that is a
prefix of another configured id is matched at an end, or after the quiet gap, never
early.  Bytes after the registration (CR/LF/NUL
right after it are consumed; a heartbeat or a wrapped frame is not) are handed to the
link with the socket, never lost nor taken for part of the id.  The quiet gap trades a
short delay of an unterminated registration for safety: a DTU that pauses longer than the
gap inside its own registration may still be taken for the id it sent so far; give such
DTUs a terminator or a ``registrationLength``.
"""

from __future__ import annotations

import bisect
import re
from collections.abc import Collection, Iterable, Iterator
from dataclasses import dataclass, field

QUIET_GAP = 0.5
"""Seconds without a further byte after which a registration that equals a configured id,
but has no end, is taken.  Longer than Linux's minimum TCP retransmission timeout (0.2 s),
so that one retransmitted segment of the rest of a longer id is still awaited."""

DUPLICATE_POLICIES = ("keep-existing", "replace")
"""What a second connection claiming a connected DTU's id gets: ``keep-existing`` (the
old connection stays while it still answers; the default, so that an impostor cannot
take an answering DTU's place) or ``replace`` (the newcomer takes over at once)."""

_LINE_ENDS = b"\r\n\0"


@dataclass(frozen=True)
class PortSettings:
    """What every device naming one listen port must agree on."""

    host: str
    port: int
    registration: str = "none"  # none | text | hex | regex
    pattern: str = ""  # regex: searched in the packet (Latin-1); group 1 or the match is the id
    length: int | None = None  # fixed registration packet length in bytes
    timeout: float = 5.0  # seconds for a new connection to register
    heartbeat: bytes = b""  # skipped before the registration packet too
    quiet_gap: float = QUIET_GAP  # see the module docstring: when a registration is complete
    # what an unregistered connection may cost (the listener faces the internet)
    max_bytes: int = 256  # registrationMaxBytes: bytes before a registration, then closed
    byte_rate: int = 1024  # registrationByteRate: bytes/s read before it (0: no limit)
    max_unregistered: int = 512  # maxUnregistered: connections not registered yet
    max_per_source: int = 64  # maxUnregisteredPerSource: the same, per source address
    allow_from: tuple[str, ...] = ()  # listenAllowFrom: CIDR networks (empty: any)
    duplicate_id: str = "keep-existing"  # duplicateId: one of DUPLICATE_POLICIES
    flip_limit: int = 5  # idFlipLimit: replacements of one id within flip_window ...
    flip_window: float = 60.0  # idFlipWindow (s): ... beyond which the id is contested
    engine: str | None = None  # engine: thread | loop (None: the registry's; line/loop.py)
    loop_threads: int | None = None  # loopThreads (None: one per core)

    @property
    def key(self) -> tuple[str, int]:
        return (self.host, self.port)

    def differences(self, other: PortSettings) -> list[str]:
        names = {"registration": "registration", "pattern": "registrationPattern",
                 "length": "registrationLength", "timeout": "registrationTimeout",
                 "heartbeat": "heartbeat", "max_bytes": "registrationMaxBytes",
                 "byte_rate": "registrationByteRate", "max_unregistered": "maxUnregistered",
                 "max_per_source": "maxUnregisteredPerSource",
                 "allow_from": "listenAllowFrom", "duplicate_id": "duplicateId",
                 "flip_limit": "idFlipLimit", "flip_window": "idFlipWindow",
                 "engine": "engine"}
        return [f"{key} {getattr(other, attr)!r} (the port has {getattr(self, attr)!r})"
                for attr, key in names.items() if getattr(self, attr) != getattr(other, attr)]


@dataclass(frozen=True)
class DtuAccess:
    """Who may register as one DTU (every device naming the DTU must agree)."""

    allow_from: tuple[str, ...] = ()  # dtuAllowFrom: CIDR networks (empty: as the port)
    key: bytes = field(default=b"", repr=False)  # registrationKey (never shown nor logged)


@dataclass(frozen=True, slots=True)
class Identified:
    """A registration that names a configured DTU."""

    dtu_id: str
    end: int  # bytes of the buffer that were the registration; the rest is the DTU's data
    key: bytes | None = field(default=None, repr=False)  # the pattern's ``key`` group


class IdIndex:
    """The configured ids of a port as the bytes they are sent as, sorted, so that
    :func:`identify` looks an id up, and asks whether a registration may still grow into
    one, in O(log n) for thousands of DTUs (not a scan of every id per segment)."""

    def __init__(self, mode: str, ids: Iterable[str] = ()) -> None:
        self._hex = mode == "hex"
        self._ids: dict[bytes, str] = {}
        self._names: set[str] = set()
        self._sorted: list[bytes] = []
        # (heartbeat, how many keys contain it): kept up to date once asked
        self._holding: tuple[bytes, int] = (b"", 0)
        for dtu_id in ids:
            self.add(dtu_id)

    def _key(self, dtu_id: str) -> bytes:
        return bytes.fromhex(dtu_id) if self._hex else dtu_id.encode()

    def add(self, dtu_id: str) -> None:
        key = self._key(dtu_id)
        if key not in self._ids:
            bisect.insort(self._sorted, key)
            hb, count = self._holding
            if hb and hb in key:
                self._holding = (hb, count + 1)
        self._ids[key] = dtu_id
        self._names.add(dtu_id)

    def remove(self, dtu_id: str) -> None:
        key = self._key(dtu_id)
        if self._ids.pop(key, None) is not None:
            del self._sorted[bisect.bisect_left(self._sorted, key)]
            hb, count = self._holding
            if hb and hb in key:
                self._holding = (hb, count - 1)
        self._names.discard(dtu_id)

    def hold(self, heartbeat: bytes) -> bool:
        """Whether a configured id contains ``heartbeat`` (counted once, then kept up to
        date as ids come and go): only then may a heartbeat be inside an id."""
        if not heartbeat:
            return False
        if self._holding[0] != heartbeat:
            self._holding = (heartbeat, sum(heartbeat in key for key in self._sorted))
        return self._holding[1] > 0

    def begins(self, packet: bytes) -> bool:
        """Whether a configured id begins with ``packet`` (or is it)."""
        return packet in self._ids or self.may_grow(packet)

    def longer(self, head: bytes, tail: bytes) -> bool:
        """Whether ``head`` + ``tail`` is, begins with, or may still grow into a
        configured id longer than ``head`` (a heartbeat in ``tail`` may be inside it)."""
        packet = head + tail
        return self.may_grow(packet) or any(
            packet[:n] in self._ids for n in range(len(head) + 1, len(packet) + 1))

    def get(self, key: bytes) -> str | None:
        """The id sent as ``key``."""
        return self._ids.get(key)

    def has_name(self, dtu_id: str) -> bool:
        return dtu_id in self._names

    def may_grow(self, packet: bytes) -> bool:
        """Whether a configured id is longer than ``packet`` and begins with it (such ids
        sort right after ``packet``)."""
        at = bisect.bisect_right(self._sorted, packet)
        return at < len(self._sorted) and self._sorted[at].startswith(packet)

    def prefixes(self, packet: bytes) -> Iterator[bytes]:
        """The configured keys that ``packet`` begins with and is longer than."""
        ids = self._ids
        return (packet[:n] for n in range(1, len(packet)) if packet[:n] in ids)


def identify(buf: bytes, ids: Collection[str] | IdIndex, settings: PortSettings, *,
             settled: bool) -> Identified | str | None:
    """Decide what the bytes a new connection sent so far register as (the rule is in the
    module docstring): :class:`Identified` for a configured id, a description (str) of a
    registration that names no configured DTU, or None while it is not complete.
    ``settled``: the quiet gap has passed since the last byte, or the registration timeout
    has run out.  Pure: the listener calls it on every segment and when a gap passes,
    with an :class:`IdIndex` it keeps (a plain collection of ids is indexed here)."""
    mode = settings.registration
    index = ids if isinstance(ids, IdIndex) else IdIndex(mode, ids)
    hb = settings.heartbeat
    starts = [0]  # where the registration may begin: after each heartbeat or line end
    while starts[-1] < len(buf):
        at = starts[-1]
        if hb and buf.startswith(hb, at):
            starts.append(at + len(hb))
        elif mode != "hex" and buf[at] in _LINE_ENDS:
            starts.append(at + 1)
        else:
            break
    if mode == "regex" or not hb or not index.begins(hb):
        starts = starts[-1:]  # no id begins with the heartbeat: skip them all
    found: Identified | str | None = None
    waiting = False
    for start in starts:
        # an id that begins with the heartbeat is tried before the heartbeat is skipped
        found = _from(buf, start, index, settings, settled)
        if isinstance(found, Identified):
            return found
        if found is None:
            waiting = True
            if not settled:
                break  # it may still grow into an id that begins here
    if waiting:
        found = None
    if found is None and len(buf) >= settings.max_bytes:
        return f"no registration in the first {settings.max_bytes} bytes"
    return found


def _from(buf: bytes, start: int, index: IdIndex, settings: PortSettings,
          settled: bool) -> Identified | str | None:
    """:func:`identify` for a registration that begins at ``start``."""
    mode = settings.registration
    hb = settings.heartbeat
    packet = buf[start:]
    if not settled and hb and packet and len(packet) < len(hb) and hb.startswith(packet):
        return None  # the first part of a heartbeat
    length = settings.length
    if length is not None:
        if len(packet) < length:
            return None
        packet = packet[:length]
        if mode == "regex":
            return _search(packet, index, settings.pattern, start + length)
        key = packet if mode == "hex" else packet.rstrip(_LINE_ENDS)
        return _lookup(key, index, start + length, mode)
    if mode == "regex":
        return _regex_terminated(packet, index, settings, start, settled)
    return _exact(packet, index, settings, start, settled)


def _lookup(key: bytes, wanted: IdIndex, end: int, mode: str) -> Identified | str:
    dtu_id = wanted.get(key)
    if dtu_id is not None:
        return Identified(dtu_id, end)
    return key.hex(" ").upper() if mode == "hex" else key.decode("latin-1")


def _text_end(byte: int) -> bool:
    """A byte that no text id contains: a control byte, or one never found in UTF-8."""
    return byte < 0x20 or byte == 0x7F or byte in (0xC0, 0xC1) or byte >= 0xF5


def _ends(packet: bytes, settings: PortSettings) -> list[tuple[int, int, bool]]:
    """(where the content ends, where the registration ends, whether a heartbeat ends it)
    for every end in ``packet`` (text and regex mode: an end byte, CR/LF/NUL consumed;
    any mode: a heartbeat)."""
    hb = settings.heartbeat
    text = settings.registration != "hex"
    found: list[tuple[int, int, bool]] = []
    i = 0
    while i < len(packet):
        if hb and packet.startswith(hb, i):
            found.append((i, i, True))
            i += len(hb)
        elif text and _text_end(packet[i]):
            j = i
            while j < len(packet) and packet[j] in _LINE_ENDS:
                j += 1
            found.append((i, j, False))
            i = max(j, i + 1)
        else:
            i += 1
    return found


def _end_at(rest: bytes, settings: PortSettings) -> int | None:
    """How many bytes of ``rest`` an end at its start consumes (0: a heartbeat, which
    stays data, or an end byte that is no line end), None when no end is there."""
    if settings.heartbeat and rest.startswith(settings.heartbeat):
        return 0
    if settings.registration != "hex" and rest and _text_end(rest[0]):
        return len(rest) - len(rest.lstrip(_LINE_ENDS))
    return None


def _exact(packet: bytes, wanted: IdIndex, settings: PortSettings, start: int,
           settled: bool) -> Identified | str | None:
    """Text and hex mode without a fixed length.  A configured id the bytes begin with,
    followed by an end, is the registration, the longest first: a heartbeat inside a
    longer configured id ("DTU-HB-7" with heartbeat "HB") does not end it early."""
    exact = wanted.get(packet)
    growing = wanted.may_grow(packet)
    if growing:
        # it may still grow into a configured id: an exact match is taken once settled,
        # else a shorter one before a heartbeat ("B" + "HB" of "BHBA")
        if not settled:
            return None
        if exact is not None:
            return Identified(exact, start + len(packet))
    if exact is not None:
        # the whole of a configured id: longer than any before a heartbeat ("AHB" of
        # "A" + "HB"); taken once settled, it may still grow into an id not configured
        return Identified(exact, start + len(packet)) if settled else None
    hb = settings.heartbeat
    for key in sorted(wanted.prefixes(packet), key=len, reverse=True):
        dtu_id = wanted.get(key)
        assert dtu_id is not None
        rest = packet[len(key):]
        consumed = _end_at(rest, settings)
        if consumed is not None:
            return Identified(dtu_id, start + len(key) + consumed)
        if hb and hb.startswith(rest):
            # maybe a heartbeat follows the id
            return Identified(dtu_id, start + len(key)) if settled else None
    if growing:
        return None  # the beginning of a configured id, quiet: the timeout decides
    ends = _ends(packet, settings)
    content, end = (ends[0][0], ends[0][1]) if ends else (len(packet), len(packet))
    # no configured id begins with these bytes, whatever follows
    return _lookup(packet[:content], wanted, start + end, settings.registration)


def _regex_terminated(packet: bytes, ids: IdIndex, settings: PortSettings,
                      start: int, settled: bool) -> Identified | str | None:
    """Regex mode without a fixed length: search terminated content only.  When a
    configured id contains the heartbeat, a heartbeat may be inside the id: a match
    before it is held while a later end may still name a longer configured id."""
    hb = settings.heartbeat
    inside = ids.hold(hb)
    held: Identified | None = None
    for content, end, beat in _ends(packet, settings):
        found = _search(packet[:end], ids, settings.pattern, start + end, quiet=True)
        if found is None:
            continue
        if beat and inside:
            name = found.dtu_id if isinstance(found, Identified) else found
            if ids.longer(name.encode(), packet[content:]):
                # "7" of "7HB8": the heartbeat may be inside a longer configured id
                if isinstance(found, Identified) and held is None:
                    held = found
                continue
        return held if held is not None and not isinstance(found, Identified) else found
    if settled:  # the whole: a longer configured id than the one held, or the held one
        found = _search(packet, ids, settings.pattern, start + len(packet), quiet=True)
        return held if held is not None and not isinstance(found, Identified) else found
    if held is not None and not ids.longer(held.dtu_id.encode(), packet[held.end - start:]):
        return held
    return None


def _search(packet: bytes, ids: IdIndex, pattern: str, end: int,
            quiet: bool = False) -> Identified | str | None:
    """The id ``pattern`` finds in ``packet`` and the key beside it (:func:`pattern_id`).
    No match: None when ``quiet`` (more may come), else the reason."""
    match = re.search(pattern, packet.decode("latin-1"))
    if match is None:
        return None if quiet else "no match of registrationPattern"
    dtu_id, key = pattern_id(match)
    return Identified(dtu_id, end, key) if ids.has_name(dtu_id) else dtu_id


def pattern_id(match: re.Match[str]) -> tuple[str, bytes | None]:
    """The id and key a registrationPattern match names: the id is the group named
    ``id``, else the first group that is not ``key``, else the whole match; the key is the
    group named ``key`` (None when the pattern has none or it took no part)."""
    groups = match.re.groupindex
    key_group = groups.get("key")
    if "id" in groups:
        dtu_id = match.group("id")
    else:
        first = next((n for n in range(1, match.re.groups + 1) if n != key_group), 0)
        dtu_id = match.group(first)
    key = match.group("key") if key_group is not None else None
    return dtu_id or "", None if key is None else key.encode("latin-1")


__all__ = ["DUPLICATE_POLICIES", "QUIET_GAP", "DtuAccess", "IdIndex", "Identified",
           "PortSettings", "identify", "pattern_id"]
