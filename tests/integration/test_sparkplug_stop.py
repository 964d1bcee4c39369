"""A stopped Sparkplug publisher holds no socket, even while something still refers to
it (a gateway keeps the old one until its reload is done; a test's local variable):
paho's loop_start() opens a wake-up socket pair that only the client's __del__ closed,
so two sockets stayed open per stopped publisher (found by the leak check of a
dial-in DTU test on the loop engine, where the driver kept the publisher referenced)."""

from __future__ import annotations

import os

from edgemodbus.northbound.sparkplug.publisher import SparkplugPublisher
from tests.mosquitto import Mosquitto


def sockets() -> set[str]:
    found = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:"):
            found.add(target)
    return found


def test_a_stopped_publisher_still_referenced_holds_no_socket(broker: Mosquitto) -> None:
    before = sockets()
    kept = []
    for round_ in range(3):
        pub = SparkplugPublisher({"mode": "sparkplug", "port": broker.port,
                                  "sparkplug": {"groupId": f"stop{round_}"}},
                                 gateway_id="n1")
        pub.start()
        assert pub.wait_connected(10)
        pub.stop()
        kept.append(pub)  # referenced: no __del__ runs
    assert sockets() - before == set()
    assert len(kept) == 3
