"""What a slave hands the loop to do on a line, and when: bytes to send, a close, or a
reset, each some seconds from now; and a reply spread over time (split, byte by byte)."""

from __future__ import annotations


class _Reset:
    """Action: reset the TCP connection (RST instead of FIN)."""


_RESET = _Reset()

# (seconds from now, bytes to send, None: close the connection, or _RESET)
_Action = tuple[float, "bytes | _Reset | None"]


def _spread(
    frame: bytes, start: float, split: int, pause: float, byte_delay: float
) -> list[_Action]:
    """Send ``frame`` from ``start`` seconds on: whole, in ``split`` chunks ``pause``
    seconds apart, or one byte every ``byte_delay`` seconds (which wins)."""
    if not frame:
        return []
    if byte_delay > 0:
        return [(start + i * byte_delay, frame[i : i + 1]) for i in range(len(frame))]
    if split > 1:
        size = -(-len(frame) // min(split, len(frame)))
        return [
            (start + k * max(0.0, pause), frame[off : off + size])
            for k, off in enumerate(range(0, len(frame), size))
        ]
    return [(start, frame)]
