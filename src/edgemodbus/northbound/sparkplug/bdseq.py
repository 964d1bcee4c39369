"""bdSeq, the number that pairs an edge node's NDEATH with its NBIRTH (Sparkplug 3.0,
6.4.6): 0-255, one more for every MQTT session, kept in ``mqtt.sparkplug.bdSeqFile``
when given so that a restarted gateway does not reuse the number of the session whose
will the broker may still deliver; without the file it starts at 0 in each process."""

from __future__ import annotations

import logging
import os
from pathlib import Path

log = logging.getLogger("edgemodbus.sparkplug")


class BdSeqStore:
    """The next session's bdSeq, read from and written to an optional file (one decimal
    number; written to a temporary file, then renamed, so a crash leaves the old one)."""

    def __init__(self, path: str | None) -> None:
        self.path = Path(path) if path is not None else None

    def load(self) -> int:
        """The stored next bdSeq; 0 without a file, or (logged) when it is unreadable."""
        if self.path is None:
            return 0
        try:
            text = self.path.read_text().strip()
        except FileNotFoundError:
            return 0
        except OSError as exc:
            log.warning("%s: cannot read bdSeq (%s); starting at 0", self.path,
                        exc.strerror or exc)
            return 0
        if not text.isdigit() or int(text) > 255:
            log.warning("%s: %r is not a bdSeq (0-255); starting at 0", self.path, text[:20])
            return 0
        return int(text)

    def save(self, value: int) -> None:
        """Keep ``value`` as the next session's bdSeq; a failure is logged, not raised
        (publishing goes on, the number is then only kept in memory)."""
        if self.path is None:
            return
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        try:
            tmp.write_text(f"{value}\n")
            os.replace(tmp, self.path)
        except OSError as exc:
            log.warning("%s: cannot keep bdSeq %d: %s", self.path, value, exc.strerror or exc)
