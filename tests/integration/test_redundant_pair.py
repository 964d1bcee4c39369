"""A redundant pair (gateway/lease.py, gateway/pair.py, docs/deploy.md "Redundant
pair"): two gateway processes with one config folder and a real redis-server poll one
pymodbus slave over RTU over TCP.  Only the leader polls (the slave counts requests per
connection); ``kill -STOP`` the leader: the standby polls within the lease time plus a
retry and two cycles; ``kill -CONT``: the old leader finds its lease gone and sends
nothing more on its connection, which it closes."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from tests.gateway_proc import GatewayProcess, device_file, write_json
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


def test_one_leader_polls_and_the_standby_takes_over_a_paused_one(tmp_path: Path) -> None:
    with RedisServer(tmp_path / "redis") as rds, \
            PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        conf = tmp_path / "conf"
        conf.mkdir()
        write_json(conf / "gateway.json", {"fleet": {"lease": {
            "url": rds.url, "keyPrefix": "test:pair:", "leaseMs": LEASE_MS}}})
        write_json(conf / "plc.json", device_file(slave.port, 1, "plc", read_cycle=CYCLE_MS))
        with GatewayProcess(conf, tmp_path / "a.log") as gw_a:
            gw_a.wait_log(r"lease: leader", timeout=30)
            with GatewayProcess(conf, tmp_path / "b.log") as gw_b:
                gw_b.wait_log(r"plc: standby", timeout=30)
                wait_for(lambda: sum(polling(slave).values()) >= 10, timeout=30,
                         what="the leader polling")
                gw_b.wait_log(r"pair: standby until", timeout=30)
                assert len(polling(slave)) == 1, slave.stats()
                assert slave.stats()["connections"] == 1  # the standby never connected
                (a_conn,) = polling(slave)

                gw_a.signal(signal.SIGSTOP)
                stopped = time.monotonic()
                try:
                    wait_for(lambda: len(polling(slave)) == 2, timeout=60,
                             what="the standby polling")
                    took_over = time.monotonic() - stopped
                    frozen = polling(slave)[a_conn]
                    b_conn = next(c for c in polling(slave) if c != a_conn)
                    b_before = polling(slave)[b_conn]
                    assert "lease: leader" in gw_b.log
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
                # B keeps polling; A sent nothing after it woke
                wait_for(lambda: polling(slave)[b_conn] >= b_before + 10, timeout=30,
                         what="the new leader polling on")
                assert polling(slave)[a_conn] == frozen, (frozen, slave.stats())
                assert len(slave.stats()["activeConnections"]) == 1
                assert "lease: leader" not in gw_a.log.split("no longer the leader")[-1]


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class _Engine:
    """The lease's engine reduced to a switch (the Redis protocol is tested above)."""

    def __init__(self) -> None:
        self.free = True

    def acquire(self, token: str, ttl_ms: int) -> int | None:
        return 1 if self.free else None

    def renew(self, token: str, ttl_ms: int) -> bool:
        return self.free

    def release(self, token: str) -> None:
        pass


def test_writes_go_out_only_while_the_lease_holds_for_their_time() -> None:
    """A LeaderDriver polling a real slave: a write reaches it while the lease holds;
    near the lease's end, or once it is lost, the write, the action path and a forwarded
    request are refused with "not the leader" and nothing reaches the slave."""
    from edgemodbus.config import load_device_config
    from edgemodbus.gateway.lease import Lease, NotLeaderError
    from edgemodbus.gateway.pair import LeaderDriver

    clock, engine = _Clock(), _Engine()
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

            clock.now = 8.5  # 1.5 s left: less than the write may take
            ok, why = driver.write_address("t0", 78)
            assert not ok and why is not None and "lease ends in 1.500 s" in why
            clock.now = 10.0  # expired: given up at the check
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
