"""mqtt-dtu drivers in a process of their own, for tests that must not touch the pytest
process (its open files used up, say).

    python -m tests.mqtt_dtu_proc DEVICES_JSON

Starts one DriverModbusRtu per device configuration in the JSON list and prints
``READY``.  Commands on stdin, each answered with one JSON line:

- ``stats``: per device its status, items (status, value, errorReason) and counters
  (cycles, the line's connectFailures), the CPU seconds of the threads by name (read
  from each thread's CPU clock: no file is opened, so it works with no fd left), and
  the log records of the ``edgemodbus`` logger (tests/listener_proc.py's counting);
- ``fill``: opens /dev/null until the open files limit (its soft limit lowered to 256
  first) is reached: ``{"held": n}``;
- ``free``: closes them again: ``{"held": 0}``.

At EOF it stops the drivers and exits 0.
"""

from __future__ import annotations

import json
import logging
import os
import resource
import sys
import threading
import time
from typing import Any

import edgemodbus as em
from tests.listener_proc import Records


def thread_cpu() -> dict[str, float]:
    """CPU seconds of each live thread, by name (threads of one name summed)."""
    found: dict[str, float] = {}
    for thread in threading.enumerate():
        if thread.ident is None:
            continue
        try:
            clock = time.pthread_getcpuclockid(thread.ident)
            used = time.clock_gettime(clock)
        except (OSError, ProcessLookupError):  # ended meanwhile
            continue
        found[thread.name] = found.get(thread.name, 0.0) + used
    return found


def main() -> int:
    records = Records()
    top = logging.getLogger("edgemodbus")
    top.setLevel(logging.INFO)
    top.addHandler(records)
    top.propagate = False
    drivers: list[tuple[em.DeviceConfig, em.DriverModbusRtu]] = []
    for data in json.loads(sys.argv[1]):
        cfg = em.load_device_config(data)
        drv = em.DriverModbusRtu()
        if not drv.start_device(cfg.organization, cfg.communication, cfg.address_list):
            return 1
        drivers.append((cfg, drv))
    held: list[int] = []
    try:
        print("READY", flush=True)
        for line in sys.stdin:
            command = line.strip()
            answer: dict[str, Any]
            if command == "fill":
                hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
                resource.setrlimit(resource.RLIMIT_NOFILE, (min(256, hard), hard))
                try:
                    while True:
                        held.append(os.open(os.devnull, os.O_RDONLY))
                except OSError:
                    pass
                answer = {"held": len(held)}
            elif command == "free":
                while held:
                    os.close(held.pop())
                answer = {"held": 0}
            elif command == "stats":
                devices = {}
                for cfg, drv in drivers:
                    stats = drv.stats()
                    devices[cfg.organization.device_code] = {
                        "status": drv.device_driver_status.value,
                        "cycles": stats["cycles"],
                        "connectFailures": stats["line"]["connectFailures"],
                        "items": [{"status": it.status.value, "value": it.value,
                                   "errorReason": it.error_reason}
                                  for it in drv.address_items]}
                with records.lock_:
                    logs = {"byLevel": dict(records.by_level),
                            "first": list(records.first)}
                answer = {"devices": devices, "cpu": thread_cpu(), "logs": logs}
            else:
                answer = {"error": f"unknown command {command!r}"}
            print(json.dumps(answer), flush=True)
    finally:
        while held:
            os.close(held.pop())
        for _, drv in drivers:
            drv.stop_device()
    return 0


if __name__ == "__main__":
    sys.exit(main())
