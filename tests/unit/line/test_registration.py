"""When a DTU's registration is complete (edgemodbus.line.registration.identify, a pure
function): ids that are prefixes of others, registrations split over TCP segments,
terminators, quiet gaps, and the bytes that follow a registration."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from hypothesis import given, settings
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


def test_a_peer_that_never_registers_is_unknown_after_a_bounded_buffer() -> None:
    ps = port("regex", pattern=r"ID:(\d+)")
    assert identify(b"x" * (ps.max_bytes - 1), ["1"], ps, settled=False) is None
    assert identify(b"x" * ps.max_bytes, ["1"], ps, settled=False) == (
        f"no registration in the first {ps.max_bytes} bytes")


# --- the class: random id sets with prefixes, random segmentation -----------------------

@dataclass(frozen=True)
class Case:
    mode: str
    ids: list[str]
    sent: str  # the id the DTU sends
    lead: bytes  # heartbeats (and line ends) before the registration
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


@st.composite
def cases(draw: st.DrawFn) -> Case:
    mode = draw(st.sampled_from(["text", "hex", "regex"]))
    if mode == "hex":
        id_st = st.lists(st.sampled_from(["01", "02", "0D", "00"]), min_size=1,
                         max_size=4).map("".join)
    else:
        id_st = st.text(alphabet="AB01", min_size=1, max_size=4)
    ids = draw(st.lists(id_st, min_size=1, max_size=6, unique=True))
    # the sender: a configured id, or one that is not (often a prefix or an extension)
    sent = draw(st.one_of(st.sampled_from(ids), id_st))
    body = bytes.fromhex(sent) if mode == "hex" else sent.encode()
    if mode == "regex":
        body = b"ID:" + body
    lead = draw(st.sampled_from([b"", HEARTBEAT] + ([] if mode == "hex" else [b"\r\n"])))
    ends: list[tuple[bytes, int]] = [(b"", 0), (HEARTBEAT, 0)]
    if mode != "hex":
        ends += [(b"\r\n", 2), (b"\0", 1), (b"\r", 1), (WRAPPED, 0)]
    end, consumed = draw(st.sampled_from(ends))
    data = draw(st.sampled_from([b"", b"\x01\x03\x02\x00\x07", HEARTBEAT, WRAPPED])) \
        if end else b""
    total = len(lead) + len(body) + len(end) + len(data)
    cuts = draw(st.lists(st.integers(1, total), max_size=6))
    return Case(mode, ids, sent, lead, body, end, consumed, data, sorted(set(cuts)))


@settings(max_examples=600, deadline=None)
@given(case=cases())
def test_a_registration_names_its_own_id_however_it_is_split(case: Case) -> None:
    ps = port(case.mode, heartbeat=HEARTBEAT,
              pattern=r"ID:([AB01]+)" if case.mode == "regex" else "")
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
        elif case.end and cut == len(stream):
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
    ps = port(case.mode, heartbeat=HEARTBEAT,
              pattern=r"ID:([AB01]+)" if case.mode == "regex" else "")
    for cut in case.cuts:
        prefix = case.stream[:cut]
        found = identify(prefix, case.ids, ps, settled=True)
        if isinstance(found, Identified) and found.dtu_id != case.sent:
            content = prefix[len(case.lead):found.end]
            if case.mode == "regex":
                assert content.rstrip(b"\r\n\0") == b"ID:" + found.dtu_id.encode()
            elif case.mode == "hex":
                assert content == bytes.fromhex(found.dtu_id)
            else:
                assert content.rstrip(b"\r\n\0") == found.dtu_id.encode()
