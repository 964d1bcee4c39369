"""A redundant pair (gateway/lease.py, gateway/pair.py, docs/deploy.md "Redundant
pair"): two gateway processes with one config folder and a real redis-server poll one
pymodbus slave over RTU over TCP.  Only the leader polls (the slave counts requests per
connection); ``kill -STOP`` the leader: the standby polls within the lease time plus a
retry and two cycles; ``kill -CONT``: the old leader finds its lease gone and sends
nothing more on its connection, which it closes."""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.gateway_proc import GatewayProcess, device_file, write_json
from tests.lease_switch import Switch
from tests.mosquitto import Mosquitto, MqttProbe, Received
from tests.peers import PymodbusSlave
from tests.redis_server import RedisServer, redis_binary
from tests.waiting import wait_for

LEASE_MS = 2000
CYCLE_MS = 100
LOAD_SLACK = 3.0  # s: a loaded 2-core machine (start of a Python thread, a connect)

try:
    redis_binary()
    import redis  # noqa: F401
except Exception as exc:  # pragma: no cover - the Makefile installs both
    pytest.skip(f"no redis-server or redis client: {exc}", allow_module_level=True)


def test_the_redis_engine_hands_the_lease_to_one_token_at_a_time(tmp_path: Path) -> None:
    """RedisEngine on a real redis-server: NX acquire with a growing fencing token,
    renewal by the holder only, release by the holder only, expiry by PX."""
    from edgemodbus.gateway.lease import RedisEngine

    with RedisServer(tmp_path / "redis") as rds:
        one = RedisEngine(rds.url, "t:", timeout=2.0)
        two = RedisEngine(rds.url, "t:", timeout=2.0)
        try:
            assert one.acquire("a", 60_000) == 1
            assert two.acquire("b", 60_000) is None
            assert one.renew("a", 60_000) and not two.renew("b", 60_000)
            two.release("b")  # not the holder: nothing happens
            assert two.acquire("b", 60_000) is None
            one.release("a")
            assert two.acquire("b", 200) == 2  # a new leader, a higher token
            assert 0 < one.client.pttl("t:leader") <= 200
            wait_for(lambda: one.client.get("t:leader") is None, timeout=10,
                     what="the lease to expire in Redis")
            assert not two.renew("b", 60_000)  # expired: not extended
            assert one.acquire("a", 60_000) == 3
        finally:
            one.close()
            two.close()


def polling(slave: PymodbusSlave) -> dict[str, int]:
    """The slave's connections that sent at least one request: name -> requests."""
    per = slave.stats()["perConnection"]
    return {name: n for name, n in per.items() if n > 0}


def write(probe: MqttProbe, value: int, request: str) -> None:
    """A per-item MQTT write of ``value`` to item t0 of device plc, with an id."""
    probe.publish("edgemodbus/plc/set/t0", json.dumps({"value": value, "id": request}))


def reply_ok(probe: MqttProbe, request: str) -> Callable[[Received], bool]:
    return lambda m: m.json().get("id") == request and m.json().get("ok") is True


