"""The exporter's HTTP server (northbound/metrics_http.py): the same answers as the
standard library's WSGI server gave (a differential test over real HTTP), and its
bounds: request size, methods, the header deadline, the connection cap, junk."""

from __future__ import annotations

import gzip
import http.client
import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from prometheus_client import make_wsgi_app

from edgemodbus.datatypes import DeviceDriverStatus
from edgemodbus.northbound.metrics import MetricsExporter
from edgemodbus.northbound.metrics_http import MetricsHttpServer
from tests.waiting import wait_for


class FixedDriver:
    """Counters that never change, so that two scrapes give the same bytes."""

    device_driver_status = DeviceDriverStatus.RUNNING
    data_item_count = 2

    def stats(self) -> dict[str, Any]:
        return {"cycles": 7, "requests": 9, "responses": 8, "timeouts": 1,
                "exceptions": {2: 1}, "avgCycleTime": 0.01, "avgRoundTrip": 0.002,
                "line": {"requests": 9, "responses": 8}}


class _Quiet(WSGIRequestHandler):
    def log_message(self, format: str, *args: Any) -> None:
        pass


@contextmanager
def serving(server: Any) -> Iterator[int]:
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield int(server.server_port)
    finally:
        server.shutdown()
        thread.join(5)
        server.server_close()


@contextmanager
def ours(app: Any, **kw: Any) -> Iterator[tuple[int, MetricsHttpServer]]:
    server = MetricsHttpServer("127.0.0.1", 0, app, **kw)
    with serving(server) as port:
        yield port, server


