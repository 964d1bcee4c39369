"""The fault checklist (docs/fault-checklist.md, "MQTT DTU links") for transport
mqtt-dtu (line/mqtt_dtu.py): oversize and storms on an uplink topic, malformed and huge
status messages, retained junk, the broker going away.  mosquitto is the broker, the
simulated DTUs (tests/mqtt_dtu_peer.py) and the flooding publisher
(tests/mqtt_flood.py) are paho clients in processes of their own."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from tests.conftest import SlaveFactory
from tests.integration.test_driver import Running
from tests.integration.test_mqtt_dtu import config, expected, hub_threads, values
from tests.mosquitto import Mosquitto, MqttProbe
from tests.mqtt_dtu_peer import MqttDtu
from tests.mqtt_flood import flood
from tests.waiting import wait_for

TICKS = os.sysconf("SC_CLK_TCK")


def thread_cpu(prefix: str) -> float:
    """CPU seconds used so far by this process's threads whose name starts with
    ``prefix`` (from /proc: user + system)."""
    total = 0
    for thread in threading.enumerate():
        if thread.name.startswith(prefix) and thread.native_id is not None:
            try:
                with open(f"/proc/self/task/{thread.native_id}/stat") as file:
                    fields = file.read().rsplit(")", 1)[1].split()
            except FileNotFoundError:  # ended meanwhile
                continue
            total += int(fields[11]) + int(fields[12])
    return total / TICKS


def rss() -> int:
    with open("/proc/self/status") as file:
        for line in file:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


def rate(drv: em.DriverModbusRtu, seconds: float) -> float:
    """The device's cycles per second over the next ``seconds``."""
    before, start = drv.stats()["cycles"], time.monotonic()
    time.sleep(seconds)  # pacing: a measuring window, not a wait for an event
    return float(drv.stats()["cycles"] - before) / (time.monotonic() - start)


def line_logs(caplog: pytest.LogCaptureFixture, since: int = 0) -> list[str]:
    return [r.getMessage() for r in caplog.records[since:] if r.name == "edgemodbus.line"
            and r.levelno >= logging.INFO]


def test_a_storm_and_an_oversize_message_on_one_uplink_leave_the_hubs_other_dtus_polled(
        broker: Mosquitto, slave_factory: SlaveFactory,
        caplog: pytest.LogCaptureFixture) -> None:
    """An impostor floods DTU s1's uplink topic (thousands of messages a second, then
    5 MB in one message): the bystander b1 on the same broker connection keeps its rate,
    memory and log lines stay bounded, the flooded DTU's drops are counted and it polls
    again afterwards."""
    caplog.set_level(logging.INFO, logger="edgemodbus.line")
    slave = slave_factory("rtu-over-tcp", units=(1, 2))
    with MqttDtu("b1", broker.port, slave.port), MqttDtu("s1", broker.port, slave.port), \
            ExitStack() as stack:
        by = stack.enter_context(Running(config(broker, "b1", 1)))
        hit = stack.enter_context(Running(config(broker, "s1", 2, readTimeout=300)))
        wait_for(lambda: values(by) == expected(1) and values(hit) == expected(2), 20,
                 "both DTUs' values")
        quiet = rate(by, 3.0)
        mark, memory = len(caplog.records), rss()
        hub_cpu = thread_cpu("edgemodbus-mqtt-dtu")
        result: dict[str, Any] = {}
        storm = threading.Thread(target=lambda: result.update(sent=flood(
            broker.port, "dtu/s1/up", b"\x02\x83\x02junk" * 4, rate=3000, seconds=4)))
        storm.start()
        try:
            time.sleep(0.5)  # pacing: the storm under way
            stormy = rate(by, 3.0)
        finally:
            storm.join()
        hub_cpu = thread_cpu("edgemodbus-mqtt-dtu") - hub_cpu
        assert result["sent"] >= 6000, result
        wait_for(lambda: hit.stats()["line"]["uplinkMessages"] >= result["sent"] // 2, 20,
                 "the storm's messages taken by the hub")
        # the bystander keeps its rate (a 100 ms cycle: 10 a second on a quiet machine)
        assert stormy >= 0.6 * quiet, (quiet, stormy)
        assert values(by) == expected(1)
        assert by.stats()["line"]["uplinkDroppedBytes"] == 0
        print(f"bystander cycles/s quiet {quiet:.1f}, storm {stormy:.1f}; hub CPU "
              f"{hub_cpu:.2f} s for {result['sent']} messages")

        # 5 MB in one message: cut to what the link's stream holds, counted
        dropped = hit.stats()["line"]["uplinkDroppedBytes"]
        with MqttProbe(broker.port, topics=("probe/none",)) as impostor:
            impostor.publish("dtu/s1/up", b"\x01" * (5 << 20), qos=1)
        wait_for(lambda: hit.stats()["line"]["uplinkDroppedBytes"] > dropped + (4 << 20),
                 20, "most of the 5 MB dropped")
        assert rss() - memory < 64 << 20, (memory, rss())
        # one line per kind and interval (line/log_limit.py), not one per message
        lines = line_logs(caplog, mark)
        assert len(lines) <= 20, lines[:30]
        assert any("uplink message dropped" in line or "uplink messages dropped" in line
                   for line in lines), lines
        cycles = hit.stats()["cycles"]
        wait_for(lambda: hit.stats()["cycles"] >= cycles + 3 and values(hit) == expected(2)
                 and values(by) == expected(1), 30, "the flooded DTU polled again")
    assert not hub_threads()


