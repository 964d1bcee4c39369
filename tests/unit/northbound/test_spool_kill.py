"""``kill -9`` of a process in the middle of appending and acknowledging: every message
SQLite acknowledged (append returned) and not deleted is in the file afterwards, in
order, with no gap and no duplicate; every deletion that committed stays deleted.

The writer (tests/spool_writer.py) prints after each commit what it appended and
acknowledged; it is killed with SIGKILL at a different point in each round, and the
next round continues in the same file (after the survivors were replayed and
acknowledged), so WAL recovery after a kill is exercised too.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from edgemodbus.northbound.mqtt.spool import Spool

ROOT = Path(__file__).resolve().parents[3]


def _run_and_kill(path: Path, first: int, lines: int) -> tuple[int, int]:
    """Start the writer at ``first``, read ``lines`` progress lines, SIGKILL it; the last
    (appended, acked) it printed."""
    proc = subprocess.Popen([sys.executable, "-m", "tests.spool_writer", str(path),
                             str(first)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout is not None
    appended = acked = 0
    try:
        for _ in range(lines):
            line = proc.stdout.readline()
            assert line, f"the writer stopped early (exit {proc.poll()})"
            _, a, _, k = line.split()
            appended, acked = int(a), int(k)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    return appended, acked


def test_kill_9_loses_nothing_acknowledged(tmp_path: Path) -> None:
    path = tmp_path / "spool.db"
    first = 1
    for lines in (7, 60, 181, 333):
        appended, acked = _run_and_kill(path, first, lines)
        with Spool(path, max_bytes=1 << 40, max_age_s=1e9) as spool:
            stored = spool.next_batch(1_000_000)
            assert spool.ack(m.id for m in stored) == len(stored)  # replayed: PUBACKed
        numbers = [int(m.payload) for m in stored]
        assert numbers, "nothing stored"
        lo, hi = numbers[0], numbers[-1]
        assert numbers == list(range(lo, hi + 1)), "a gap or a duplicate"
        assert hi >= appended, f"message {appended} was acknowledged by SQLite, then lost"
        assert lo - 1 >= acked, f"deleted messages {acked} and before came back"
        assert lo <= hi
        # ids grow with the numbers: the order of appending, hence per device too
        assert [m.id for m in stored] == sorted(m.id for m in stored)
        assert all(m.device == f"d{int(m.payload) % 4}" for m in stored)
        first = hi + 1
