"""The MQTT DTU keys (transport mqtt-dtu, config/mqtt_dtu.py): checked with the
transport, each bad value named with what is allowed; the endpoint carries the broker
and the DTU's topics with its id in place."""

from __future__ import annotations

from typing import Any

import pytest

from edgemodbus.config import ConfigError, DriverModbusRtuParameter, load_device_config
from edgemodbus.line.endpoint import MqttDtuEndpoint, endpoint_for


def errors_of(**keys: Any) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_device_config({"communication": {"transport": "mqtt-dtu", **keys},
                            "addressList": []})
    return [str(p) for p in info.value.problems]


def test_the_endpoint_has_the_broker_and_the_dtu_s_topics() -> None:
    params = DriverModbusRtuParameter.model_validate({
        "transport": "mqtt-dtu", "mqttHost": "broker.local", "mqttPort": 8883,
        "mqttUsername": "gw", "mqttPassword": "s3cret", "mqttTls": True, "dtuId": "861234",
        "heartbeat": "HB", "framing": "wrapped-report", "statusTopic": "site/{dtuId}/lwt"})
    ep = endpoint_for(params)
    assert isinstance(ep, MqttDtuEndpoint)
    assert (ep.uplink, ep.downlink, ep.status) == ("dtu/861234/up", "dtu/861234/down",
                                                   "site/861234/lwt")
    assert (ep.broker.host, ep.broker.port, ep.broker.tls) == ("broker.local", 8883, True)
    assert (ep.heartbeat, ep.framing) == (b"HB", "wrapped-report")
    assert "s3cret" not in repr(ep) and "s3cret" not in ep.describe()
    assert ep.key == ("mqtt-dtu", "broker.local", "8883", "861234")
    assert params.use_tcp  # not a serial line


@pytest.mark.parametrize(("keys", "error"), [
    ({}, "communication.dtuId '': required with transport mqtt-dtu: the {dtuId} of its "
         "topics"),
    ({"dtuId": "a+b"}, "communication.dtuId 'a+b': must not contain MQTT wildcards (+, #) "
                       "or NUL: it is part of the DTU's topics"),
    ({"dtuId": "d", "uplinkTopic": "dtu/up"}, "communication.uplinkTopic 'dtu/up': needs "
     "{dtuId}: each DTU has topics of its own, e.g. dtu/{dtuId}/up"),
    ({"dtuId": "d", "downlinkTopic": "dtu/{dtuId}/up"}, "communication.downlinkTopic "
     "'dtu/{dtuId}/up': must differ from uplinkTopic: the gateway would read its own "
     "requests"),
    ({"dtuId": "d", "uplinkTopic": "dtu/#"}, "communication.uplinkTopic 'dtu/#': must not "
     "contain MQTT wildcards (+, #) or NUL"),
    ({"dtuId": "d", "statusTopic": "x/{id}"}, "communication.statusTopic 'x/{id}': the only "
     "placeholder is {dtuId} (no other braces)"),
    ({"dtuId": "d", "offlinePayload": "online"}, "communication.offlinePayload 'online': "
     "must differ from onlinePayload"),
    ({"dtuId": "d", "mqttPassword": "pw"}, "communication.mqttPassword '**********': needs "
     "mqttUsername"),
    ({"dtuId": "d", "mqttTls": True, "mqttCaFile": "/nonexistent/ca.pem"},
     "communication.mqttCaFile '/nonexistent/ca.pem': no such file"),
    ({"dtuId": "d", "alternates": ["h:1"]}, "communication.alternates ['h:1']: a DTU that "
     "dials in (mqtt-dtu) picks its own path; alternates are for lines we open (rtu, "
     "rtu-over-tcp, tcp)"),
])
def test_bad_mqtt_dtu_keys_are_named(keys: dict[str, Any], error: str) -> None:
    assert errors_of(**keys) == [error]


def test_the_keys_are_ignored_on_other_transports_but_each_form_is_checked() -> None:
    assert DriverModbusRtuParameter.model_validate({"transport": "tcp", "uplinkTopic": "x"})
    with pytest.raises(ConfigError, match=r"uplinkTopic 'a/\+': must not contain"):
        load_device_config({"communication": {"transport": "tcp", "uplinkTopic": "a/+"},
                            "addressList": []})
