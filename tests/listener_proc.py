"""A listen-mode driver in a process of its own, for tests that must not touch the
pytest process (a low open-files limit, say).

    python -m tests.listener_proc DEVICE_JSON [--nofile N]

Starts one DriverModbusRtu from DEVICE_JSON (a device configuration: organization,
communication, addressList), then lowers the soft RLIMIT_NOFILE to N (its hard limit
stays) and prints ``{"port": P}``.  Each line ``stats`` on stdin is answered with one
JSON line: the listener's counters, the log records of the ``edgemodbus`` logger so far
(count by level, the messages of the first 20 and the longest), the items' statuses and
values.  At EOF it stops the driver and exits 0.
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import sys
import threading
from typing import Any

import edgemodbus as em


class Records(logging.Handler):
    """The log records of the ``edgemodbus`` logger, counted (and a few kept)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lock_ = threading.Lock()
        self.by_level: dict[str, int] = {}
        self.first: list[str] = []
        self.longest = 0

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        with self.lock_:
            self.by_level[record.levelname] = self.by_level.get(record.levelname, 0) + 1
            self.longest = max(self.longest, len(text))
            if len(self.first) < 20:
                self.first.append(f"{record.levelname} {record.name}: {text[:300]}")


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("device")
    parser.add_argument("--nofile", type=int, default=0)
    args = parser.parse_args()
    records = Records()
    top = logging.getLogger("edgemodbus")
    top.setLevel(logging.INFO)
    top.addHandler(records)
    top.propagate = False
    cfg = em.load_device_config(json.loads(args.device))
    drv = em.DriverModbusRtu()
    if not drv.start_device(cfg.organization, cfg.communication, cfg.address_list):
        return 1
    try:
        if args.nofile:
            hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
            resource.setrlimit(resource.RLIMIT_NOFILE, (args.nofile, hard))
        port = cfg.communication.effective_listen_port
        print(json.dumps({"port": port}), flush=True)
        for line in sys.stdin:
            if line.strip() != "stats":
                continue
            stats: dict[str, Any] = em.DriverModbusRtu.dtu_registry.stats()
            with records.lock_:
                logs = {"byLevel": dict(records.by_level), "first": list(records.first),
                        "longest": records.longest}
            items = [{"name": it.name, "status": it.status.value, "value": it.value,
                      "errorReason": it.error_reason} for it in cfg.address_list]
            print(json.dumps({"stats": stats.get(f"127.0.0.1:{port}", {}), "logs": logs,
                              "items": items}), flush=True)
    finally:
        drv.stop_device()
    return 0


if __name__ == "__main__":
    sys.exit(main())
