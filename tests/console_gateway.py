"""A gateway with its web console on 127.0.0.1 (an ephemeral port) over a config folder
of device files polling a pymodbus slave, and a small HTTP client of the console's API
(a cookie jar, the CSRF header).  Used by tests/unit/console/ and tests/browser/."""

from __future__ import annotations

import http.client
import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from edgemodbus.gateway import Gateway, load_gateway_config
from tests.gateway_proc import device_file


@contextmanager
def console_gateway(folder: Path, slave_port: int, console: dict[str, Any] | None = None,
                    *, tags: int = 5, read_cycle: int = 100, devices: int = 1,
                    extra: dict[str, Any] | None = None) -> Iterator[Gateway]:
    """A started Gateway over ``folder``: ``devices`` device files (Dev1.., unit 1..) of
    ``tags`` holding registers each, with the keys of ``extra`` added; stopped on exit."""
    folder.mkdir(parents=True, exist_ok=True)
    for n in range(1, devices + 1):
        doc = device_file(slave_port, n, f"Dev{n}", tags=tags, read_cycle=read_cycle)
        (folder / f"dev{n}.json").write_text(json.dumps({**doc, **(extra or {})}))
    gateway_file = folder / "gateway.json"
    gateway_file.write_text(json.dumps({"console": {"port": 0, **(console or {})}}))
    gateway = Gateway(folder, load_gateway_config(gateway_file), gateway_file)
    try:
        gateway.start()
        yield gateway
    finally:
        gateway.stop()


class Client:
    """The console's API over http.client: JSON in and out, the session cookie, the
    CSRF token of /api/session (or of the login)."""

    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        self.port = port
        self.host = host
        self.cookie: str | None = None
        self.csrf: str | None = None

    def request(self, method: str, path: str, body: Any = None, *,
                headers: dict[str, str] | None = None, raw: bytes | None = None,
                csrf: bool = True) -> tuple[int, Any]:
        conn = http.client.HTTPConnection(self.host, self.port, timeout=30)
        try:
            sent = dict(headers or {})
            if self.cookie:
                sent.setdefault("Cookie", self.cookie)
            data = raw
            if body is not None:
                data = json.dumps(body).encode()
                sent.setdefault("Content-Type", "application/json")
            if csrf and self.csrf and method != "GET":
                sent.setdefault("X-CSRF-Token", self.csrf)
            conn.request(method, path, body=data, headers=sent)
            resp = conn.getresponse()
            text = resp.read()
            cookie = resp.getheader("Set-Cookie")
            if cookie:
                self.cookie = cookie.split(";", 1)[0]
            try:
                return resp.status, json.loads(text)
            except ValueError:
                return resp.status, text
        finally:
            conn.close()

    def get(self, path: str, **kw: Any) -> tuple[int, Any]:
        return self.request("GET", path, **kw)

    def post(self, path: str, body: Any = None, **kw: Any) -> tuple[int, Any]:
        return self.request("POST", path, body if body is not None else {}, **kw)

    def session(self) -> dict[str, Any]:
        status, data = self.get("/api/session")
        assert status == 200, data
        self.csrf = data["csrf"]
        return dict(data)

    def login(self, **credentials: str) -> tuple[int, Any]:
        status, data = self.post("/api/login", credentials)
        if status == 200:
            self.csrf = data["csrf"]
        return status, data