def ask(port: int, method: str = "GET", path: str = "/metrics",
        headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request(method, path, headers=headers or {})
        resp = conn.getresponse()
        return resp.status, {k.lower(): v for k, v in resp.getheaders()}, resp.read()
    finally:
        conn.close()


@pytest.fixture
def app() -> Any:
    exporter = MetricsExporter({"port": 0})
    exporter.attach(FixedDriver(), "dev1", "line1")
    return make_wsgi_app(exporter.registry)


REQUESTS = [
    ("GET", "/metrics", {}),
    ("GET", "/metrics", {"Accept": "application/openmetrics-text; version=1.0.0"}),
    ("GET", "/metrics", {"Accept-Encoding": "gzip"}),
    ("GET", "/metrics?name[]=edgemodbus_requests_total", {}),
    ("GET", "/", {}),
    ("GET", "/favicon.ico", {}),
    ("HEAD", "/metrics", {}),
]


@pytest.mark.parametrize(("method", "path", "headers"), REQUESTS)
def test_answers_are_the_standard_library_servers(
        app: Any, method: str, path: str, headers: dict[str, str]) -> None:
    """The exposition is prometheus_client's: status, Content-Type, Content-Encoding and
    body as wsgiref's server (the exporter's server before) gave them."""
    reference = make_server("127.0.0.1", 0, app, server_class=WSGIServer,
                            handler_class=_Quiet)
    with serving(reference) as ref_port, ours(app) as (port, _):
        want = ask(ref_port, method, path, headers)
        got = ask(port, method, path, headers)
    assert got[0] == want[0]
    for key in ("content-type", "content-encoding"):
        assert got[1].get(key) == want[1].get(key), key
    assert got[2] == want[2]
    if headers.get("Accept-Encoding") == "gzip":
        assert b"edgemodbus_requests_total" in gzip.decompress(got[2])
    elif method == "GET" and path == "/metrics":
        assert b'edgemodbus_requests_total{device="dev1",line="line1"} 9.0' in got[2]


def test_other_methods_and_oversize_requests_are_refused(app: Any) -> None:
    with ours(app, max_request_bytes=1024) as (port, server):
        status, headers, _ = ask(port, "POST")
        assert status == 405 and headers["allow"] == "GET, HEAD"
        status, _, _ = ask(port, headers={"X-Pad": "x" * 2000})
        assert status == 431
        with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            sock.sendall(b"GET /metrics HTTP/1.1\r\nX-Pad: " + b"y" * 4096)
            assert sock.recv(64).startswith(b"HTTP/1.1 431 ")
        assert server.counts["tooLarge"] == 2 and server.counts["badRequests"] == 1
        assert ask(port)[0] == 200


def test_the_header_deadline_closes_a_slow_request(app: Any) -> None:
    with ours(app, header_deadline=0.3) as (port, server), \
            socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
        sock.sendall(b"GET /metrics HTTP/1.1\r\n")  # and nothing more
        wait_for(lambda: server.connections() == 1, timeout=20, what="accepted")
        sock.settimeout(10)
        assert sock.recv(64) == b""  # closed by the server
        assert server.counts["timedOut"] == 1 and server.connections() == 0


def test_at_the_connection_cap_the_oldest_waiting_request_makes_room(app: Any) -> None:
    with ours(app, max_connections=3) as (port, server):
        held = [socket.create_connection(("127.0.0.1", port), timeout=5) for _ in range(3)]
        try:
            for sock in held:
                sock.sendall(b"GET /metrics HTTP/1.1\r\n")
            wait_for(lambda: server.connections() == 3, timeout=20, what="3 held")
            assert ask(port)[0] == 200  # one more: the oldest waiting one is closed
            held[0].settimeout(10)
            assert held[0].recv(64) == b""
            assert server.counts["evicted"] == 1
            wait_for(lambda: server.connections() == 2, timeout=20,
                     what="the scrape's connection closed, two held")
        finally:
            for sock in held:
                sock.close()


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(junk=st.one_of(
    st.binary(max_size=300),
    st.lists(st.sampled_from([b"GET", b" ", b"/metrics", b"HTTP/1.1", b"\r\n", b":",
                              b"Host", b"\x00", b"\xff", b"HTTP/2", b"POST"]),
             max_size=30).map(b"".join)))
def test_junk_gets_an_answer_or_a_close_and_the_server_goes_on(app: Any, junk: bytes) -> None:
    """Whatever the bytes (then the blank line that ends headers): an HTTP status line
    or nothing, never a hang past the deadline, and the next scrape is answered."""
    with ours(app, header_deadline=1.0) as (port, server):
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            sock.sendall(junk + b"\r\n\r\n")
            started = time.monotonic()
            data = b""
            while chunk := sock.recv(65536):
                data += chunk
            assert time.monotonic() - started < 8
        assert data == b"" or data.startswith(b"HTTP/1.1 "), data[:80]
        assert ask(port)[0] == 200
        wait_for(lambda: server.connections() == 0, timeout=20, what="all closed")


PAUSE_CHILD = r"""
import json, os, resource, sys, threading, time
from edgemodbus.northbound.metrics_http import MetricsHttpServer

def app(environ, start_response):
    start_response("200 OK", [("Content-Type", "text/plain")])
    return [b"ok\n"]

resource.setrlimit(resource.RLIMIT_NOFILE, (64, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
server = MetricsHttpServer("127.0.0.1", 0, app)
threading.Thread(target=server.serve_forever, daemon=True).start()
held = []
try:
    while True:
        held.append(os.open(os.devnull, os.O_RDONLY))
except OSError:
    pass
print(server.server_port, flush=True)
sys.stdin.readline()                      # the parent connected: accept fails meanwhile
cpu = time.process_time()
time.sleep(2.0)
cpu = time.process_time() - cpu
counts = dict(server.counts)
for fd in held:
    os.close(fd)
print(json.dumps({"cpu": cpu, **counts}), flush=True)
sys.stdin.readline()                      # the parent scraped
server.shutdown()
server.server_close()
"""


def test_at_the_fd_limit_with_nothing_to_evict_accepting_pauses() -> None:
    """Every fd of the process taken elsewhere (none of them the exporter's): accept
    fails with EMFILE and accepting pauses, 50 ms doubling, instead of spinning; once
    fds are free the waiting scrape is answered."""
    proc = subprocess.Popen([sys.executable, "-c", PAUSE_CHILD], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdin is not None and proc.stdout is not None
    conn: http.client.HTTPConnection | None = None
    try:
        port = int(proc.stdout.readline())
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=20)
        conn.request("GET", "/metrics")  # waits in the backlog
        proc.stdin.write("connected\n")
        proc.stdin.flush()
        figures = json.loads(proc.stdout.readline())
        assert 1 <= figures["acceptErrors"] <= 8, figures  # 2 s of 50, 100, 200 ... ms
        assert figures["cpu"] < 0.2, figures
        resp = conn.getresponse()
        assert resp.status == 200 and resp.read() == b"ok\n"
        proc.stdin.write("scraped\n")
        proc.stdin.flush()
        assert proc.wait(20) == 0
    finally:
        if conn is not None:
            conn.close()
        if proc.poll() is None:
            proc.kill()
        proc.wait()


def test_the_exporter_exports_its_own_http_counters() -> None:
    """A refused method and an oversize request show in the exporter's own families, read
    through a real scrape of the exporter (MetricsExporter.start)."""
    with MetricsExporter({"port": 0, "host": "127.0.0.1"}) as exporter:
        port = exporter.port
        assert ask(port, "POST")[0] == 405
        assert ask(port, headers={"X-Pad": "x" * 20000})[0] == 431
        status, _, body = ask(port)
    assert status == 200
    text = body.decode()
    assert "edgemodbus_metrics_http_bad_requests_total 1.0" in text, text
    assert "edgemodbus_metrics_http_too_large_total 1.0" in text, text
    assert "edgemodbus_metrics_http_accepted_total 3.0" in text, text