def test_one_leader_polls_and_the_standby_takes_over_a_paused_one(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two gateway processes (instances a and b of one config folder), a per-item MQTT
    publisher each, one pymodbus slave that counts requests, writes and their times per
    connection.  ``kill -STOP`` the leader a: b polls within the lease time plus two
    cycles; a write sent through MQTT meanwhile reaches the slave once, through b;
    ``kill -CONT``: a finds its lease gone, sends nothing more (none of its requests came
    after its lease's end in Redis, all of them before b's first) and closes its
    connection; the write it finds waiting when it wakes is not sent again."""
    import redis

    with RedisServer(tmp_path / "redis") as rds, Mosquitto(tmp_path / "mqtt") as broker, \
            PymodbusSlave("rtu-over-tcp", units=(1,)) as slave, \
            MqttProbe(broker.port, ["edgemodbus/plc/#"]) as probe:
        conf = tmp_path / "conf"
        conf.mkdir()
        write_json(conf / "gateway.json", {
            "gatewayId": "pair", "mqtt": {"port": broker.port, "reconnectMin": 100},
            "fleet": {"lease": {"url": rds.url, "keyPrefix": "test:pair:",
                                "leaseMs": LEASE_MS}}})
        plc = device_file(slave.port, 1, "plc", read_cycle=CYCLE_MS)
        plc["communication"]["readTimeout"] = 300  # a write may take 0.6 s: < the lease
        write_json(conf / "plc.json", plc)
        monkeypatch.setenv("EDGEMODBUS_INSTANCE", "a")
        with GatewayProcess(conf, tmp_path / "a.log") as gw_a:
            gw_a.wait_log(r"lease: leader", timeout=30)
            monkeypatch.setenv("EDGEMODBUS_INSTANCE", "b")
            with GatewayProcess(conf, tmp_path / "b.log") as gw_b:
                gw_b.wait_log(r"plc: standby", timeout=30)
                wait_for(lambda: sum(polling(slave).values()) >= 10, timeout=30,
                         what="the leader polling")
                gw_b.wait_log(r"pair: standby until", timeout=30)
                assert len(polling(slave)) == 1, slave.stats()
                assert slave.stats()["connections"] == 1  # the standby never connected
                (a_conn,) = polling(slave)
                probe.wait_for("edgemodbus/plc/t0", timeout=30)  # a publishes: subscribed
                write(probe, 11, "w1")
                probe.wait_for("edgemodbus/plc/$reply", reply_ok(probe, "w1"), timeout=30)
                assert slave.stats()["writesPerConnection"] == {a_conn: 1}

                with redis.Redis.from_url(rds.url) as client:
                    gw_a.signal(signal.SIGSTOP)
                    stopped = time.monotonic()
                    # a's lease ends in Redis no earlier than this (the key's time to live)
                    a_lease_end = stopped + client.pttl("test:pair:leader") / 1000
                try:
                    wait_for(lambda: len(polling(slave)) == 2, timeout=60,
                             what="the standby polling")
                    took_over = time.monotonic() - stopped
                    b_conn = next(c for c in polling(slave) if c != a_conn)
                    b_before = polling(slave)[b_conn]
                    assert "lease: leader" in gw_b.log
                    mark = probe.mark()
                    write(probe, 22, "w2")  # a is paused: b writes (a gets it too, later)
                    probe.wait_for("edgemodbus/plc/$reply", reply_ok(probe, "w2"),
                                   timeout=30, after=mark)
                finally:
                    gw_a.signal(signal.SIGCONT)
                print(f"takeover after SIGSTOP: {took_over:.3f} s "
                      f"(lease {LEASE_MS} ms, cycle {CYCLE_MS} ms)")
                bound = (LEASE_MS + LEASE_MS / 3 / 2 + 2 * CYCLE_MS) / 1000 + LOAD_SLACK
                assert took_over < bound, (took_over, bound)

                gw_a.wait_log(r"lease: no longer the leader", timeout=30)
                gw_a.wait_log(r"plc: standby", timeout=30, count=1)
                wait_for(lambda: a_conn not in slave.stats()["activeConnections"],
                         timeout=30, what="the old leader's connection closed")
                # b keeps polling; a sent nothing after it woke
                wait_for(lambda: polling(slave)[b_conn] >= b_before + 10, timeout=30,
                         what="the new leader polling on")
                stats = slave.stats()
                _, a_last = stats["requestTimes"][a_conn]
                b_first, _ = stats["requestTimes"][b_conn]
                assert a_last < a_lease_end, (a_last, a_lease_end)
                assert a_last < b_first  # one master at a time
                assert set(polling(slave)) == {a_conn, b_conn}  # a opened no other link
                assert stats["activeConnections"] == [b_conn]
                # each write reached the slave once: w1 through a, w2 through b only
                assert stats["writesPerConnection"] == {a_conn: 1, b_conn: 1}, stats
                assert slave.registers(1, "hr", 0) == [22]
                assert "lease: leader" not in gw_a.log.split("no longer the leader")[-1]


class _Clock:
    """The monotonic clock, moved on by hand (the line compares the lease's deadline
    with the real one)."""

    def __init__(self) -> None:
        self.start = self.now = time.monotonic()

    def __call__(self) -> float:
        return self.now


def test_writes_go_out_only_while_the_lease_holds_for_their_time() -> None:
    """A LeaderDriver polling a real slave: a write reaches it while the lease holds;
    near the lease's end, or once it is lost, the write, the action path and a forwarded
    request are refused with "not the leader" and nothing reaches the slave."""
    from edgemodbus.config import load_device_config
    from edgemodbus.gateway.lease import Lease, NotLeaderError
    from edgemodbus.gateway.pair import LeaderDriver

    clock, engine = _Clock(), Switch()
    lease = Lease(engine, 10_000, 3_000, clock=clock)
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        cfg = load_device_config(device_file(slave.port, 1, "plc", read_cycle=CYCLE_MS))
        driver = LeaderDriver(lease, cfg)
        assert driver.write_budget == pytest.approx(2.0)  # 2 x 1000 ms x (0 retries + 1)
        org = cfg.organization.model_copy(update={"device_code": "plc"})
        assert driver.start_device(org, cfg.communication, cfg.address_list)
        try:
            ok, why = driver.write_address("t0", 77)
            assert not ok and why is not None and "not the leader of the pair" in why
            lease.step()  # the lease is ours for 10 s (fake clock)
            assert driver.write_address("t0", 77) == (True, None)
            assert slave.registers(1, "hr", 0) == [77]

            clock.now = clock.start + 8.5  # 1.5 s left: less than the write may take
            ok, why = driver.write_address("t0", 78)
            assert not ok and why is not None and "lease ends in 1.500 s" in why
            clock.now = clock.start + 10.0  # expired: given up at the check
            ok, why = driver.write_address("t0", 79)
            assert not ok and why is not None and "not the leader of the pair" in why
            with pytest.raises(NotLeaderError, match="not the leader"):
                driver.submit_writes([("t0", 80)])
            with pytest.raises(NotLeaderError, match="not the leader"):
                driver.forward(bytes([0x06, 0, 0, 0, 81])).result(timeout=10)
            ok, why = driver.run_action("anything")
            assert not ok and why is not None and "not the leader" in why
            assert slave.registers(1, "hr", 0) == [77]
        finally:
            driver.stop_device()
