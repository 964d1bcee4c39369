"""The gateway's Modbus TCP server (serve mode and the server side of forward mode),
driven by independent masters: pymodbus' client (3.16.1) and Debian's mbpoll, with
pymodbus (own process) as the slaves behind the gateway's line, and raw sockets for the
frames no client sends."""

from __future__ import annotations

import random
import shutil
import socket
import struct
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

import edgemodbus as em
from edgemodbus.northbound.metrics import MetricsExporter
from edgemodbus.serve import ModbusTcpServer, write_exception_code
from tests.conftest import SlaveFactory
from tests.integration.test_metrics import lbl, scrape
from tests.peers import ExceptionRange, PymodbusSlave, default_bit, default_register
from tests.waiting import wait_for

REFUSING = ExceptionRange(300, 302, code=4, unit=1)  # the slave refuses writes there


def items() -> list[dict[str, Any]]:
    regs = [{"name": f"r{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
            for a in range(10)]
    return [
        *regs,
        {"name": "f", "address": "hr:20", "deviceDataType": "UInt32"},
        {"name": "refused", "address": "hr:300", "deviceDataType": "UInt16"},
        {"name": "bit3", "address": "hr:30.3", "deviceDataType": "Boolean"},
        *({"name": f"c{a}", "address": f"coil:{a}", "deviceDataType": "Boolean"}
          for a in range(8)),
        *({"name": f"i{a}", "address": f"ir:{a}", "deviceDataType": "UInt16"}
          for a in range(4)),
    ]


def comm(peer: PymodbusSlave, slave: int, **extra: Any) -> dict[str, Any]:
    base = {"transport": peer.transport, "tcpHost": "127.0.0.1", "tcpPort": peer.port,
            "slaveId": slave, "readTimeout": 500, "readCycle": 50, "retries": 0,
            "reconnectInterval": 200, "offlineAfterFailedCycles": 2}
    base.update(extra)
    return base


class Gateway:
    """Drivers for slaves 1 and 2 of one pymodbus peer and a server: unit 1 serves
    slave 1 at its own addresses, unit 5 the same at +1000, unit 9 forwards to slave 2."""

    def __init__(self, peer: PymodbusSlave, **server: Any) -> None:
        self.peer = peer
        self.drivers: list[em.DriverModbusRtu] = []
        self.cfg1 = em.load_device_config({"organization": {"deviceCode": "meter1"},
                                           "communication": comm(peer, 1),
                                           "addressList": items()})
        self.dev1 = self._start(self.cfg1)
        cfg2 = em.load_device_config({"organization": {"deviceCode": "meter2"},
                                      "communication": comm(peer, 2),
                                      "addressList": items()[:2]})
        self.dev2 = self._start(cfg2)
        self.server = ModbusTcpServer("127.0.0.1", 0, **server)
        try:
            self.server.serve_device(1, self.dev1, self.cfg1)
            self.server.serve_device(5, self.dev1, self.cfg1, offset=1000, max_age=0.5)
            self.server.forward_device(9, self.dev2, timeout=0.5)
            self.server.start()
            self.port = self.server.port
            # every item read once ("refused" never: the slave answers 03 for it)
            wait_for(lambda: all(s["status"] == "Ok" for name, s
                                 in self.dev1.snapshot()["items"].items()
                                 if name != "refused"),
                     what="every item of meter1 read once")
        except BaseException:
            self.close()
            raise

    def _start(self, cfg: em.DeviceConfig) -> em.DriverModbusRtu:
        drv = em.DriverModbusRtu()
        self.drivers.append(drv)
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        return drv

    def client(self, **kw: Any) -> ModbusTcpClient:
        client = ModbusTcpClient("127.0.0.1", port=self.port, timeout=2, retries=0, **kw)
        assert client.connect()
        return client

    def close(self) -> None:
        if hasattr(self, "server"):
            self.server.stop()
        for drv in self.drivers:
            drv.stop_device()


@pytest.fixture
def gateway(slave_factory: SlaveFactory) -> Iterator[Gateway]:
    peer = slave_factory("rtu-over-tcp", units=(1, 2), size=2000,
                         exception_ranges=[REFUSING])
    gw = Gateway(peer, max_connections=4, idle_timeout=1.0)
    try:
        yield gw
    finally:
        gw.close()


def hr(unit: int, address: int, count: int) -> list[int]:
    return [default_register(unit, "hr", a) for a in range(address, address + count)]


# -- serve mode: reads ---------------------------------------------------------------
def read_fresh(gateway: Gateway, client: ModbusTcpClient, unit: int, address: int,
               count: int) -> list[int]:
    """Holding registers of a unit with a max age: a 0B answer is retried only when the
    server counts it as too old (on a loaded machine the slave may not have answered
    within the unit's max age: serve/staleness.py), never an unexplained one."""
    got: list[int] = []

    def counts() -> dict[str, int]:
        return dict(gateway.server.stats()["staleReplies"][unit])

    def answered() -> bool:
        before = counts()
        rr = client.read_holding_registers(address, count=count, device_id=unit)
        if not rr.isError():
            got[:] = rr.registers
            return True
        assert rr.exception_code == 0x0B, rr
        # the server's thread counts it at its next tick (0.1 s)
        wait_for(lambda: sum(counts().values()) > sum(before.values()),
                 what=f"the server counted unit {unit}'s 0B")
        assert counts()["invalid"] == before["invalid"], (before, counts())
        return False

    wait_for(answered, what=f"unit {unit}'s registers {address}+{count}")
    return got


def test_reads_equal_the_slave_with_no_line_traffic(gateway: Gateway) -> None:
    client = gateway.client()
    try:
        line, server = gateway.dev1.stats()["line"], gateway.server.stats()
        rr = client.read_holding_registers(0, count=10, device_id=1)
        assert not rr.isError() and rr.registers == hr(1, 0, 10)
        rr = client.read_holding_registers(20, count=2, device_id=1)
        assert rr.registers == hr(1, 20, 2)
        rr = client.read_input_registers(0, count=4, device_id=1)
        assert rr.registers == [default_register(1, "ir", a) for a in range(4)]
        rr = client.read_coils(0, count=8, device_id=1)
        assert rr.bits[:8] == [default_bit(1, "co", a) for a in range(8)]
        # the register of a bit item holds that bit, 0 elsewhere
        rr = client.read_holding_registers(30, count=1, device_id=1)
        assert rr.registers == [default_register(1, "hr", 30) & 0x0008]
        # unit 5: the same device at +1000
        assert read_fresh(gateway, client, 5, 1003, 3) == hr(1, 3, 3)
        # the server read nothing itself: every read answered from the image, no job
        # (read on demand, forward, write) on the line, only the polling used it (a
        # count of the line's requests would depend on how long the reads took)
        after = gateway.dev1.stats()["line"]
        assert (after["jobs"], after["forwarded"]) == (line["jobs"], line["forwarded"])
        assert gateway.server.stats()["cachedReplies"] - server["cachedReplies"] == 6
        assert gateway.server.stats()["forwarded"] == server["forwarded"]
    finally:
        client.close()


def test_values_follow_the_slave(gateway: Gateway) -> None:
    gateway.peer.set_registers(1, "hr", 2, [4242])
    client = gateway.client()
    try:
        wait_for(lambda: client.read_holding_registers(2, count=1, device_id=1).registers
                 == [4242], what="the new value through the gateway")
    finally:
        client.close()


def test_exceptions_of_serve_mode(gateway: Gateway) -> None:
    client = gateway.client()
    try:
        # unmapped registers (10..19), a read reaching them, an unmapped area: 02
        assert client.read_holding_registers(10, count=1, device_id=1).exception_code == 2
        assert client.read_holding_registers(8, count=4, device_id=1).exception_code == 2
        assert client.read_discrete_inputs(0, count=1, device_id=1).exception_code == 2
        # an item the slave refuses to read is Invalid: 0B
        assert client.read_holding_registers(300, count=1, device_id=1).exception_code == 0x0B
        # a unit nobody serves: 0A (gateway path unavailable)
        assert client.read_holding_registers(0, count=1, device_id=77).exception_code == 0x0A
        # a function the server does not do: 01
        assert client.report_device_id(device_id=1).exception_code == 1
    finally:
        client.close()


def test_invalid_and_stale_items_get_0b(gateway: Gateway) -> None:
    client = gateway.client()
    try:
        assert client.read_holding_registers(1000, count=1, device_id=5).registers == hr(1, 0, 1)
        gateway.peer.stop()  # the slave is gone: items go Invalid
        wait_for(lambda: gateway.dev1.snapshot()["items"]["r0"]["status"] == "Invalid",
                 what="r0 Invalid")
        client.close()
        client = gateway.client()
        assert client.read_holding_registers(0, count=1, device_id=1).exception_code == 0x0B
        assert client.read_coils(0, count=1, device_id=1).exception_code == 0x0B
    finally:
        client.close()


def test_max_age_turns_reads_into_0b(gateway: Gateway, ) -> None:
    """Unit 5 has maxAge 0.5 s: stop the polling without marking the items Invalid (the
    device stopped: its items keep their last values) and its reads go 0B; unit 1,
    without an age limit, still answers."""
    client = gateway.client()
    try:
        # fresh within 0.5 s once polling runs (a loaded machine may answer 0B first)
        wait_for(lambda: client.read_holding_registers(1000, count=1, device_id=5).registers
                 == hr(1, 0, 1), what="unit 5 answering while polled")
        gateway.dev1.stop_device()
        time.sleep(0.8)  # pacing: the values age past maxAge 0.5 s
        client.close()
        client = gateway.client()
        assert client.read_holding_registers(1000, count=1, device_id=5).exception_code == 0x0B
        assert client.read_holding_registers(0, count=1, device_id=1).registers == hr(1, 0, 1)
    finally:
        client.close()


# -- serve mode: writes ----------------------------------------------------------------
def test_writes_land_on_the_slave(gateway: Gateway) -> None:
    client = gateway.client()
    peer = gateway.peer
    try:
        assert not client.write_register(3, 777, device_id=1).isError()
        assert peer.registers(1, "hr", 3) == [777]  # confirmed before the reply came
        assert client.read_holding_registers(3, count=1, device_id=1).registers == [777]
        assert not client.write_registers(20, [0x1234, 0x5678], device_id=1).isError()
        assert peer.registers(1, "hr", 20, 2) == [0x1234, 0x5678]
        assert not client.write_registers(1005, [11, 12], device_id=5).isError()
        assert peer.registers(1, "hr", 5, 2) == [11, 12]
        on = not default_bit(1, "co", 2)
        assert not client.write_coil(2, on, device_id=1).isError()
        assert peer.bits(1, "co", 2) == [on]
        assert not client.write_coils(4, [True, False, True], device_id=1).isError()
        assert peer.bits(1, "co", 4, 3) == [True, False, True]
        assert gateway.server.stats()["writes"] == 5
    finally:
        client.close()


def test_refused_writes_get_their_exception(gateway: Gateway) -> None:
    client = gateway.client()
    try:
        # the slave answers 04 for register 300: passed on
        assert client.write_register(300, 1, device_id=1).exception_code == 4
        # half of the 2-register item f: 02; an unmapped register: 02; a bit item's
        # register (read-only here): 02; an input register area cannot be written at all
        assert client.write_register(21, 1, device_id=1).exception_code == 2
        assert client.write_register(12, 1, device_id=1).exception_code == 2
        assert client.write_register(30, 8, device_id=1).exception_code == 2
        # the slave gone: 0B after its timeout
        gateway.peer.stop()
        client.close()
        client = gateway.client()
        assert client.write_register(3, 5, device_id=1).exception_code == 0x0B
    finally:
        client.close()


def test_write_exception_code_mapping() -> None:
    assert write_exception_code("r3: exception 0x02 (illegal data address)") == 2
    assert write_exception_code("r3: exception 0x04 (slave device failure)") == 4
    assert write_exception_code("r3: exception 0x06 (slave device busy)") == 4
    assert write_exception_code("r3: no response (timeout)") == 0x0B


# -- forward mode -----------------------------------------------------------------------
def test_forward_passes_requests_and_replies(gateway: Gateway) -> None:
    client = gateway.client()
    peer = gateway.peer
    try:
        # any address of slave 2, not only its items
        rr = client.read_holding_registers(500, count=5, device_id=9)
        assert rr.registers == hr(2, 500, 5)
        assert not client.write_register(600, 99, device_id=9).isError()
        assert peer.registers(2, "hr", 600) == [99]
        # the slave's own exception (2000 registers: 2000 is past the end)
        assert client.read_holding_registers(1999, count=2, device_id=9).exception_code == 2
        # Report Server ID (FC 0x11) is forwarded: the slave's own answer
        ident = client.report_device_id(device_id=9)
        assert not ident.isError(), ident
        assert ident.identifier, ident
        # a function forward mode does not send (0x2B, device identification): 01
        assert client.read_device_information(device_id=9).exception_code == 1
        assert gateway.dev2.stats()["line"]["forwarded"] >= 3
        peer.stop()
        client.close()
        client = gateway.client()  # (the stop may take longer than the idle timeout)
        # no reply (0B), or the line found down (0A: gateway path unavailable)
        assert client.read_holding_registers(0, count=1, device_id=9).exception_code in (
            0x0A, 0x0B)
    finally:
        client.close()


# -- connections ------------------------------------------------------------------------
def mbap(tid: int, unit: int, pdu: bytes, proto: int = 0, length: int | None = None) -> bytes:
    return struct.pack(">HHHB", tid, proto, len(pdu) + 1 if length is None else length,
                       unit) + pdu


def recv_adu(sock: socket.socket) -> bytes:
    head = b""
    while len(head) < 6:
        chunk = sock.recv(6 - len(head))
        if not chunk:
            return head
        head += chunk
    (length,) = struct.unpack(">H", head[4:6])
    body = b""
    while len(body) < length:
        body += sock.recv(length - len(body))
    return head + body


def closed(sock: socket.socket, timeout: float = 3.0) -> bool:
    sock.settimeout(timeout)
    try:
        return sock.recv(100) == b""
    except ConnectionResetError:
        return True


def test_bad_frames_do_not_disturb_the_others(gateway: Gateway) -> None:
    client = gateway.client()
    bad = [socket.create_connection(("127.0.0.1", gateway.port)) for _ in range(3)]
    try:
        bad[0].sendall(mbap(1, 1, b"\x03\x00\x00\x00\x01", proto=7))  # not Modbus
        bad[1].sendall(mbap(1, 1, b"\x03\x00\x00\x00\x01", length=1000))  # a bad length
        # an unknown function gets 01, a read too short for its function 03, and the
        # connection stays; two requests in one segment both get answers, in order
        bad[2].sendall(mbap(7, 1, b"\x41\x00") + mbap(8, 1, b"\x03\x00\x00"))
        assert recv_adu(bad[2]) == mbap(7, 1, b"\xc1\x01")
        assert recv_adu(bad[2]) == mbap(8, 1, b"\x83\x03")
        # a quantity out of range: 03 (Application Protocol 6.3)
        bad[2].sendall(mbap(10, 1, b"\x03\x00\x00\x00\x7e"))
        assert recv_adu(bad[2]) == mbap(10, 1, b"\x83\x03")
        bad[2].sendall(mbap(9, 1, b"\x03\x00\x00\x00\x01"))
        assert recv_adu(bad[2]) == mbap(9, 1, b"\x03\x02" + struct.pack(">H", hr(1, 0, 1)[0]))
        assert closed(bad[0]) and closed(bad[1])
        assert client.read_holding_registers(0, count=2, device_id=1).registers == hr(1, 0, 2)
        assert gateway.server.stats()["closedBad"] == 2
    finally:
        for s in bad:
            s.close()
        client.close()


def test_every_answer_is_counted_before_the_master_holds_it(gateway: Gateway) -> None:
    """The server's counters (requests, cachedReplies, exceptions by code) already count
    an answer when the master has it: a stats read right after each reply equals a tally
    kept here.  cachedReplies was counted after the reply was sent (csrc/emb_serve.c), so
    about half such reads missed the last reply, and a test asserting the count after
    its reads failed on a loaded machine."""
    kinds = [  # (unit, PDU, the exception code expected, 0: a reply from the image)
        (1, b"\x03\x00\x00\x00\x0a", 0), (1, b"\x01\x00\x00\x00\x08", 0),
        (1, b"\x04\x00\x00\x00\x04", 0), (5, b"\x03\x03\xe8\x00\x01", None),
        (1, b"\x03\x00\x0a\x00\x01", 2), (1, b"\x03\x01\x2c\x00\x01", 0x0B),
        (77, b"\x03\x00\x00\x00\x01", 0x0A), (1, b"\x11", 1)]
    rng = random.Random(25)
    first = gateway.server.stats()
    requests, cached = first["requests"], first["cachedReplies"]
    exceptions = dict(first["exceptions"])
    with socket.create_connection(("127.0.0.1", gateway.port)) as sock:
        sock.settimeout(5)
        for tid in range(1000):
            unit, pdu, code = rng.choice(kinds)
            sock.sendall(mbap(tid, unit, pdu))
            reply = recv_adu(sock)
            assert reply[:2] == tid.to_bytes(2, "big"), (tid, reply)
            got = reply[8] if reply[7] & 0x80 else 0
            if code is None:  # unit 5 (maxAge 0.5 s): 0B while the polling is late
                assert got in (0, 0x0B), (unit, pdu, reply)
            else:
                assert got == code, (unit, pdu, reply)
            requests += 1
            if got:
                exceptions[got] = exceptions.get(got, 0) + 1
            else:
                cached += 1
            now = gateway.server.stats()
            assert (now["requests"], now["cachedReplies"], now["exceptions"]) == (
                requests, cached, exceptions), (tid, unit, pdu)


def test_a_function_code_with_the_high_bit_gets_its_own_code_back(gateway: Gateway) -> None:
    """0x80..0xFF are exception replies' codes, no request's (Application Protocol 1.1b3,
    4.1): the exception reply keeps the code (libmodbus's own would wrap 0xFF + 0x80 into
    0x7F, a normal reply's code); found by csrc/fuzz/fuzz_serve.c."""
    with socket.create_connection(("127.0.0.1", gateway.port)) as sock:
        sock.settimeout(5)
        for tid, (unit, fc, code) in enumerate([(1, 0xFF, 1), (1, 0x83, 1), (77, 0xFF, 0x0A),
                                                (9, 0x90, 1), (77, 0x7F, 0x0A)]):
            sock.sendall(mbap(tid, unit, bytes([fc, 0, 0, 0, 1])))
            assert recv_adu(sock) == mbap(tid, unit, bytes([fc | 0x80, code])), (unit, fc)
        sock.sendall(mbap(9, 1, b"\x03\x00\x00\x00\x01"))  # the connection is fine
        assert recv_adu(sock)[7:9] == b"\x03\x02"


def test_connection_cap_and_idle_timeout(gateway: Gateway) -> None:
    socks = [socket.create_connection(("127.0.0.1", gateway.port)) for _ in range(4)]
    try:
        wait_for(lambda: gateway.server.stats()["connections"] == 4, what="4 connections")
        extra = socket.create_connection(("127.0.0.1", gateway.port))
        try:
            assert closed(extra)  # the fifth is over the cap of 4
        finally:
            extra.close()
        assert gateway.server.stats()["refused"] == 1
        # the others are served until idle for 1 s
        socks[0].sendall(mbap(1, 1, b"\x03\x00\x00\x00\x01"))
        assert recv_adu(socks[0])[7:9] == b"\x03\x02"
        assert all(closed(s, timeout=3.0) for s in socks)
        wait_for(lambda: gateway.server.stats()["closedIdle"] == 4, timeout=20,
                 what="4 idle connections closed and counted")
    finally:
        for s in socks:
            s.close()


def test_several_masters_at_once(gateway: Gateway) -> None:
    clients = [gateway.client() for _ in range(4)]
    try:
        for _ in range(20):
            for k, client in enumerate(clients):
                rr = client.read_holding_registers(k, count=4, device_id=1)
                assert rr.registers == hr(1, k, 4)
    finally:
        for client in clients:
            client.close()


# -- mbpoll ------------------------------------------------------------------------------
MBPOLL = shutil.which("mbpoll")


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed (make deps)")
def test_mbpoll_reads_and_writes_both_modes(gateway: Gateway) -> None:
    def mbpoll(*args: str) -> str:
        assert MBPOLL is not None
        proc = subprocess.run([MBPOLL, "-m", "tcp", "-p", str(gateway.port), "-0", "-1",
                               "-o", "2", *args, "127.0.0.1"],
                              capture_output=True, text=True, timeout=10, check=False)
        return proc.stdout + proc.stderr

    def values(text: str) -> dict[int, int]:
        found = {}
        for line in text.splitlines():
            if line.startswith("[") and "]:" in line:
                ref, _, value = line.partition("]:")
                found[int(ref[1:])] = int(value.split()[0])
        return found

    out = mbpoll("-a", "1", "-r", "0", "-c", "5")
    assert values(out) == dict(enumerate(hr(1, 0, 5))), out
    out = mbpoll("-a", "9", "-r", "700", "-c", "3")
    assert values(out) == {700 + k: v for k, v in enumerate(hr(2, 700, 3))}, out
    # writes: values after the host
    proc = subprocess.run([str(MBPOLL), "-m", "tcp", "-p", str(gateway.port), "-0", "-1",
                           "-a", "1", "-r", "4", "127.0.0.1", "321"],
                          capture_output=True, text=True, timeout=10, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert gateway.peer.registers(1, "hr", 4) == [321]
    out = mbpoll("-a", "1", "-r", "12", "-c", "1")
    assert "Illegal data address" in out, out


# -- Prometheus ------------------------------------------------------------------------
def test_prometheus_exports_the_servers_counters(gateway: Gateway) -> None:
    """The real exporter, scraped over HTTP: the server's counters (label ``listen``),
    its exception replies by code and the connections open now."""
    listen = f"127.0.0.1:{gateway.port}"
    client = gateway.client()
    bad = socket.create_connection(("127.0.0.1", gateway.port))
    try:
        with MetricsExporter({"port": 0}) as exporter:
            exporter.set_server_stats(gateway.server)
            bad.sendall(mbap(1, 1, b"\x03\x00\x00\x00\x01", proto=7))  # not Modbus
            assert closed(bad)
            assert client.read_holding_registers(10, count=1, device_id=1).exception_code == 2
            assert client.read_holding_registers(0, count=1, device_id=77).exception_code == 10
            assert not client.write_register(3, 777, device_id=1).isError()
            assert client.read_holding_registers(500, count=2, device_id=9).registers == hr(
                2, 500, 2)
            assert client.read_holding_registers(0, count=2, device_id=1).registers == hr(
                1, 0, 2)
            _, samples = scrape(exporter.port)
            stats = gateway.server.stats()
    finally:
        bad.close()
        client.close()
    at = lbl(listen=listen)
    expect = {"accepted": 2, "refused": 0, "closed_idle": 0, "closed_bad": 1,
              "closed_by_peer": 0, "requests": 5, "cached_replies": 1, "writes": 1,
              "write_errors": 0, "forwarded": 1}
    assert {k: samples[(f"edgemodbus_serve_{k}_total", at)] for k in expect} == expect
    assert samples[("edgemodbus_serve_exceptions_total", lbl(listen=listen, code="2"))] == 1
    assert samples[("edgemodbus_serve_exceptions_total", lbl(listen=listen, code="10"))] == 1
    assert samples[("edgemodbus_serve_connections", at)] == 1  # the client's
    assert stats["accepted"] == 2 and stats["exceptions"] == {2: 1, 10: 1}
