"""The mqtt-dtu TLS keys get the same file checks as the northbound's mqtt.tls
(config/tls.py, one copy): each problem names the mqtt-dtu key, the path and why."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.config import ConfigError, load_device_config
from edgemodbus.config.tls import tls_file_problems
from tests.fake_brokers import self_signed_cert


def errors_of(**keys: Any) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_device_config({"communication": {"transport": "mqtt-dtu", "dtuId": "d",
                                              "mqttTls": True, **keys}, "addressList": []})
    return [str(p) for p in info.value.problems]


def test_the_mqtt_dtu_tls_files_are_checked_as_the_northbound_s(tmp_path: Path) -> None:
    cert, key = self_signed_cert(tmp_path / "a")
    _, other_key = self_signed_cert(tmp_path / "b")
    text = tmp_path / "text.pem"
    text.write_text("not PEM at all\n")
    (tmp_path / "dir.pem").mkdir()
    fifo = tmp_path / "fifo.pem"
    os.mkfifo(fifo)
    c = "communication."
    assert errors_of(mqttCaFile=str(text)) == [
        f"{c}mqttCaFile '{text}': no PEM certificate in it"]
    assert errors_of(mqttCaFile=str(tmp_path / "dir.pem")) == [
        f"{c}mqttCaFile '{tmp_path / 'dir.pem'}': is a directory, not a file"]
    assert errors_of(mqttCaFile=str(fifo)) == [
        f"{c}mqttCaFile '{fifo}': is a FIFO, not a regular file"]
    assert errors_of(mqttKeyFile=str(key)) == [
        f"{c}mqttKeyFile '{key}': needs mqttCertFile (the client certificate of this key)"]
    assert errors_of(mqttCertFile=str(cert), mqttKeyFile=str(other_key)) == [
        f"{c}mqttCertFile/mqttKeyFile '{cert}, {other_key}': the key does not belong to "
        "the certificate"]
    assert errors_of(mqttCertFile=str(cert)) == [
        f"{c}mqttCertFile '{cert}': no PEM private key in it (mqttKeyFile is not set, so "
        "the key must be in mqttCertFile)"]
    good = load_device_config({"communication": {
        "transport": "mqtt-dtu", "dtuId": "d", "mqttTls": True, "mqttCaFile": str(cert),
        "mqttCertFile": str(cert), "mqttKeyFile": str(key)}, "addressList": []})
    assert good.communication.mqtt_ca_file == str(cert)
    # without mqttTls the files are not used, so not checked
    load_device_config({"communication": {"transport": "mqtt-dtu", "dtuId": "d",
                                          "mqttCaFile": str(text)}, "addressList": []})


def test_one_check_names_each_caller_s_keys(tmp_path: Path) -> None:
    missing = str(tmp_path / "missing.pem")
    assert [str(p) for p in tls_file_problems(missing, None, None, where="mqtt.tls.")] == [
        f"mqtt.tls.caFile '{missing}': no such file"]
    assert [str(p) for p in tls_file_problems(None, None, missing, keys=(
        "mqttCaFile", "mqttCertFile", "mqttKeyFile"))] == [
        f"mqttKeyFile '{missing}': no such file",
        f"mqttKeyFile '{missing}': needs mqttCertFile (the client certificate of this key)"]
