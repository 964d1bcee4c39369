"""The ``engine`` key on connect-mode lines (config/listen.py, line/endpoint.py,
line/registry.py): where it is allowed, the error naming the field where not, and which
lines the registry puts on a loop thread (plain RTU over TCP without alternates) and
which keep a thread of their own."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from edgemodbus.config import ConfigError, load_device_config
from edgemodbus.line.endpoint import TcpEndpoint, endpoint_for
from edgemodbus.line.loop import LoopLine, loop_serves
from edgemodbus.line.loop_connect import Dialer
from edgemodbus.line.registry import LineRegistry
from tests.peers import free_port
from tests.waiting import wait_for


def comm(**extra: Any) -> dict[str, Any]:
    return {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": 1502,
            "engine": "loop", **extra}


def problems(raw: dict[str, Any]) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_device_config({"communication": raw})
    return [str(p) for p in info.value.problems]


@pytest.mark.parametrize("transport", ["rtu", "mqtt-dtu"])
def test_engine_loop_is_refused_where_the_loop_does_not_serve(transport: str) -> None:
    raw = comm(transport=transport, comPort="/dev/ttyS0", mqttHost="127.0.0.1", dtuId="d1")
    found = [p for p in problems(raw) if p.startswith("communication.engine")]
    assert found == [f"communication.engine 'loop': the loop engine serves transports "
                     f"rtu-over-tcp-server, rtu-over-tcp, tcp, not {transport!r}; "
                     "use engine 'thread'"], found


def test_engine_loop_on_modbus_tcp_reaches_a_loop_line() -> None:
    cfg = load_device_config({"communication": comm(transport="tcp")})
    ep = endpoint_for(cfg.communication)
    assert isinstance(ep, TcpEndpoint) and ep.transport == "tcp" and ep.engine == "loop"
    assert loop_serves(ep)


def test_engine_loop_on_rtu_over_tcp_reaches_the_endpoint() -> None:
    cfg = load_device_config({"communication": comm(loopThreads=2)})
    ep = endpoint_for(cfg.communication)
    assert isinstance(ep, TcpEndpoint)
    assert (ep.engine, ep.loop_threads) == ("loop", 2)
    assert loop_serves(ep)
    thread = endpoint_for(load_device_config({"communication": comm(engine="thread")})
                          .communication)
    assert isinstance(thread, TcpEndpoint) and thread.engine == "thread"
    # one line, one engine: devices of an endpoint must agree (loopThreads aside)
    assert thread != ep and thread.key == ep.key
    assert ep == TcpEndpoint("127.0.0.1", 1502, engine="loop", loop_threads=None)


def test_an_endpoint_names_a_bad_engine() -> None:
    with pytest.raises(ValueError, match=r"engine 'fast': must be one of thread, loop"):
        TcpEndpoint("127.0.0.1", 1502, engine="fast")


@pytest.mark.parametrize(("ep", "why"), [
    (TcpEndpoint("127.0.0.1", 1502, echo=True, engine="loop"),
     "echo: engine 'loop' serves rtu-over-tcp endpoints without the echo option"),
    (TcpEndpoint("127.0.0.1", 1502, framing="wrapped-report", engine="loop"),
     "framing 'wrapped-report': engine 'loop' serves rtu-over-tcp endpoints with framing rtu"),
    (TcpEndpoint("127.0.0.1", 1502, alternates=(("127.0.0.2", 1502),), engine="loop"),
     "alternates: engine 'loop' serves endpoints without alternates"),
    (TcpEndpoint("127.0.0.1", 1502, "tcp", alternates=(("127.0.0.2", 1502),), engine="loop"),
     "alternates: engine 'loop' serves endpoints without alternates"),
])
def test_lines_the_loop_cannot_serve_keep_a_thread(ep: TcpEndpoint, why: str) -> None:
    assert not loop_serves(ep)
    with pytest.raises(ValueError, match=f"{why}; use engine 'thread'"):
        LoopLine(ep, None, Dialer(TcpEndpoint("127.0.0.1", 1502)), None)  # type: ignore[arg-type]


def test_the_registry_puts_a_loop_endpoint_on_a_loop_thread_and_devices_must_agree() -> None:
    registry = LineRegistry()
    port = free_port()
    loop_ep = TcpEndpoint("127.0.0.1", port, engine="loop", loop_threads=1)
    line = registry.acquire(loop_ep)
    try:
        assert isinstance(line, LoopLine) and isinstance(line.connector, Dialer)
        assert not [t for t in threading.enumerate() if t.name.startswith("edgemodbus-line")]
        with pytest.raises(ValueError, match=r"they differ in engine"):
            registry.acquire(TcpEndpoint("127.0.0.1", port))
        # nothing listens there: the connect fails with the line worker's words
        wait_for(lambda: line.last_link_error is not None, what="a failed connect")
        assert "connect failed: Connection refused" in (line.last_link_error or "")
    finally:
        registry.release(line)
    thread_ep = TcpEndpoint("127.0.0.1", port, echo=True, engine="loop")
    line = registry.acquire(thread_ep)  # echo: the loop link does not skip it yet
    try:
        assert type(line).__name__ == "LineWorker"
    finally:
        registry.release(line)


@pytest.mark.parametrize(("extra", "engine"), [({}, "thread"), ({"engine": "loop"}, "loop"),
                                               ({"engine": "thread"}, "thread")])
def test_a_connect_line_is_on_the_loop_only_when_its_device_says_so(
        extra: dict[str, str], engine: str) -> None:
    """The key's default ("loop") is the DTUs'; an rtu-over-tcp endpoint keeps a thread
    unless its device sets the key."""
    raw = {k: v for k, v in comm().items() if k != "engine"}
    cfg = load_device_config({"communication": {**raw, **extra}})
    assert endpoint_for(cfg.effective_parameters()).engine == engine