def test_retained_junk_and_a_stale_reply_on_the_uplink_are_never_taken_as_answers(
        broker: Mosquitto, slave_factory: SlaveFactory,
        caplog: pytest.LogCaptureFixture) -> None:
    """A retained message on an uplink topic comes at every subscribe, before any
    request: a well-formed reply with other values there must never become an item's
    value; it is dropped (a reply is never retained), counted, logged once."""
    from edgemodbus.protocol.rtu import frame

    caplog.set_level(logging.INFO, logger="edgemodbus.line")
    fake = frame(1, bytes([3, 4, 0x12, 0x34, 0x56, 0x78]))  # hr:3, hr:4 = 0x1234, 0x5678
    slave = slave_factory("rtu-over-tcp", units=(1,))
    seen: list[Any] = []
    cfg = config(broker, "r1", 1)
    with MqttDtu("r1", broker.port, slave.port):
        for _ in range(3):
            # published while no driver subscribes (the last one stopped: its hub
            # unsubscribed), so it reaches the next subscribe as a retained message; a
            # retained publish to a live subscription is a live message, which no one
            # can tell from the DTU's reply
            flood(broker.port, "dtu/r1/up", fake, rate=0, seconds=0, retain=True)
            with Running(cfg, address_updated_callback=lambda it: seen.append(it.value)) \
                    as drv:
                wait_for(lambda: values(drv) == expected(1), 30, "the slave's values")
        assert 0x1234 not in seen and 0x5678 not in seen, seen
    # logged through line/log_limit.py (a burst, then a summary per window): a line or
    # two per round at most, however many times the broker hands the message over
    lines = [m for m in line_logs(caplog) if "retained" in m]
    assert 1 <= len(lines) <= 6 and "'dtu/r1/up'" in lines[0], lines


@pytest.mark.parametrize("payload", [b"maybe", b"\xff\x00junk", b"x" * (2 << 20)],
                         ids=["word", "binary", "2MB"])
def test_a_status_that_is_neither_online_nor_offline_changes_nothing_and_is_logged_once(
        broker: Mosquitto, slave_factory: SlaveFactory, caplog: pytest.LogCaptureFixture,
        payload: bytes) -> None:
    caplog.set_level(logging.INFO, logger="edgemodbus.line")
    slave = slave_factory("rtu-over-tcp", units=(1,))
    with MqttDtu("m1", broker.port, slave.port), Running(config(broker, "m1", 1)) as drv, \
            MqttProbe(broker.port, topics=("probe/none",)) as other:
        wait_for(lambda: values(drv) == expected(1), 20, "values")
        memory = rss()
        for _ in range(5):
            other.publish("dtu/m1/status", payload)
        wait_for(lambda: sum("dtu/m1/status" in m for m in line_logs(caplog)) >= 1, 20,
                 "the status logged")
        cycles = drv.stats()["cycles"]
        wait_for(lambda: drv.stats()["cycles"] >= cycles + 5, 20, "polling goes on")
        assert drv.device_driver_status is em.DeviceDriverStatus.RUNNING
        lines = [m for m in line_logs(caplog) if "status" in m and "m1" in m]
        assert 1 <= len(lines) <= 4, lines  # a burst of 3, then a summary (log_limit.py)
        assert "neither" in lines[0] and len(lines[0]) < 300, lines[0]
        assert rss() - memory < 32 << 20
        # an offline after it still takes the DTU down, online brings it back
        other.publish("dtu/m1/status", b"offline")
        wait_for(lambda: drv.device_driver_status is em.DeviceDriverStatus.RECONNECTING,
                 20, "offline")
        other.publish("dtu/m1/status", payload)  # still nothing: stays offline
        other.publish("dtu/m1/status", b"online")
        wait_for(lambda: drv.device_driver_status is em.DeviceDriverStatus.RUNNING, 20,
                 "online again")


