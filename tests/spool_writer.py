"""A process that appends numbered messages to a spool until it is killed, for the
``kill -9`` test (tests/unit/northbound/test_spool_kill.py).

    python -m tests.spool_writer PATH FIRST

Appends batches of :data:`BATCH` messages numbered from FIRST on (device ``d{n % 4}``,
payload ``str(n)``), one transaction each, and acknowledges (deletes) what lies more
than :data:`WINDOW` behind, as a sender would after PUBACKs.  After every commit it
prints ``appended N acked A``: every message up to N was committed, every one up to A
was deleted.  It never stops by itself.
"""

from __future__ import annotations

import sys

from edgemodbus.northbound.mqtt.spool import Message, Spool

BATCH = 50
WINDOW = 1000


def main() -> None:
    path, first = sys.argv[1], int(sys.argv[2])
    spool = Spool(path, max_bytes=1 << 40, max_age_s=1e9)
    ids: dict[int, int] = {}  # number -> spool id
    acked = first - 1
    n = first
    while True:
        numbers = range(n, n + BATCH)
        got = spool.append([Message(f"d{k % 4}", f"t/d{k % 4}", str(k).encode(), 1, False)
                            for k in numbers])
        ids.update(zip(numbers, got, strict=True))
        n += BATCH
        print(f"appended {n - 1} acked {acked}", flush=True)
        if n - 1 - acked > WINDOW + BATCH:
            upto = n - 1 - WINDOW
            spool.ack([ids.pop(k) for k in range(acked + 1, upto + 1)])
            acked = upto
            print(f"appended {n - 1} acked {acked}", flush=True)


if __name__ == "__main__":
    main()
