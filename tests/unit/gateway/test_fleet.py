"""The gateway file's ``fleet`` section (gateway/fleet.py) and the retained-status rule
of a fleet device (northbound/mqtt/holding.py)."""

from __future__ import annotations

import orjson
import pytest

from edgemodbus.config import ConfigError
from edgemodbus.gateway.config import load_gateway_config, mqtt_key
from edgemodbus.gateway.fleet import INSTANCE_ENV, MAX_BALANCERS
from edgemodbus.northbound.mqtt.holding import Holding, holder_of


def test_the_section_is_read_and_normalised() -> None:
    cfg = load_gateway_config({"fleet": {"instanceId": "gw-2",
                                         "loadBalancers": "10.0.5.10, 10.1.0.0/16 ::1"}})
    assert cfg.fleet is not None and cfg.instance == "gw-2"
    assert cfg.fleet.load_balancers == ("10.0.5.10/32", "10.1.0.0/16", "::1/128")
    assert load_gateway_config({}).instance is None
    assert load_gateway_config({"fleet": {"enabled": False}}).instance is None


def test_the_instance_comes_from_the_environment_then_the_host_name(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(INSTANCE_ENV, "unit-3")
    assert load_gateway_config({"fleet": {}}).instance == "unit-3"
    monkeypatch.delenv(INSTANCE_ENV)
    monkeypatch.setattr("socket.gethostname", lambda: "box7.example.org")
    assert load_gateway_config({"fleet": {}}).instance == "box7"


@pytest.mark.parametrize(("fleet", "key", "words"), [
    ({"instanceId": "a/b"}, "fleet.instanceId", "cannot be used in MQTT topics"),
    ({"instanceId": "a+b"}, "fleet.instanceId", "cannot be used in MQTT topics"),
    ({"loadBalancers": ["10.0.0.1/8"]}, "fleet.loadBalancers[0]", "use 10.0.0.0/8"),
    ({"loadBalancers": ["haproxy"]}, "fleet.loadBalancers[0]", "CIDR"),
    ({"loadBalancers": 5}, "fleet.loadBalancers", "list of networks"),
    ({"loadBalancers": [f"10.0.0.{i}" for i in range(MAX_BALANCERS + 1)]},
     "fleet.loadBalancers", f"at most {MAX_BALANCERS}"),
])
def test_bad_values_are_named(fleet: dict[str, object], key: str, words: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_gateway_config({"fleet": fleet})
    assert key in str(err.value) and words in str(err.value)


def test_a_new_instance_id_restarts_the_publisher() -> None:
    one = load_gateway_config({"mqtt": {}, "fleet": {"instanceId": "a"}})
    two = load_gateway_config({"mqtt": {}, "fleet": {"instanceId": "b"}})
    assert mqtt_key(one) != mqtt_key(two)


def status(instance: str, since: float, text: str = "Running") -> bytes:
    return orjson.dumps({"status": text, "instance": instance, "heldSince": since})


def test_the_holder_with_the_newer_registration_wins() -> None:
    here = [True]
    holding = Holding(lambda: here[0])
    assert holding.turn(100.0) == "arrived" and holding.turn(101.0) is None
    assert not holding.read_back(status("A", 100.0), "A")  # our own
    assert holding.read_back(status("B", 99.0), "A")  # B took it earlier: ours again
    assert not holding.read_back(status("B", 150.0), "A")  # B took it later: B's
    assert holding.read_back(status("B", 100.0), "A") is False  # a tie: the larger id, B
    assert holding.read_back(status("B", 150.0, "NotHere"), "A")  # B let it go: ours
    assert Holding(lambda: True).read_back(status("B", 1.0), "C") is False  # not holding
    here[0] = False
    assert holding.turn(200.0) == "left"
    assert not holding.may_say_left("A")  # the last read names B: A stays silent
    holding.read_back(status("A", 100.0), "A")
    assert holding.may_say_left("A")


@pytest.mark.parametrize("payload", [b"", b"[]", b"{}", b'{"instance": 1, "heldSince": 2}',
                                     b'{"instance": "A", "heldSince": "x"}', b"\xff"])
def test_statuses_without_a_holder_are_ignored(payload: bytes) -> None:
    assert holder_of(payload) is None


def test_a_fleet_device_without_writes_subscribes_to_its_status_only() -> None:
    """writes off: a held device's subscriptions are its status topic (read back), no
    command topic (the subscription for the fleet must not turn commands on)."""
    from edgemodbus.northbound.mqtt import MqttSettings
    from edgemodbus.northbound.mqtt.devices import AttachedDevice

    settings = MqttSettings()

    def topic(template: str, code: str = "", item: str = "") -> str:
        return template.format(prefix="p", deviceCode=code, itemName=item, gatewayId="g")

    dev = AttachedDevice(settings, topic, None, "m1")  # type: ignore[arg-type]
    assert "p/m1/set/#" in dev.filters(True) and dev.filters(False) == []
    dev.fleet = Holding(lambda: True)
    assert dev.filters(False) == ["p/m1/$status"]
    assert dev.filters(True)[-1] == "p/m1/$status"


def test_the_lease_section_is_read_with_its_defaults() -> None:
    cfg = load_gateway_config({"fleet": {"lease": {"url": "redis://10.0.5.20:6379/0"}}})
    assert cfg.fleet is not None and cfg.fleet.lease is not None
    lease = cfg.fleet.lease
    assert (lease.key_prefix, lease.lease_ms, lease.effective_renew_ms) == (
        "edgemodbus:pair:", 10_000, 3_333)


@pytest.mark.parametrize(("lease", "key", "words"), [
    ({}, "fleet.lease.url", "required"),
    ({"url": "http://x"}, "fleet.lease.url", "is not a Redis URL: use redis://"),
    ({"url": "redis://x", "leaseMs": 999}, "fleet.lease.leaseMs", "must be 1000..600000"),
    ({"url": "redis://x", "leaseMs": 600_001}, "fleet.lease.leaseMs", "must be 1000..600000"),
    ({"url": "redis://x", "leaseMs": 3000, "renewMs": 1001}, "fleet.lease",
     "renewMs 1001 must be at most a third of leaseMs 3000"),
    ({"url": "redis://x", "keyPrefix": "a b"}, "fleet.lease.keyPrefix", "without spaces"),
    ({"url": "redis://x", "leaseMs": 2000, "marginMs": 1001}, "fleet.lease",
     "marginMs 1001 must be at most half of leaseMs 2000"),
    ({"url": "redis://x", "marginMs": -1}, "fleet.lease.marginMs", "must be 0..300000"),
])
def test_bad_lease_values_are_named(lease: dict[str, object], key: str, words: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_gateway_config({"fleet": {"lease": lease}})
    assert key in str(err.value) and words in str(err.value)


SPARKPLUG = {"mode": "sparkplug", "sparkplug": {"groupId": "g", "sharedByPair": True,
                                                "bdSeqFile": "/nonexistent/ignored"}}


@pytest.mark.parametrize("fleet", [
    None, {"instanceId": "a"}, {"lease": {"url": "redis://x", "enabled": False}},
    {"enabled": False, "lease": {"url": "redis://x"}}])
def test_a_node_shared_by_a_pair_needs_the_pair(fleet: dict[str, object] | None) -> None:
    data: dict[str, object] = {"mqtt": SPARKPLUG}
    if fleet is not None:
        data["fleet"] = fleet
    with pytest.raises(ConfigError) as err:
        load_gateway_config(data)
    assert "mqtt.sparkplug.sharedByPair" in str(err.value)
    assert "needs a redundant pair: an enabled fleet.lease" in str(err.value)


def test_a_node_shared_by_a_pair_has_one_id() -> None:
    from edgemodbus.northbound.sparkplug.settings import node_id_for

    assert node_id_for(None, "gw", "a", shared=True) == "gw"
    assert node_id_for("line-7", "gw", "b", shared=True) == "line-7"
    with pytest.raises(ValueError, match="sharedByPair makes both instances"):
        node_id_for("line-{instance}", "gw", "a", shared=True)


def test_the_shared_bdseq_store_reads_only_its_numbers() -> None:
    from edgemodbus.northbound.sparkplug.bdseq import RedisBdSeqStore

    class Client:
        def __init__(self, value: object) -> None:
            self.value = value

        def get(self, key: str) -> object:
            assert key == "p:bdseq"
            return self.value

        def eval(self, script: str, keys: int, *args: object) -> None:
            raise ConnectionError("refused")

    assert RedisBdSeqStore(Client(None), "p:bdseq", lambda: True).load() == 0
    assert RedisBdSeqStore(Client(b"255"), "p:bdseq", lambda: True).load() == 255
    # what save() leaves in a real Redis: tests/integration/test_sparkplug_bdseq_redis.py
    for bad in (b"256", b"-1", b"x", b"1.5"):
        with pytest.raises(ValueError, match="not a bdSeq 0-255"):
            RedisBdSeqStore(Client(bad), "p:bdseq", lambda: True).load()
    RedisBdSeqStore(Client(None), "p:bdseq", lambda: True).save(3)  # logged, not raised
