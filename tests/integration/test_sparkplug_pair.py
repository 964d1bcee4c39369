"""Sparkplug B with a redundant pair (``mqtt.sparkplug.sharedByPair``, docs/deploy.md "A
redundant pair"): the two gateway processes are one edge node; only the leader is
connected as it; bdSeq is kept in the pair's Redis, so the new leader's NBIRTH carries the
number after the old leader's and a host that applies the spec's rule (an NDEATH ends
the node's session only with the bdSeq of its last NBIRTH) ignores the old leader's late
NDEATH.  Real mosquitto, redis-server and pymodbus slave; payloads read by
tests/sparkplug_wire.py (not our encoder)."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from tests.gateway_proc import GatewayProcess, device_file, write_json
from tests.mosquitto import Mosquitto, MqttProbe, Received
from tests.peers import PymodbusSlave
from tests.redis_server import RedisServer, redis_binary
from tests.sparkplug_wire import decode
from tests.waiting import wait_for

G, NODE = "plant1", "pair"
NODE_TOPIC = f"spBv1.0/{G}/{{}}/{NODE}"
NBIRTH, NDEATH = NODE_TOPIC.format("NBIRTH"), NODE_TOPIC.format("NDEATH")
LEASE_MS, KEEPALIVE_S = 2000, 5

try:
    redis_binary()
    import redis
except Exception as exc:  # pragma: no cover - the Makefile installs both
    pytest.skip(f"no redis-server or redis client: {exc}", allow_module_level=True)


def bd_seq(message: Received) -> int:
    return int(decode(message.payload).by_name()["bdSeq"].value)


class Host:
    """A Sparkplug host's view of one edge node, by the spec's rule: NBIRTH starts a
    session (online, its bdSeq); an NDEATH ends it only if it carries that bdSeq, any
    other NDEATH is a late one of an older session and is ignored."""

    def __init__(self) -> None:
        self.online = False
        self.bd_seq: int | None = None
        self.ignored: list[int] = []

    def see(self, message: Received) -> None:
        if message.topic == NBIRTH:
            self.online, self.bd_seq = True, bd_seq(message)
        elif message.topic == NDEATH:
            if bd_seq(message) == self.bd_seq:
                self.online = False
            else:
                self.ignored.append(bd_seq(message))


def test_the_pair_is_one_edge_node_and_the_new_leader_births_with_a_higher_bdseq(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with RedisServer(tmp_path / "redis") as rds, Mosquitto(tmp_path / "mqtt") as broker, \
            PymodbusSlave("rtu-over-tcp", units=(1,)) as slave, \
            MqttProbe(broker.port, [f"spBv1.0/{G}/#"]) as probe:
        conf = tmp_path / "conf"
        conf.mkdir()
        write_json(conf / "gateway.json", {
            "gatewayId": NODE,
            "mqtt": {"mode": "sparkplug", "port": broker.port, "keepalive": KEEPALIVE_S,
                     "reconnectMin": 100, "reconnectMax": 500,
                     "sparkplug": {"groupId": G, "sharedByPair": True}},
            "fleet": {"lease": {"url": rds.url, "keyPrefix": "sp:pair:",
                                "leaseMs": LEASE_MS}}})
        write_json(conf / "plc.json", device_file(slave.port, 1, "plc", read_cycle=100))

        def start(name: str) -> GatewayProcess:
            monkeypatch.setenv("EDGEMODBUS_INSTANCE", name)
            return GatewayProcess(conf, tmp_path / f"{name}-{time.monotonic_ns()}.log")

        with start("a") as gw_a, start("b") as gw_b:
            # a leads (it started first; b may win the race: then the roles swap)
            first = probe.wait_for(NBIRTH, timeout=30)
            n = bd_seq(first)
            leader, standby = (gw_a, gw_b) if "lease: leader" in gw_a.log else (gw_b, gw_a)
            other = "b" if leader is gw_a else "a"
            standby.wait_log(r"pair: standby until", timeout=30)
            probe.wait_for(f"spBv1.0/{G}/DBIRTH/{NODE}/plc", timeout=30)
            assert f"edgemodbus-{NODE}-{other}" not in broker.log_text  # never connected
            assert len(probe.on(NBIRTH)) == 1

            leader.signal(signal.SIGKILL)  # the broker sends its will at once
            leader.wait(30)
            death = probe.wait_for(NDEATH, timeout=30)
            assert bd_seq(death) == n  # the will the old leader registered
            mark = probe.mark()
            second = probe.wait_for(NBIRTH, timeout=30, after=mark)
            assert bd_seq(second) == (n + 1) % 256  # the standby's, above the old one's
            probe.wait_for(f"spBv1.0/{G}/DBIRTH/{NODE}/plc", timeout=30, after=mark)

            # the old leader again, as the standby; then the new leader paused: the
            # broker sends its will only after 1.5 keepalives, once the other leads
            with start("c") as gw_c:
                gw_c.wait_log(r"pair: standby until", timeout=30)
                standby.signal(signal.SIGSTOP)
                try:
                    mark = probe.mark()
                    third = probe.wait_for(NBIRTH, timeout=60, after=mark)
                    assert bd_seq(third) == (n + 2) % 256
                    late = probe.wait_for(NDEATH, timeout=60, after=mark)
                    assert bd_seq(late) == (n + 1) % 256  # the paused one's will, late
                finally:
                    standby.signal(signal.SIGCONT)
                standby.wait_log(r"lease: no longer the leader", timeout=30)
                wait_for(lambda: "Sparkplug: edge node" in standby.log and (
                    "standby, disconnected" in standby.log
                    or "no longer the pair's leader" in standby.log), timeout=30,
                    what="the woken leader leaving the node")
                probe.wait_for(f"spBv1.0/{G}/DBIRTH/{NODE}/plc", timeout=30, after=mark)
                host = Host()
                for message in probe.messages():
                    host.see(message)
                assert host.online and host.bd_seq == (n + 2) % 256, host.__dict__
                assert (n + 1) % 256 in host.ignored  # the late NDEATH
                # every NBIRTH had a new bdSeq: no session of the woken one
                assert [bd_seq(m) for m in probe.on(NBIRTH)] == \
                    [n, (n + 1) % 256, (n + 2) % 256]
                with redis.Redis.from_url(rds.url) as client:
                    assert int(client.get("sp:pair:bdseq")) == (n + 3) % 256
