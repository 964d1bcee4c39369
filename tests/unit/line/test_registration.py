"""When a DTU's registration is complete (edgemodbus.line.registration.identify, a pure
function): ids that are prefixes of others, registrations split over TCP segments,
terminators, quiet gaps, and the bytes that follow a registration."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from edgemodbus.line.registration import Identified, PortSettings, identify

HEARTBEAT = b"HB"
WRAPPED = bytes.fromhex("FFAA0001010302030578B70D")  # a report right after registering


def port(registration: str, *, heartbeat: bytes = b"", pattern: str = "",
         length: int | None = None) -> PortSettings:
    return PortSettings("127.0.0.1", 9502, registration=registration, pattern=pattern,
                        length=length, heartbeat=heartbeat)


def feed(settings_: PortSettings, ids: list[str], segments: list[bytes]
         ) -> Identified | str | None:
    """What the listener decides, segment by segment, before any quiet gap."""
    buf = b""
    for segment in segments:
        buf += segment
        found = identify(buf, ids, settings_, settled=False)
        if found is not None:
            return found
    return None


# --- the reported cases ---------------------------------------------------------------

@pytest.mark.parametrize(("mode", "ids", "segments", "short"), [
    ("text", ["DTU1", "DTU10"], [b"DTU1", b"0"], "DTU1"),
    ("hex", ["0102", "010203"], [b"\x01\x02", b"\x03"], "0102"),
    ("regex", ["1", "10"], [b"ID:1", b"0"], "1"),
])
def test_an_id_that_is_a_prefix_of_another_is_not_taken_early(
        mode: str, ids: list[str], segments: list[bytes], short: str) -> None:
    ps = port(mode, pattern=r"ID:(\d+)" if mode == "regex" else "")
    assert feed(ps, ids, segments[:1]) is None  # "DTU1" may be the start of "DTU10"
    long_id = ids[1]
    assert feed(ps, ids, segments) is None or feed(ps, ids, segments) == Identified(
        long_id, len(b"".join(segments)))
    whole = b"".join(segments)
    assert identify(whole, ids, ps, settled=True) == Identified(long_id, len(whole))
    # the short id on its own is taken once the line is quiet, not before
    first = segments[0]
    assert identify(first, ids, ps, settled=True) == Identified(short, len(first))


def test_regex_unknown_short_id_is_not_matched_on_a_prefix() -> None:
    """"ID:1" of "ID:10" used to be taken as id "1" (here not configured: the peer was
    closed as unknown)."""
    ps = port("regex", pattern=r"ID:(\d+)")
    assert feed(ps, ["10"], [b"ID:1"]) is None
    assert feed(ps, ["10"], [b"ID:1", b"0\r\n"]) == Identified("10", 7)
    assert identify(b"ID:1\r\n", ["10"], ps, settled=False) == "1"  # terminated: unknown


@pytest.mark.parametrize(("mode", "buf", "expected"), [
    ("text", b"DTU1\r\nrest", Identified("DTU1", 6)),
    ("text", b"HBDTU1HB", Identified("DTU1", 6)),  # the heartbeat after it stays data
    ("text", b"\r\nDTU1\0", Identified("DTU1", 7)),
    ("text", b"DTU1" + WRAPPED, Identified("DTU1", 4)),
    ("text", b"DTU12\r\n", "DTU12"),  # not configured, though DTU1 is
    ("text", b"DTU1X", "DTU1X"),  # nothing configured begins so: unknown at once
    ("hex", b"\x01\x02HB", Identified("0102", 2)),
    ("hex", b"\x01\x02\r\n", "01 02 0D 0A"),  # binary ids: CR/LF are no terminators
    ("regex", b"IMEI:42,ID:10\r\n", Identified("10", 15)),
])
def test_ends_and_what_follows(mode: str, buf: bytes, expected: Identified | str) -> None:
    ids = {"text": ["DTU1", "DTU10"], "hex": ["0102", "010203"], "regex": ["1", "10"]}[mode]
    ps = port(mode, heartbeat=HEARTBEAT, pattern=r"ID:(\d+)" if mode == "regex" else "")
    assert identify(buf, ids, ps, settled=False) == expected


def test_fixed_length_ends_the_packet() -> None:
    ps = port("text", length=6)
    assert identify(b"DTU1\0", ["DTU1", "DTU10"], ps, settled=True) is None
    assert identify(b"DTU1\0\0" + WRAPPED, ["DTU1", "DTU10"], ps,
                    settled=False) == Identified("DTU1", 6)
    ps = port("regex", length=7, pattern=r"ID:(\d+)")
    assert identify(b"ID:10\r\n", ["1", "10"], ps, settled=False) == Identified("10", 7)
    assert identify(b"ID:x\r\n\r", ["1"], ps, settled=False) == "no match of registrationPattern"


@pytest.mark.parametrize(("mode", "hb", "ids", "segments", "expected"), [
    # the heartbeat inside an id used to end it: "DTU-" was refused as unknown
    ("text", b"HB", ["DTU-HB-7"], [b"DTU-", b"HB", b"-7\r\n"], Identified("DTU-HB-7", 10)),
    ("text", b"HB", ["DTU-HB-7", "DTU-"], [b"HBDTU-HB-7HB"], Identified("DTU-HB-7", 10)),
    ("text", b"HB", ["DTU-HB-7", "DTU-"], [b"DTU-HBHB"], Identified("DTU-", 4)),
    ("hex", b"\x00", ["0100A3"], [b"\x01", b"\x00\xa3"], None),  # waits: 0100A3FF...
    ("hex", b"\x00", ["0100A3"], [b"\x00\x01\x00", b"\xa3\x00"],
     Identified("0100A3", 4)),
    ("hex", b"\x00", ["00A1"], [b"\x00\x00\xa1\x00"], Identified("00A1", 3)),
    ("regex", b"HB", ["7HB8"], [b"ID:7", b"HB8\r\n"], Identified("7HB8", 9)),
    ("regex", b"HB", ["7HB8", "7"], [b"ID:7HB", b"\x01\x03"], Identified("7", 4)),
])
def test_a_heartbeat_inside_a_configured_id_does_not_end_it(
        mode: str, hb: bytes, ids: list[str], segments: list[bytes],
        expected: Identified | None) -> None:
    ps = port(mode, heartbeat=hb, pattern=r"ID:(\w+)" if mode == "regex" else "")
    assert feed(ps, ids, segments) == expected
    if expected is None:  # taken once the line is quiet
        whole = b"".join(segments)
        assert identify(whole, ids, ps, settled=True) == Identified(ids[0], len(whole))


def test_a_peer_that_never_registers_is_unknown_after_a_bounded_buffer() -> None:
    ps = port("regex", pattern=r"ID:(\d+)")
    assert identify(b"x" * (ps.max_bytes - 1), ["1"], ps, settled=False) is None
    assert identify(b"x" * ps.max_bytes, ["1"], ps, settled=False) == (
        f"no registration in the first {ps.max_bytes} bytes")


# --- the class: random id sets with prefixes, random segmentation -----------------------

@dataclass(frozen=True)
class Case:
    mode: str
    hb: bytes  # the port's heartbeat
    ids: list[str]
    sent: str  # the id the DTU sends
    lead: bytes  # heartbeats (and line ends) before the registration
    starts: list[int]  # where each of them ends (0 first): where a registration may begin
    body: bytes  # what the id is sent as (regex: with its prefix)
    end: bytes  # what ends it (b"": nothing, the quiet gap must)
    consumed: int  # bytes of ``end`` that belong to the registration
    data: bytes  # what the DTU sends after it
    cuts: list[int]

    @property
    def stream(self) -> bytes:
        return self.lead + self.body + self.end + self.data

    @property
    def configured(self) -> bool:
        return self.sent in self.ids

    def may_grow(self, stream: bytes) -> bool:
        """Whether ``stream`` (from where a registration may begin) is the beginning of
        a longer configured id (a heartbeat after the id may be inside it): then only
        the quiet gap completes it."""
        bodies = [body_of(self.mode, i) for i in self.ids]
        return any(b.startswith(stream[at:]) and len(b) > len(stream) - at
                   for b in bodies for at in self.starts)


def body_of(mode: str, dtu_id: str) -> bytes:
    if mode == "hex":
        return bytes.fromhex(dtu_id)
    return b"ID:" + dtu_id.encode() if mode == "regex" else dtu_id.encode()


def lead_starts(mode: str, hb: bytes, stream: bytes) -> list[int]:
    """Where a registration may begin: 0, and after each heartbeat (and, but in hex
    mode, each CR/LF/NUL) the stream begins with."""
    starts = [0]
    while True:
        at = starts[-1]
        if stream.startswith(hb, at):
            starts.append(at + len(hb))
        elif mode != "hex" and at < len(stream) and stream[at] in b"\r\n\0":
            starts.append(at + 1)
        else:
            return starts


def ambiguous(mode: str, hb: bytes, ids: list[str], sent: str, stream: bytes,
              starts: list[int], reg_start: int, reg_end: int) -> bool:
    """Whether ``stream`` is also another configured id's registration, followed by an
    end, that begins before the sent one (at ``reg_start``, up to ``reg_end``) or as
    early and reaches further ("A" + heartbeat when "A" and "AHB" are both configured;
    "AHB" unconfigured when "A" is; an id beginning with the heartbeat after a leading
    heartbeat): the rule takes the configured id the bytes match that begins first, the
    longest of those, so such streams have no single answer."""
    for other in ids:
        if other == sent:
            continue
        body = body_of(mode, other)
        for at in starts:
            if not stream.startswith(body, at):
                continue
            reach = at + len(body)
            if sent in ids and at >= reg_start and (at > reg_start or reach < reg_end):
                continue  # the sent id begins first, or as early and is longer: taken
            rest = stream[reach:]
            if not rest or rest.startswith(hb) or (mode != "hex" and rest[0] < 0x20) or \
                    (mode != "hex" and rest[0] >= 0xF5) or hb.startswith(rest):
                return True
    return False


@st.composite
def cases(draw: st.DrawFn) -> Case:
    mode = draw(st.sampled_from(["text", "hex", "regex"]))
    # ids contain the heartbeat (text and regex "HB"; hex 00 or "HB")
    hb = draw(st.sampled_from([b"\x00", HEARTBEAT])) if mode == "hex" else HEARTBEAT
    if mode == "hex":
        id_st = st.lists(st.sampled_from(["01", "02", "0D", "00", hb.hex().upper()]),
                         min_size=1, max_size=4).map("".join)
    else:
        id_st = st.lists(st.sampled_from(["A", "B", "0", "1", "HB"]), min_size=1,
                         max_size=4).map("".join)
    # an id made of heartbeats alone is refused by the configuration (listen.py)
    id_st = id_st.filter(lambda i: body_of("text" if mode == "regex" else mode, i)
                         .replace(hb, b"") != b"")
    ids = draw(st.lists(id_st, min_size=1, max_size=6, unique=True))
    # the sender: a configured id, or one that is not (often a prefix or an extension)
    sent = draw(st.one_of(st.sampled_from(ids), id_st))
    body = body_of(mode, sent)
    leads = draw(st.lists(st.sampled_from([hb] + ([] if mode == "hex" else [b"\r\n"])),
                          max_size=2))
    lead = b"".join(leads)
    ends: list[tuple[bytes, int]] = [(b"", 0), (hb, 0)]
    if mode != "hex":
        ends += [(b"\r\n", 2), (b"\0", 1), (b"\r", 1), (WRAPPED, 0)]
    end, consumed = draw(st.sampled_from(ends))
    data = draw(st.sampled_from([b"", b"\x01\x03\x02\x00\x07", hb, WRAPPED])) \
        if end else b""
    stream = lead + body + end + data
    starts = lead_starts(mode, hb, stream)
    assume(not ambiguous(mode, hb, ids, sent, stream, starts, len(lead),
                          len(lead) + len(body)))
    cuts = draw(st.lists(st.integers(1, len(stream)), max_size=6))
    return Case(mode, hb, ids, sent, lead, starts, body, end, consumed, data,
                sorted(set(cuts)))


@settings(max_examples=600, deadline=None)
@given(case=cases())
def test_a_registration_names_its_own_id_however_it_is_split(case: Case) -> None:
    ps = port(case.mode, heartbeat=case.hb,
              pattern=r"ID:([ABH01]+)" if case.mode == "regex" else "")
    stream = case.stream
    reg_start = len(case.lead) + len(case.body)  # the registration's content ends here
    for cut in [*case.cuts, len(stream)]:
        prefix = stream[:cut]
        found = identify(prefix, case.ids, ps, settled=False)
        if isinstance(found, Identified):
            # taken early only as the id it really is, with nothing of it left over and
            # nothing of what follows swallowed
            assert case.configured and found.dtu_id == case.sent, (prefix, found)
            assert reg_start <= found.end <= min(cut, reg_start + case.consumed), (prefix, found)
        elif found is not None:
            assert not case.configured, (prefix, found)
        elif case.end and cut == len(stream) and not case.may_grow(stream):
            raise AssertionError(f"terminated registration {stream!r} left undecided")
    final = identify(stream, case.ids, ps, settled=True)
    if case.configured:
        assert final == Identified(case.sent, reg_start + case.consumed)
    else:
        assert not isinstance(final, Identified), final


@settings(max_examples=300, deadline=None)
@given(case=cases())
def test_a_quiet_gap_mid_registration_takes_only_an_exact_configured_id(case: Case) -> None:
    """The documented limit of the quiet gap: a DTU that pauses longer than it may be
    taken for an id that equals what it sent so far, never for anything else."""
    ps = port(case.mode, heartbeat=case.hb,
              pattern=r"ID:([ABH01]+)" if case.mode == "regex" else "")
    for cut in case.cuts:
        prefix = case.stream[:cut]
        found = identify(prefix, case.ids, ps, settled=True)
        if isinstance(found, Identified) and found.dtu_id != case.sent:
            # what it took, from some point of the heartbeats before it, is that id
            contents = [prefix[at:found.end] for at in case.starts]
            if case.mode != "hex":
                contents = [c.rstrip(b"\r\n\0") for c in contents]
            assert body_of(case.mode, found.dtu_id) in contents, (prefix, found)
