"""The console's server against a real gateway polling a pymodbus slave: the API, the
live stream (and that no listener is subscribed while nobody watches), writes, the
CSRF / Host / auth checks, and the socket's bounds (docs/fault-checklist.md, console)."""

from __future__ import annotations

import contextlib
import http.client
import json
import socket
import ssl
import time
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.console import server as console_server
from edgemodbus.console.auth import hash_password
from edgemodbus.console.routes import MAX_BODY
from edgemodbus.driver import DriverModbusRtu
from edgemodbus.gateway import Gateway
from edgemodbus.gateway.status_log import StatusWatch
from tests.conftest import SlaveFactory
from tests.console_gateway import Client, console_gateway
from tests.fake_brokers import self_signed_cert
from tests.peers import free_port
from tests.waiting import wait_for

HASH = hash_password("letmein", log2_n=4)


def device(gateway: Gateway, code: str = "Dev1") -> Any:
    return next(d for d in gateway.devices.values() if d.code == code)


def port(gateway: Gateway) -> int:
    assert gateway.console is not None
    return gateway.console.port


def read_event(sock: socket.socket, want: str, timeout: float = 15.0) -> str:
    """Read the stream until a ``data:`` line holding ``want``; the line."""
    buf = b""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        sock.settimeout(max(0.1, deadline - time.monotonic()))
        chunk = sock.recv(65536)
        if not chunk:
            break
        buf += chunk
        for line in buf.decode(errors="replace").splitlines():
            if line.startswith("data:") and want in line:
                return line
    raise AssertionError(f"no event with {want!r} in {buf[-500:]!r}")


def open_stream(console_port: int, path: str) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", console_port), timeout=10)
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{console_port}\r\n\r\n".encode())
    return sock


