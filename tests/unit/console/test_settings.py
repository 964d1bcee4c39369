"""The gateway file's console section (console/settings.py, gateway/config.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from edgemodbus.config import ConfigError
from edgemodbus.console import console_key
from edgemodbus.console.auth import hash_password
from edgemodbus.gateway import load_gateway_config
from tests.fake_brokers import self_signed_cert

HASH = hash_password("pw", log2_n=4)


def load(tmp_path: Path, console: object) -> object:
    path = tmp_path / "gateway.json"
    path.write_text(json.dumps({"console": console}))
    return load_gateway_config(path)


def problems(tmp_path: Path, console: object) -> str:
    with pytest.raises(ConfigError) as info:
        load(tmp_path, console)
    return str(info.value)


def test_off_unless_the_section_is_there(tmp_path: Path) -> None:
    path = tmp_path / "gateway.json"
    path.write_text("{}")
    cfg = load_gateway_config(path)
    assert cfg.console is None and console_key(cfg.console) is None
    on = load(tmp_path, {})
    assert on.console.host == "127.0.0.1" and on.console.port == 8099  # type: ignore[attr-defined]


@pytest.mark.parametrize("console, words", [
    ({"host": "0.0.0.0"}, "console: host '0.0.0.0' is reachable from other machines"),
    ({"port": 70000}, "console.port 70000"),
    ({"host": "bad host/x"}, "console.host"),
    ({"token": "short"}, "token: 5 characters: at least 16"),
    ({"users": [{"name": "a", "passwordHash": "plain"}]},
     "console.users[0].passwordHash 'plain': is not a password hash"),
    ({"users": [{"name": "a", "passwordHash": HASH}, {"name": "a", "passwordHash": HASH}]},
     "'a' given twice"),
    ({"maxStreams": 64, "maxConnections": 64}, "maxStreams 64 must be less than"),
    ({"tls": {"certFile": "missing.pem"}}, "console.tls.certFile"),
])
def test_bad_sections_name_the_field(tmp_path: Path, console: object, words: str) -> None:
    assert words in problems(tmp_path, console)


def test_token_not_shown_in_errors(tmp_path: Path) -> None:
    assert "sekrit" not in problems(tmp_path, {"token": "sekrit"})


def test_other_hosts_with_credentials(tmp_path: Path) -> None:
    cfg = load(tmp_path, {"host": "0.0.0.0", "users": [{"name": "ops", "passwordHash": HASH}]})
    assert cfg.console.has_credentials  # type: ignore[attr-defined]
    cfg = load(tmp_path, {"host": "0.0.0.0", "token": "t" * 16})
    assert cfg.console.has_credentials  # type: ignore[attr-defined]


def test_tls_files_relative_to_the_gateway_file(tmp_path: Path) -> None:
    self_signed_cert(tmp_path / "tls")
    cfg = load(tmp_path, {"tls": {"certFile": "tls/cert.pem", "keyFile": "tls/key.pem"}})
    tls = cfg.console.tls  # type: ignore[attr-defined]
    assert Path(tls.cert_file).is_absolute() and Path(tls.cert_file).is_file()
    assert cfg.console.scheme == "https"  # type: ignore[attr-defined]
    (tmp_path / "tls" / "bad.pem").write_text("not pem")
    text = problems(tmp_path, {"tls": {"certFile": "tls/bad.pem", "keyFile": "tls/key.pem"}})
    assert "console.tls.certFile" in text
