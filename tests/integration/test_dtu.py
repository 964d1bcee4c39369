"""Listen mode (rtu-over-tcp-server): DTUs dial in to the driver's listen port.

The DTUs are our simulator in DTU-client mode (``Simulator.dial``): it connects,
registers and answers as RTU slaves.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import Area, DeviceDriverStatus, ItemStatus
from edgemodbus.line import dtu_registry
from edgemodbus.sim import Simulator, default_register
from tests.engines import with_engine
from tests.waiting import wait_for


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def dtu_device(port: int, dtu_id: str, slave: int = 1, addresses: tuple[int, ...] = (0, 1, 7),
               **extra: Any) -> em.DeviceConfig:
    comm: dict[str, Any] = {
        "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
        "dtuId": dtu_id, "registration": "text", "registrationTimeout": 400,
        "slaveId": slave, "readTimeout": 300, "readCycle": 100, "reconnectInterval": 300,
        "byteTimeout": 50,
    }
    comm.update(extra)
    return em.load_device_config({
        "organization": {"deviceCode": f"{dtu_id or 'dtu'}-{slave}"},
        "communication": with_engine(comm),
        "addressList": [{"name": f"r{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                        for a in addresses],
    })


@contextmanager
def running(*cfgs: em.DeviceConfig) -> Iterator[list[em.DriverModbusRtu]]:
    drivers = []
    try:
        for cfg in cfgs:
            drv = em.DriverModbusRtu()
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            drivers.append(drv)
        yield drivers
    finally:
        for drv in drivers:
            drv.stop_device()


def values(cfg: em.DeviceConfig) -> list[Any]:
    return [it.value if it.status is ItemStatus.OK else None for it in cfg.address_list]


def ok(cfg: em.DeviceConfig) -> Callable[[], bool]:
    return lambda: all(it.status is ItemStatus.OK for it in cfg.address_list)


@pytest.mark.usefixtures("engine")
def test_two_dtus_on_one_port_each_feed_their_own_devices() -> None:
    port = free_port()
    a1, a2 = dtu_device(port, "DTU-A", 1), dtu_device(port, "DTU-A", 2)
    b1 = dtu_device(port, "DTU-B", 1)  # same slave id, other DTU
    with ExitStack() as stack:
        sim_a = stack.enter_context(Simulator(slaves=[1, 2]))
        sim_b = stack.enter_context(Simulator(slaves=[1]))
        sim_b.slave(1).set_registers(Area.HOLDING_REGISTER, 0, [11, 12, 13, 14, 15, 16, 17, 18])
        stack.enter_context(running(a1, a2, b1))
        listener = dtu_registry.listener("127.0.0.1", port)
        assert listener is not None  # one listener serves both DTUs
        sim_b.dial("127.0.0.1", port, registration=b"DTU-B")
        sim_a.dial("127.0.0.1", port, registration=b"DTU-A\r\n")
        for cfg in (a1, a2, b1):
            wait_for(ok(cfg), what=f"{cfg.organization.device_code} Ok")
        assert values(a1) == [default_register(1, a) for a in (0, 1, 7)]
        assert values(a2) == [default_register(2, a) for a in (0, 1, 7)]
        assert values(b1) == [11, 12, 18]  # never a value from the other DTU
        assert listener.stats["registered"] == 2


@pytest.mark.usefixtures("engine")
def test_not_connected_then_dial_in_then_a_reconnect_replaces_the_old_link() -> None:
    port = free_port()
    cfg = dtu_device(port, "861234567890123", registration="regex",
                     registrationPattern=r"IMEI:(\d{15})", duplicateId="replace")
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RECONNECTING)
        wait_for(lambda: all(it.status is ItemStatus.INVALID for it in cfg.address_list))
        assert all("DTU not connected" in (it.error_reason or "") for it in cfg.address_list)
        first = sim.dial("127.0.0.1", port, registration=b"IMEI:861234567890123\r\n")
        wait_for(ok(cfg), what="values after dial-in")
        assert drv.device_driver_status is DeviceDriverStatus.RUNNING
        second = sim.dial("127.0.0.1", port, registration=b"IMEI:861234567890123\r\n")
        wait_for(lambda: first.closed, what="the old connection closed")
        assert not second.closed
        requests = drv.stats()["requests"]
        wait_for(lambda: drv.stats()["requests"] > requests + 3, what="polling on the new link")
        assert drv.device_driver_status is DeviceDriverStatus.RUNNING
        assert drv.stats()["line"]["reconnects"] >= 1
        second.close()  # the DTU goes away: Reconnecting, items Invalid
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RECONNECTING)
        wait_for(lambda: all("DTU not connected" in (it.error_reason or "")
                             for it in cfg.address_list), what="DTU not connected")


@pytest.mark.usefixtures("engine")
def test_a_write_reaches_the_dtus_slave_and_is_read_back() -> None:
    port = free_port()
    cfg = dtu_device(port, "DTU-W", 1)
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        sim.dial("127.0.0.1", port, registration=b"DTU-W")
        wait_for(ok(cfg), what="values after dial-in")
        assert drv.write_address("r1", 4321) == (True, None)
        assert sim.slave(1).get_registers(Area.HOLDING_REGISTER, 1) == [4321]
        wait_for(lambda: values(cfg)[1] == 4321, what="the written value read back")
        assert values(cfg)[0] == default_register(1, 0)


@pytest.mark.usefixtures("engine")
def test_a_silent_slave_goes_offline_while_the_neighbour_dtu_keeps_its_cycle() -> None:
    port = free_port()
    silent = dtu_device(port, "DTU-S", 9, readTimeout=100)  # the simulator serves slave 1
    good = dtu_device(port, "DTU-G", 1)
    with ExitStack() as stack:
        sim_s = stack.enter_context(Simulator(slaves=[1]))
        sim_g = stack.enter_context(Simulator(slaves=[1]))
        drv_s, drv_g = stack.enter_context(running(silent, good))
        sim_s.dial("127.0.0.1", port, registration=b"DTU-S")
        sim_g.dial("127.0.0.1", port, registration=b"DTU-G")
        wait_for(ok(good), what="the good DTU's values")
        wait_for(lambda: drv_s.device_driver_status is DeviceDriverStatus.OFFLINE,
                 what="the silent slave offline")
        requests = drv_g.stats()["requests"]
        wait_for(lambda: drv_g.stats()["requests"] > requests + 5, what="the good DTU polled")
        assert values(good) == [default_register(1, a) for a in (0, 1, 7)]
        assert drv_g.device_driver_status is DeviceDriverStatus.RUNNING


def test_keep_existing_refuses_a_second_connection_while_the_first_answers() -> None:
    """The default duplicateId: the newcomer is held for the registration timeout and
    closed, because the connection in use answered meanwhile; then, once that one is
    gone, the next dial takes the id at once."""
    port = free_port()
    cfg = dtu_device(port, "D7")
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        first = sim.dial("127.0.0.1", port, registration=b"D7\r\n")
        wait_for(ok(cfg), what="values after dial-in")
        second = sim.dial("127.0.0.1", port, registration=b"D7\r\n")
        wait_for(lambda: second.closed, what="the newcomer closed")
        assert not first.closed
        listener = dtu_registry.listener("127.0.0.1", port)
        assert listener is not None
        assert listener.stats["duplicateRefused"] == 1 and listener.stats["replaced"] == 0
        first.close()
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RECONNECTING)
        sim.dial("127.0.0.1", port, registration=b"D7\r\n")
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RUNNING)
        assert listener.stats["duplicateRefused"] == 1


def test_unknown_and_silent_dtus_are_closed_after_the_timeout_and_take_no_place() -> None:
    port = free_port()
    cfg = dtu_device(port, "GOOD", registrationTimeout=300)
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        good = sim.dial("127.0.0.1", port, registration=b"GOOD")
        wait_for(ok(cfg))
        started = time.monotonic()
        unknown = sim.dial("127.0.0.1", port, registration=b"EVIL")
        silent = sim.dial("127.0.0.1", port)
        wait_for(lambda: unknown.closed and silent.closed, what="both closed")
        assert time.monotonic() - started >= 0.25  # held until the registration timeout
        listener = dtu_registry.listener("127.0.0.1", port)
        assert listener is not None
        assert listener.stats["unknown"] == 1 and listener.stats["silent"] == 1
        assert not good.closed
        requests = drv.stats()["requests"]
        wait_for(lambda: drv.stats()["requests"] > requests + 2)
        assert drv.device_driver_status is DeviceDriverStatus.RUNNING


def test_without_registration_the_single_dtu_takes_the_connection() -> None:
    port = free_port()
    cfg = dtu_device(port, "", registration="none", tcpPort=port, listenPort=None)
    with Simulator(slaves=[1]) as sim, running(cfg):
        sim.dial("127.0.0.1", port)
        wait_for(ok(cfg))
        assert values(cfg) == [default_register(1, a) for a in (0, 1, 7)]


@pytest.mark.usefixtures("engine")
def test_heartbeats_are_discarded_wherever_they_arrive() -> None:
    port = free_port()
    cfg = dtu_device(port, "DTU7", heartbeat="HB")
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        client = sim.dial("127.0.0.1", port, registration=b"HBDTU7", heartbeat=b"HB",
                          heartbeat_interval=0.03, heartbeat_before_reply=True)
        wait_for(ok(cfg))
        responses = drv.stats()["responses"]
        wait_for(lambda: drv.stats()["responses"] > responses + 5)
        stats = drv.stats()
        assert values(cfg) == [default_register(1, a) for a in (0, 1, 7)]
        assert stats["timeouts"] == 0 and stats["protocolErrors"] == 0
        assert stats["line"]["heartbeats"] >= 5
        assert client.heartbeats_sent >= stats["line"]["heartbeats"] - 1


def test_devices_on_one_port_must_agree_on_its_registration() -> None:
    port = free_port()
    a = dtu_device(port, "A")
    b = dtu_device(port, "0B", registration="hex")
    with running(a):
        drv = em.DriverModbusRtu()
        try:
            drv.start_device(b.organization, b.communication, b.address_list)
        except ValueError as exc:
            assert "registration 'hex'" in str(exc)
        else:
            drv.stop_device()
            raise AssertionError("conflicting registration accepted")
    assert dtu_registry.listener("127.0.0.1", port) is None  # stopped with its last device


class SegmentedDtu:
    """A DTU that dials in and sends its registration in TCP segments with short pauses
    between them, then passes bytes through to a simulator's TCP port (its slaves)."""

    def __init__(self, port: int, segments: Sequence[bytes], slave_port: int,
                 pause: float = 0.05) -> None:
        self._down = socket.create_connection(("127.0.0.1", slave_port))
        self._up = socket.create_connection(("127.0.0.1", port))
        self._up.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for i, segment in enumerate(segments):
            if i:
                time.sleep(pause)  # pacing: the segments apart
            self._up.sendall(segment)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._relay, name="segmented-dtu")
        self._thread.start()

    def _relay(self) -> None:
        pair = {self._up: self._down, self._down: self._up}
        while not self._stop.is_set():
            for sock in select.select(list(pair), [], [], 0.05)[0]:
                try:
                    data = sock.recv(4096)
                except OSError:
                    return
                if not data:
                    return
                pair[sock].sendall(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._up.close()
        self._down.close()


@pytest.mark.parametrize(("mode", "short", "long", "short_reg", "long_segments"), [
    ("text", "DTU1", "DTU10", b"DTU1", [b"DTU1", b"0"]),
    ("hex", "0102", "010203", b"\x01\x02", [b"\x01\x02", b"\x03"]),
    ("regex", "1", "10", b"ID:1\r\n", [b"ID:", b"1", b"0\r\n"]),
])
def test_a_registration_in_segments_is_never_taken_for_an_id_it_begins_with(
        mode: str, short: str, long: str, short_reg: bytes, long_segments: list[bytes]) -> None:
    """DTU10's registration arrives as "DTU1", then "0" (hex: 01 02, then 03; regex:
    "ID:", "1", "0\\r\\n"): it is DTU10's, not DTU1's.  Each device shows its own DTU's
    values, and DTU10's never appear on DTU1's device with status Ok."""
    port = free_port()
    extra: dict[str, Any] = {"registration": mode, "registrationTimeout": 3000}
    if mode == "regex":
        extra["registrationPattern"] = r"ID:(\d+)"
    short_cfg = dtu_device(port, short, **extra)
    long_cfg = dtu_device(port, long, **extra)
    long_values = [2000, 2001, 2007]
    on_short: list[tuple[Any, ItemStatus]] = []
    with ExitStack() as stack:
        sim_short = stack.enter_context(Simulator(slaves=[1]))
        sim_long = stack.enter_context(Simulator(slaves=[1]))
        sim_long.slave(1).set_registers(Area.HOLDING_REGISTER, 0, list(range(2000, 2008)))
        short_drv, _ = stack.enter_context(running(short_cfg, long_cfg))
        short_drv.address_updated_callback = lambda it: on_short.append((it.value, it.status))

        def long_value_on_short() -> bool:
            return any(v in long_values and st is ItemStatus.OK for v, st in on_short)

        started = time.monotonic()
        relay = SegmentedDtu(port, long_segments, sim_long.serve_tcp("127.0.0.1", 0))
        stack.callback(relay.close)
        wait_for(lambda: ok(long_cfg)() or long_value_on_short(), what=f"{long} Ok")
        assert not long_value_on_short(), on_short
        assert values(long_cfg) == long_values
        assert time.monotonic() - started < 2.5  # well before the registration timeout
        sim_short.dial("127.0.0.1", port, registration=short_reg)
        wait_for(ok(short_cfg), what=f"{short} Ok")
        assert values(short_cfg) == [default_register(1, a) for a in (0, 1, 7)]
        requests = sim_long.slave(1).stats()["requests"]
        wait_for(lambda: sim_long.slave(1).stats()["requests"] > requests + 3)
        assert values(long_cfg) == long_values and values(short_cfg) == [
            default_register(1, a) for a in (0, 1, 7)]
        assert not long_value_on_short(), on_short
        listener = dtu_registry.listener("127.0.0.1", port)
        assert listener is not None
        assert listener.stats["registered"] == 2 and listener.stats["unknown"] == 0


def test_a_full_port_evicts_its_oldest_idle_connection_for_a_dtu() -> None:
    """maxUnregistered idle connections do not keep a DTU out: when the port is full, the
    oldest connection that has sent nothing for the quiet gap makes room."""
    port = free_port()
    cfg = dtu_device(port, "D9", maxUnregistered=3, registrationTimeout=5000)
    with Simulator(slaves=[1]) as sim, running(cfg), ExitStack() as stack:
        listener = dtu_registry.listener("127.0.0.1", port)
        assert listener is not None
        idle = [stack.enter_context(socket.create_connection(("127.0.0.1", port)))
                for _ in range(3)]
        wait_for(lambda: listener.stats["unregistered"] == 3, what="three waiting")
        time.sleep(0.6)  # pacing: longer than the quiet gap: they are idle now
        sim.dial("127.0.0.1", port, registration=b"D9\r\n")
        wait_for(ok(cfg), what="the DTU polled")
        stats = listener.stats
        assert stats["evicted"] == 1 and stats["refusedPortCap"] == 0
        assert stats["unregistered"] == 2
        oldest = idle[0]
        oldest.settimeout(2)
        assert oldest.recv(1) == b""  # the oldest was closed


def test_the_port_s_engine_key_puts_its_dtus_on_a_loop_thread() -> None:
    """``engine: "loop"`` on the devices of a port (no process-wide setting): their
    line is served by a loop thread; a device that disagrees is refused by name."""
    port = free_port()
    cfg = dtu_device(port, "DTU-K", 1, engine="loop", loopThreads=1)
    with Simulator(slaves=[1]) as sim, running(cfg):
        loops = [t.name for t in threading.enumerate() if t.name.startswith("edgemodbus-loop")]
        assert len(loops) == 1
        assert not [t for t in threading.enumerate() if "DTU-K" in t.name]  # no line thread
        sim.dial("127.0.0.1", port, registration=b"DTU-K")
        wait_for(ok(cfg), what="values on the loop engine")
        assert values(cfg) == [default_register(1, a) for a in (0, 1, 7)]
        other = dtu_device(port, "DTU-L", 1, engine="thread")
        with pytest.raises(ValueError, match=r"engine 'thread' \(the port has 'loop'\)"):
            em.DriverModbusRtu().start_device(other.organization, other.communication,
                                              other.address_list)


def test_the_loop_is_the_default_for_plain_dtus_and_thread_stays_selectable(
        ) -> None:
    """No ``engine`` key ("auto"): a plain DTU's line is on a loop thread, a
    wrapped-report DTU's keeps a line thread (its reports are applied in C there);
    ``engine: "thread"`` (another port) gives a DTU a line thread of its own."""
    plain_port, thread_port, wrapped_port = free_port(), free_port(), free_port()
    plain = dtu_device(plain_port, "DEF-P", 1)
    threaded = dtu_device(thread_port, "DEF-T", 1, engine="thread")
    wrapped = dtu_device(wrapped_port, "DEF-W", 1, framing="wrapped-report")
    assert plain.communication.engine == "auto"

    def line_threads(dtu_id: str) -> list[str]:
        return [t.name for t in threading.enumerate()
                if t.name.startswith("edgemodbus-line") and dtu_id in t.name]

    with ExitStack() as stack:
        sims = [stack.enter_context(Simulator(slaves=[1])) for _ in range(2)]
        stack.enter_context(running(plain, threaded, wrapped))
        assert line_threads("DEF-P") == []
        assert [t.name for t in threading.enumerate() if t.name.startswith("edgemodbus-loop")]
        assert len(line_threads("DEF-T")) == 1 and len(line_threads("DEF-W")) == 1
        sims[0].dial("127.0.0.1", plain_port, registration=b"DEF-P")
        sims[1].dial("127.0.0.1", thread_port, registration=b"DEF-T")
        for cfg in (plain, threaded):
            wait_for(ok(cfg), what=f"{cfg.organization.device_code} Ok")
            assert values(cfg) == [default_register(1, a) for a in (0, 1, 7)]
