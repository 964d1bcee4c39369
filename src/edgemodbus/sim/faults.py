"""The fault knobs of one simulated slave: how it misbehaves on the wire."""

from __future__ import annotations

import dataclasses

from ..datatypes import Area

ExceptionRange = tuple[Area, int, int, int]
"""(area, start, end exclusive, exception code) for :attr:`Faults.exception_ranges`."""


@dataclasses.dataclass(slots=True)
class Faults:
    """Fault knobs of one slave. Assign fields at any time from any thread (each
    assignment is atomic; use :meth:`Slave.set_faults` to change several together).

    "every N" knobs count the replies they could apply to since that knob was last
    changed and act on the Nth, 2Nth, ...; 0 disables. Each time a knob acts it is
    counted in ``Slave.stats()["faults"][knob name]``.
    """

    silent: bool = False
    """Never answer (the request is not executed either)."""
    drop_every: int = 0
    """Execute the request but do not send every Nth reply."""
    delay: float = 0.0
    """Seconds before a reply goes out (may exceed the master's timeout: a late reply)."""
    delay_every: int = 0
    """Apply ``delay`` to every Nth reply only (0: to every reply)."""
    corrupt_crc_every: int = 0
    """Flip a bit of the CRC of every Nth reply."""
    corrupt_data_every: int = 0
    """Flip a bit of the last data byte of every Nth reply, keeping the original CRC."""
    wrong_byte_count_every: int = 0
    """Every Nth read reply carries one data unit (register or bit byte) too few (or,
    for a single one, too many), with a consistent byte count and a valid CRC."""
    answer_as: int | None = None
    """Reply with this slave address instead of our own (valid CRC)."""
    patch: dict[int, int] = dataclasses.field(default_factory=dict)
    """{index: byte} written into every ``patch_every``-th reply frame before its CRC is
    computed (valid CRC): 0 is the slave address, 1 the function code, 2 a read reply's
    byte count.  Indices past the frame are ignored.  Assign a new dict."""
    patch_every: int = 0
    """See ``patch`` (0: off)."""
    raw_reply: bytes = b""
    """Bytes sent verbatim, instead of the reply, to every ``raw_reply_every``-th
    request (a crafted or oversized frame)."""
    raw_reply_every: int = 0
    """See ``raw_reply`` (0: off)."""
    exception_ranges: list[ExceptionRange] = dataclasses.field(default_factory=list)
    """Requests touching [start, end) of an area get that exception code. Assign a new
    list rather than mutating this one from another thread."""
    close_every: int = 0
    """Close the TCP connection instead of answering every Nth request (on a pty the
    request is just not answered)."""
    cut_every: int = 0
    """Send the first half of every Nth reply, then close the TCP connection: with a
    reset (RST) if ``cut_with_reset``, else an orderly close (FIN).  On a pty only the
    half frame goes out."""
    cut_with_reset: bool = True
    """See ``cut_every``."""
    hold_reply_every: int = 0
    """Hold back every Nth reply and send it in one write with the next one (a DTU that
    buffers a late reply: two frames in one TCP segment)."""
    trailing_garbage: bytes = b""
    """Bytes sent right after each good frame."""
    noise_before: bytes = b""
    """Bytes sent right before each frame."""
    split_reply: int = 0
    """Send each reply in this many chunks, ``split_pause`` seconds apart (<= 1: off)."""
    split_pause: float = 0.005
    """Seconds between the chunks of a split reply."""
    byte_delay: float = 0.0
    """Send replies one byte at a time, this many seconds apart."""
    truncate_every: int = 0
    """Send only the first half of every Nth reply, then nothing."""
    echo_request: bool = False
    """Send the request bytes back before the reply (an RS-485 adapter echo)."""
    random_reply_count: int = 0
    """Answer the next N requests with random bytes (counts down to 0)."""
    exception_for_other_function: bool = False
    """Answer every request with an exception whose function code is not the request's
    plus 0x80."""
    answer_broadcast: bool = False
    """Answer broadcast writes (a real slave must not, Serial Line 2.1)."""
    refused_functions: frozenset[int] = frozenset()
    """Function codes this slave does not implement: exception 01 (a device without
    FC16 or FC22, say)."""

    def clear(self) -> None:
        """Back to a well-behaved slave."""
        for f in dataclasses.fields(self):
            if f.default_factory is not dataclasses.MISSING:
                setattr(self, f.name, f.default_factory())
            else:
                setattr(self, f.name, f.default)