def test_overview_tags_and_a_confirmed_write(tmp_path: Path, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp")
    with console_gateway(tmp_path / "cfg", slave.port) as gateway:
        client = Client(port(gateway))
        client.session()
        wait_for(lambda: client.get("/api/overview")[1]["devices"][0]["cycles"] > 2,
                 what="Dev1 polled")
        status, data = client.get("/api/overview")
        row = data["devices"][0]
        assert (row["code"], row["status"], row["items"]) == ("Dev1", "Running", 5)
        assert row["requests"] >= row["cycles"] > 0 and row["timeouts"] == 0
        status, tags = client.get("/api/devices/Dev1/tags")
        assert status == 200 and [t["name"] for t in tags["tags"]] == [f"t{i}" for i in range(5)]
        assert all(t["writable"] and t["status"] == "Ok" for t in tags["tags"])
        status, out = client.post("/api/devices/Dev1/write", {"name": "t2", "value": 4321})
        assert (status, out["ok"], out["error"]) == (200, True, None)
        assert slave.registers(1, "hr", 2, 1) == [4321]
        status, out = client.post("/api/devices/Dev1/write", {"name": "t2", "value": 70000})
        assert out["ok"] is False and "70000" in out["error"]
        status, out = client.post("/api/devices/Dev1/write", {"name": "nope", "value": 1})
        assert status == 400 and "'nope': no such tag" in out["error"]
        assert client.get("/api/devices/Nope/tags")[0] == 404


def test_slave_exception_shown(tmp_path: Path, slave_factory: SlaveFactory) -> None:
    """A write the slave refuses comes back with the slave's exception."""
    slave = slave_factory("rtu-over-tcp", size=5)
    with console_gateway(tmp_path / "cfg", slave.port, tags=5) as gateway:
        doc = json.loads((tmp_path / "cfg" / "dev1.json").read_text())
        doc["addressList"].append({"name": "far", "address": "hr:9", "deviceDataType": "UInt16"})
        (tmp_path / "cfg" / "dev1.json").write_text(json.dumps(doc))
        gateway.reload()
        client = Client(port(gateway))
        client.session()
        status, out = client.post("/api/devices/Dev1/write", {"name": "far", "value": 1})
        assert status == 200 and out["ok"] is False, out
        assert "exception" in out["error"].lower(), out


def test_stream_subscribes_only_while_watched(tmp_path: Path, slave_factory: SlaveFactory,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """No listener on the driver while no stream is open (nothing per cycle), one while
    a browser watches, none again after it left."""
    calls: list[str] = []
    subscribe, unsubscribe = DriverModbusRtu.subscribe, DriverModbusRtu.unsubscribe

    # the console's listeners only (the gateway's status log watches every device it
    # starts: gateway/status_log.py)
    def spy_subscribe(self: DriverModbusRtu, listener: Any) -> None:
        if not isinstance(listener, StatusWatch):
            calls.append("subscribe " + type(listener).__name__)
        subscribe(self, listener)

    def spy_unsubscribe(self: DriverModbusRtu, listener: Any) -> None:
        if not isinstance(listener, StatusWatch):
            calls.append("unsubscribe " + type(listener).__name__)
        unsubscribe(self, listener)

    monkeypatch.setattr(DriverModbusRtu, "subscribe", spy_subscribe)
    monkeypatch.setattr(DriverModbusRtu, "unsubscribe", spy_unsubscribe)
    slave = slave_factory("rtu-over-tcp")
    with console_gateway(tmp_path / "cfg", slave.port) as gateway:
        console = gateway.console
        assert console is not None
        Client(console.port).get("/api/devices/Dev1/tags")
        assert calls == [] and console.stats()["subscribed"] == 0
        sock = open_stream(console.port, "/api/devices/Dev1/events")
        try:
            wait_for(lambda: console.stats()["subscribed"] == 1, what="feed subscribed")
            assert calls == ["subscribe DeviceFeed"]
            slave.set_registers(1, "hr", 3, [2468])
            # (the device's first read may come first: t3 at its old value)
            line = read_event(sock, '{"name":"t3","value":2468,')
            event = json.loads(line[5:])
            assert {"name": "t3", "value": 2468, "status": "Ok"}.items() <= \
                next(r for r in event["rows"] if r["name"] == "t3").items()
        finally:
            sock.close()
        wait_for(lambda: console.stats()["subscribed"] == 0, what="feed unsubscribed")
        assert calls == ["subscribe DeviceFeed", "unsubscribe DeviceFeed"]


def test_csrf_host_and_content_type(tmp_path: Path, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp")
    with console_gateway(tmp_path / "cfg", slave.port) as gateway:
        client = Client(port(gateway))
        client.session()
        body = {"name": "t1", "value": 5}
        status, out = client.post("/api/devices/Dev1/write", body, csrf=False)
        assert status == 403 and "X-CSRF-Token" in out["error"]
        status, out = client.post("/api/devices/Dev1/write", body,
                                  headers={"Origin": "http://evil.example"})
        assert status == 403 and "evil.example" in out["error"]
        status, out = client.request("POST", "/api/devices/Dev1/write", raw=b"name=t1",
                                     headers={"Content-Type": "text/plain"})
        assert status == 415
        status, out = client.get("/api/overview", headers={"Host": "evil.example"})
        assert status == 421 and "evil.example" in out["error"]
        assert slave.registers(1, "hr", 1, 1) != [5]


def test_oversize_and_malformed_bodies(tmp_path: Path, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp")
    with console_gateway(tmp_path / "cfg", slave.port) as gateway:
        client = Client(port(gateway))
        client.session()
        big = b'{"document": "' + b"x" * MAX_BODY + b'"}'
        status, out = client.request("POST", "/api/commission/check", raw=big,
                                     headers={"Content-Type": "application/json"})
        assert status == 413
        status, out = client.request("POST", "/api/commission/check", raw=b"{not json",
                                     headers={"Content-Type": "application/json"})
        assert status == 400 and "not JSON" in out["error"]
        status, out = client.post("/api/commission/check", [1, 2])
        assert status == 400 and "JSON object" in out["error"]


def test_login_required_when_users_are_set(tmp_path: Path, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp")
    console = {"users": [{"name": "ops", "passwordHash": HASH}], "token": "t" * 20}
    with console_gateway(tmp_path / "cfg", slave.port, console) as gateway:
        client = Client(port(gateway))
        session = client.session()
        assert session["required"] and session["user"] is None and session["csrf"] is None
        assert client.get("/api/overview")[0] == 401
        assert client.post("/api/devices/Dev1/write", {"name": "t1", "value": 1})[0] == 401
        assert client.login(user="ops", password="wrong")[0] == 401
        status, data = client.login(user="ops", password="letmein")
        assert status == 200 and data["user"] == "ops" and client.cookie
        assert client.get("/api/overview")[0] == 200
        assert client.post("/api/devices/Dev1/write", {"name": "t1", "value": 11},
                           csrf=False)[0] == 403
        status, out = client.post("/api/devices/Dev1/write", {"name": "t1", "value": 11})
        assert out["ok"] is True and slave.registers(1, "hr", 1, 1) == [11]
        bearer = Client(port(gateway))
        assert bearer.get("/api/overview", headers={"Authorization": "Bearer " + "t" * 20}
                          )[0] == 200
        assert bearer.get("/api/overview", headers={"Authorization": "Bearer nope"})[0] == 401
        client.post("/api/logout")
        assert client.get("/api/overview")[0] == 401


def test_commission_check_save_and_poll(tmp_path: Path, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp")
    folder = tmp_path / "cfg"
    with console_gateway(folder, slave.port) as gateway:
        client = Client(port(gateway))
        client.session()
        doc = json.loads((folder / "dev1.json").read_text())
        doc["organization"]["deviceCode"] = "Dev9"
        doc["communication"]["slaveId"] = 300
        _, out = client.post("/api/commission/check", {"document": doc})
        assert out["ok"] is False
        assert [p["path"] for p in out["problems"]] == ["communication.slaveId"]
        doc["communication"]["slaveId"] = 2
        _, out = client.post("/api/commission/check", {"document": doc})
        assert out["ok"] is True and out["plan"]["requests"][0]["count"] == 5
        for bad in ("../x.json", "gateway.json", "x.txt"):
            _, out = client.post("/api/commission/save",
                                 {"fileName": bad, "document": doc})
            assert out["ok"] is False and out["problems"][0]["path"] == "fileName", bad
        _, out = client.post("/api/commission/save",
                             {"fileName": "dev9.json", "document": doc})
        assert out == {"ok": True, "file": "dev9.json", "code": "Dev9"}
        assert json.loads((folder / "dev9.json").read_text()) == doc
        wait_for(lambda: any(r["code"] == "Dev9" and r["cycles"] > 0
                             for r in client.get("/api/overview")[1]["devices"]),
                 what="the saved device polled")
        _, out = client.post("/api/commission/save",
                             {"fileName": "dev9.json", "document": doc})
        assert out["ok"] is False and "exists" in out["problems"][0]["message"]


def test_connection_cap_and_slow_heads(tmp_path: Path, slave_factory: SlaveFactory,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(console_server, "HEAD_SECONDS", 0.5)
    slave = slave_factory("rtu-over-tcp")
    with console_gateway(tmp_path / "cfg", slave.port,
                         {"maxConnections": 4, "maxStreams": 1}) as gateway:
        console = gateway.console
        assert console is not None
        idle = [socket.create_connection(("127.0.0.1", console.port), timeout=10)
                for _ in range(4)]
        try:
            wait_for(lambda: console.stats()["connections"] == 4, what="4 connections")
            extra = socket.create_connection(("127.0.0.1", console.port), timeout=10)
            with extra, contextlib.suppress(ConnectionResetError):
                assert extra.recv(10) == b""
            assert console.stats()["refused"] >= 1
            # none sent a request head: each is closed at the head deadline
            for sock in idle:
                with contextlib.suppress(ConnectionResetError):
                    assert sock.recv(10) == b""
            wait_for(lambda: console.stats()["connections"] == 0, what="slow heads closed")
            assert console.stats()["slowHeads"] == 4
        finally:
            for sock in idle:
                sock.close()
        client = Client(console.port)
        client.session()
        assert client.get("/api/overview")[0] == 200  # still serving


def test_stream_cap(tmp_path: Path, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp")
    with console_gateway(tmp_path / "cfg", slave.port, {"maxStreams": 1}) as gateway:
        console = gateway.console
        assert console is not None
        first = open_stream(console.port, "/api/devices/Dev1/events")
        try:
            wait_for(lambda: console.stats()["streams"] == 1, what="one stream")
            status, out = Client(console.port).get("/api/devices/Dev1/events")
            assert status == 503 and "maxStreams" in out["error"]
        finally:
            first.close()
        wait_for(lambda: console.stats()["streams"] == 0, what="stream closed")


def test_overview_shows_the_held_dtus(tmp_path: Path, slave_factory: SlaveFactory) -> None:
    """The DTU table: a DTU that registered on a listen port, with its peer address, and
    the port's counters (a refusal by kind)."""
    slave = slave_factory("rtu-over-tcp")
    listen = free_port()
    with console_gateway(tmp_path / "cfg", slave.port) as gateway:
        (tmp_path / "cfg" / "dtu.json").write_text(json.dumps({
            "organization": {"deviceCode": "Dtu1"},
            "communication": {
                "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                "listenPort": listen, "registration": "regex",
                "registrationPattern": "IMEI:(\\d{15})", "dtuId": "861234567890123",
                "slaveId": 1, "readTimeout": 500},
            "addressList": [{"name": "a", "address": "hr:0", "deviceDataType": "UInt16"}]}))
        gateway.reload()
        client = Client(port(gateway))
        client.session()
        key = f"127.0.0.1:{listen}"
        wait_for(lambda: key in client.get("/api/overview")[1]["dtus"], what="the port")
        dtu = socket.create_connection(("127.0.0.1", listen), timeout=10)
        stranger = socket.create_connection(("127.0.0.1", listen), timeout=10)
        try:
            dtu.sendall(b"IMEI:861234567890123")
            stranger.sendall(b"IMEI:999999999999999")
            here = f"127.0.0.1:{dtu.getsockname()[1]}"

            def held() -> dict[str, Any]:
                return dict(client.get("/api/overview")[1]["dtus"][key][0])

            wait_for(lambda: held()["connected"] and held()["peer"] == here, timeout=15,
                     what="the DTU held with its peer address")
            assert held()["dtuId"] == "861234567890123"
            wait_for(lambda: any(v for k, v in client.get("/api/overview")[1]["listeners"]
                                 [key].items() if "nknown" in k), timeout=15,
                     what="the stranger's refusal counted")
        finally:
            dtu.close()
            stranger.close()


def test_run_an_action(tmp_path: Path, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp")
    folder = tmp_path / "cfg"
    actions = [{"name": "preset", "functionCode": 16, "parameters": [
        {"name": "a", "item": "t1", "type": "UInt16", "maxValue": 100},
        {"name": "b", "item": "t2", "default": 7}]}]
    with console_gateway(folder, slave.port, extra={"actions": actions}) as gateway:
        client = Client(port(gateway))
        client.session()
        assert client.get("/api/devices/Dev1/tags")[1]["actions"] == ["preset"]
        _, out = client.post("/api/devices/Dev1/action", {"name": "preset",
                                                          "params": {"a": 42}})
        assert out == {"ok": True, "error": None, "name": "preset"}
        assert slave.registers(1, "hr", 1, 2) == [42, 7]
        _, out = client.post("/api/devices/Dev1/action", {"name": "preset",
                                                          "params": {"a": 101}})
        assert out["ok"] is False and "101" in out["error"] and "100" in out["error"]
        status, out = client.post("/api/devices/Dev1/action", {"name": 5})
        assert status == 400 and "name" in out["error"]


def test_reload_moves_and_stops_the_console(tmp_path: Path, slave_factory: SlaveFactory
                                            ) -> None:
    """SIGHUP's path: a changed console section restarts the console, a removed one
    stops it (and the old port no longer answers)."""
    slave = slave_factory("rtu-over-tcp")
    folder = tmp_path / "cfg"
    with console_gateway(folder, slave.port) as gateway:
        old = gateway.console
        assert old is not None
        (folder / "gateway.json").write_text(json.dumps({"console": {"port": 0,
                                                                     "maxStreams": 3}}))
        gateway.reload()
        new = gateway.console
        assert new is not None and new is not old and new.settings.max_streams == 3
        assert Client(new.port).get("/api/session")[0] == 200
        (folder / "gateway.json").write_text("{}")
        gateway.reload()
        assert gateway.console is None
        with pytest.raises(OSError):
            Client(new.port).get("/api/session")


def test_tls(tmp_path: Path, slave_factory: SlaveFactory) -> None:
    """HTTPS with the configured certificate; the session cookie is Secure; a renewed
    certificate restarts the console on reload."""
    cert, key = self_signed_cert(tmp_path / "tls")
    slave = slave_factory("rtu-over-tcp")
    console = {"tls": {"certFile": str(cert), "keyFile": str(key)},
               "users": [{"name": "ops", "passwordHash": HASH}]}
    with console_gateway(tmp_path / "cfg", slave.port, console) as gateway:
        server = gateway.console
        assert server is not None and server.url.startswith("https://127.0.0.1:")
        context = ssl.create_default_context(cafile=str(cert))
        conn = http.client.HTTPSConnection("127.0.0.1", server.port, timeout=30,
                                           context=context)
        try:
            conn.request("POST", "/api/login", body=json.dumps(
                {"user": "ops", "password": "letmein"}),
                headers={"Content-Type": "application/json"})
            resp = conn.getresponse()
            resp.read()
            assert resp.status == 200
            assert "Secure" in (resp.getheader("Set-Cookie") or "")
        finally:
            conn.close()
        with pytest.raises(OSError):  # plain HTTP is not answered
            Client(server.port).get("/api/session")
        self_signed_cert(tmp_path / "tls")  # renewed: same paths, new contents
        gateway.reload()
        assert gateway.console is not None and gateway.console is not server