def test_the_broker_going_away_says_why_without_a_spin_and_polling_resumes(
        broker: Mosquitto, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp", units=(1,))
    with MqttDtu("g1", broker.port, slave.port) as dtu, \
            Running(config(broker, "g1", 1)) as drv:
        wait_for(lambda: values(drv) == expected(1), 20, "values")
        broker.stop()
        where = f"mqtt://127.0.0.1:{broker.port}"
        wait_for(lambda: drv.device_driver_status is em.DeviceDriverStatus.RECONNECTING
                 and f"cannot connect to the broker {where}: " in
                 (drv.address_items[0].error_reason or ""), 20, "the reason")
        reason = drv.address_items[0].error_reason or ""
        assert "refused" in reason, reason
        cpu = thread_cpu("edgemodbus-mqtt-dtu") + thread_cpu("edgemodbus-line")
        time.sleep(3.0)  # pacing: a measuring window: the hub and the line while the broker is away
        used = thread_cpu("edgemodbus-mqtt-dtu") + thread_cpu("edgemodbus-line") - cpu
        assert used < 0.15, used  # below 5 % of a core
        broker.restart()
        dtu.kill()  # its client lost the old broker (nothing to say goodbye to)
        dtu.start()
        wait_for(lambda: drv.device_driver_status is em.DeviceDriverStatus.RUNNING
                 and values(drv) == expected(1), 30, "running again")


class Child:
    """tests/mqtt_dtu_proc.py in a child process: one command, one JSON answer."""

    def __init__(self, devices: list[dict[str, Any]]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tests.mqtt_dtu_proc", json.dumps(devices)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
            cwd=Path(__file__).resolve().parents[2])
        assert self.proc.stdout is not None and self.proc.stdin is not None
        self.out, self.inp = self.proc.stdout, self.proc.stdin
        assert self.out.readline().strip() == "READY"

    def ask(self, command: str) -> Any:
        self.inp.write(command + "\n")
        self.inp.flush()
        return json.loads(self.out.readline())

    def close(self) -> None:
        self.inp.close()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.out.close()


def device(broker: Mosquitto, dtu: str, slave: int) -> dict[str, Any]:
    cfg = config(broker, dtu, slave)
    return {"organization": {"deviceCode": dtu},
            "communication": cfg.communication.model_dump(by_alias=True, mode="json"),
            "addressList": [{"name": "a", "address": "hr:3", "deviceDataType": "UInt16"},
                            {"name": "b", "address": "hr:4", "deviceDataType": "UInt16"}]}


def test_no_fd_for_a_dtus_socketpair_is_told_on_its_line_without_a_spin(
        broker: Mosquitto, slave_factory: SlaveFactory) -> None:
    """EMFILE at socket.socketpair() when a DTU comes online: its devices say why, the
    line retries at its reconnect interval (no spin), the other DTU on the broker keeps
    polling, and the DTU is polled again once fds are free."""
    slave = slave_factory("rtu-over-tcp", units=(1, 2))
    with MqttDtu("e1", broker.port, slave.port), MqttDtu("e2", broker.port, slave.port), \
            MqttProbe(broker.port, topics=("probe/none",)) as other:
        child = Child([device(broker, "e1", 1), device(broker, "e2", 2)])
        try:
            def state(dtu: str) -> dict[str, Any]:
                return child.ask("stats")["devices"][dtu]  # type: ignore[no-any-return]

            wait_for(lambda: [it["value"] for it in state("e1")["items"]] == expected(1)
                     and [it["value"] for it in state("e2")["items"]] == expected(2), 20,
                     "both DTUs' values")
            other.publish("dtu/e2/status", b"offline")  # its link (and its fds) gone
            wait_for(lambda: state("e2")["status"] == "Reconnecting", 20, "e2 offline")
            assert child.ask("fill")["held"] > 0
            other.publish("dtu/e2/status", b"online")  # a new socketpair: no fd for it
            wait_for(lambda: "Too many open files" in (
                state("e2")["items"][0]["errorReason"] or ""), 20, "EMFILE told")
            reason = state("e2")["items"][0]["errorReason"]
            assert "mqtt-dtu e2@127.0.0.1" in reason and "cannot open the line" in reason
            first = child.ask("stats")
            time.sleep(3.0)  # pacing: a measuring window while no fd is left
            last = child.ask("stats")
            spent = {name: used - first["cpu"].get(name, 0.0)
                     for name, used in last["cpu"].items()
                     if name.startswith(("edgemodbus-line", "edgemodbus-mqtt-dtu"))}
            assert spent and max(spent.values()) < 0.15, spent  # below 5 % of a core
            failures = (last["devices"]["e2"]["connectFailures"]
                        - first["devices"]["e2"]["connectFailures"])
            assert 1 <= failures <= 20, failures  # its reconnect interval, not a spin
            polled = last["devices"]["e1"]["cycles"] - first["devices"]["e1"]["cycles"]
            assert polled >= 15, polled  # e1 kept its 100 ms cycle (30 in 3 s when quiet)
            assert last["devices"]["e1"]["status"] == "Running"
            child.ask("free")
            wait_for(lambda: state("e2")["status"] == "Running"
                     and [it["value"] for it in state("e2")["items"]] == expected(2), 20,
                     "e2 polled again")
        finally:
            child.close()
