"""Wrapped report framing (edge MCU: FF AA + register address + RTU frame + 0D) end to
end: unsolicited reports update items, integrity polls and writes go wrapped, bad frames
are dropped and counted.  The peer is our simulator in wrapped mode."""

from __future__ import annotations

import itertools
import select
import socket
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import edgemodbus as em
from edgemodbus.datatypes import Area, DeviceDriverStatus, ItemStatus
from edgemodbus.protocol.wrapped import wrap
from edgemodbus.sim import DtuClient, Simulator
from tests.integration.test_dtu import free_port, wait_for

ADDRESSES = (1, 2, 30, 80)


def wrapped_device(comm: dict[str, Any]) -> em.DeviceConfig:
    base: dict[str, Any] = {
        "framing": "wrapped-report", "slaveId": 1, "readTimeout": 300,
        "reconnectInterval": 300, "byteTimeout": 50,
    }
    base.update(comm)
    return em.load_device_config({
        "organization": {"deviceCode": "mcu"},
        "communication": base,
        "addressList": [{"name": f"r{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                        for a in ADDRESSES],
    })


@contextmanager
def running(cfg: em.DeviceConfig, **callbacks: Any) -> Iterator[em.DriverModbusRtu]:
    drv = em.DriverModbusRtu()
    for name, fn in callbacks.items():
        setattr(drv, name, fn)
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        yield drv
    finally:
        drv.stop_device()


def value_of(cfg: em.DeviceConfig, name: str) -> Any:
    item = next(it for it in cfg.address_list if it.name == name)
    return item.value if item.status is ItemStatus.OK else None


def test_report_only_device_takes_unsolicited_reports_in_listen_mode() -> None:
    port = free_port()
    cfg = wrapped_device({"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "dtuId": "MCU1", "registration": "text",
                          "readCycle": 0, "heartbeatHex": "FE"})
    seen: list[tuple[str, Any]] = []
    with Simulator(slaves=[1]) as sim, running(
        cfg, address_updated_callback=lambda it: seen.append((it.name, it.value))
    ) as drv:
        regs = list(range(100, 180))
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 1, regs)
        client: DtuClient = sim.dial("127.0.0.1", port, registration=b"MCU1", wrapped=True)
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RUNNING)
        # a batch report of 80 registers from address 1 (the seed's second example's shape)
        client.push_report(1, Area.HOLDING_REGISTER, 1, 80)
        wait_for(lambda: value_of(cfg, "r80") is not None, what="batch report applied")
        assert [value_of(cfg, f"r{a}") for a in ADDRESSES] == [100, 101, 129, 179]
        assert ("r30", 129) in seen
        # a single report (seed example 1: address 1 = 773), split over two segments,
        # behind a heartbeat and garbage, plus a frame with a bad CRC
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 1, [773])
        good = bytes.fromhex("FFAA0001010302030578B70D")
        bad_crc = bytes.fromhex("FFAA0001010302030578B80D")
        client.send(b"\xfe" + bad_crc + b"\x00\x13" + good[:5])
        time.sleep(0.05)  # pacing: the segments apart
        client.send(good[5:])
        wait_for(lambda: value_of(cfg, "r1") == 773, what="single report applied")
        stats = drv.stats()
        assert stats["reports"] == 2
        assert stats["line"]["droppedFrames"] == 2  # bad CRC, then the noise 00 13
        # a frame whose length and tail disagree is one drop, its rest is not noise
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 1, [774])
        client.send(bytes.fromhex("FFAA0001010302030578B70E"))
        client.push_report(1, Area.HOLDING_REGISTER, 1, 1)
        wait_for(lambda: value_of(cfg, "r1") == 774, what="report after a bad tail")
        stats = drv.stats()
        assert stats["line"]["droppedFrames"] == 3 and stats["reports"] == 3
        assert stats["line"]["heartbeats"] == 1
        assert stats["requests"] == 0  # report-only: never polled
        # a report for another slave or area touches nothing of this device
        sim.add_slave(2)
        client.push_report(2, Area.HOLDING_REGISTER, 1, 2)
        client.push_report(1, Area.INPUT_REGISTER, 1, 2)
        wait_for(lambda: drv.stats()["line"]["reports"] >= 5)
        assert value_of(cfg, "r1") == 774 and drv.stats()["reports"] == 3


def test_a_report_in_the_registration_segment_is_applied() -> None:
    """The MCU registers and reports at once, in one TCP segment: the report after the
    registration is neither lost nor taken for part of the id (the wrapped header ends
    a text id)."""
    port = free_port()
    cfg = wrapped_device({"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "dtuId": "MCU1", "registration": "text",
                          "readCycle": 0})
    report = wrap(80, 1, bytes.fromhex("03021234"))
    with Simulator(slaves=[1]) as sim, running(cfg) as drv:
        sim.dial("127.0.0.1", port, registration=b"MCU1" + report, wrapped=True)
        wait_for(lambda: value_of(cfg, "r80") == 0x1234, what="the report applied")
        assert drv.stats()["reports"] == 1 and drv.stats()["line"]["droppedFrames"] == 0


def test_client_mode_integrity_poll_and_wrapped_writes() -> None:
    with Simulator(slaves=[1]) as sim:
        port = sim.serve_tcp("127.0.0.1", 0, wrapped=True)
        cfg = wrapped_device({"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": port, "readCycle": 150,
                              "maxMergeAddressGap": 100})
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 0, list(range(500, 600)))
        with running(cfg) as drv:
            wait_for(lambda: all(it.status is ItemStatus.OK for it in cfg.address_list),
                     what="integrity poll")
            assert [value_of(cfg, f"r{a}") for a in ADDRESSES] == [501, 502, 530, 580]
            ok, err = drv.write_address("r30", 4242)
            assert ok, err
            assert sim.slave(1).get_registers(Area.HOLDING_REGISTER, 30) == [4242]
            # a report pushed between polls is applied too
            sim.slave(1).set_registers(Area.HOLDING_REGISTER, 2, [7])
            (client,) = sim.clients()
            client.push_report(1, Area.HOLDING_REGISTER, 2, 1)
            wait_for(lambda: value_of(cfg, "r2") == 7)
            # no wrapped echo within the response timeout: the write failed
            sim.slave(1).set_faults(silent=True)
            started = time.monotonic()
            ok, err = drv.write_address("r1", 1)
            assert not ok and err is not None and "timeout" in err
            assert time.monotonic() - started >= 0.25
            assert drv.stats()["writeErrors"] == 1


class EagerMcu:
    """An edge MCU (TCP server, wrapped frames) that, on a read of holding registers from
    ``REPORT_AT``, first pushes an unsolicited report from the same address for two more
    registers (its own, newer values), then answers the read: the report has the
    request's slave, function and address, and only its byte count tells it apart."""

    REPORT_AT = 1

    def __init__(self, *, report_after: bool = False) -> None:
        self.report_after = report_after  # the report right after the reply, one segment
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = int(self._listener.getsockname()[1])
        self._stop = threading.Event()
        self.reports = 0
        self.replies = 0
        self._thread = threading.Thread(target=self._run, name="eager-mcu")
        self._thread.start()

    @staticmethod
    def polled(address: int) -> int:
        return 500 + address

    @staticmethod
    def reported(seq: int, address: int) -> int:
        return 9000 + 10 * seq + address

    def _run(self) -> None:
        with self._listener:
            while not self._stop.is_set():
                if select.select([self._listener], [], [], 0.05)[0]:
                    conn, _ = self._listener.accept()
                    with conn:
                        self._serve(conn)

    def _serve(self, conn: socket.socket) -> None:
        buf = b""
        while not self._stop.is_set():
            if not select.select([conn], [], [], 0.05)[0]:
                continue
            data = conn.recv(4096)
            if not data:
                return
            buf += data
            while len(buf) >= 13:  # FF AA | address | slave fc start count CRC | 0D
                request, buf = buf[:13], buf[13:]
                slave, fc, start, count = struct.unpack_from(">BBHH", request, 4)
                assert request[:2] == b"\xff\xaa" and fc == 3, request.hex()
                regs = [self.polled(start + i) for i in range(count)]
                reply = wrap(start, slave, struct.pack(f">BB{count}H", 3, 2 * count, *regs))
                if start == self.REPORT_AT:
                    n = count + 2
                    regs = [self.reported(self.reports, start + i) for i in range(n)]
                    report = wrap(start, slave, struct.pack(f">BB{n}H", 3, 2 * n, *regs))
                    self.reports += 1
                    if self.report_after:
                        reply += report
                    else:
                        conn.sendall(report)
                        if self.reports % 2:
                            time.sleep(0.005)  # pacing: every other report in a segment of its own
                conn.sendall(reply)
                self.replies += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


def test_a_report_that_looks_like_the_reply_but_has_another_count_is_a_report() -> None:
    """Poll blocks [1, 2] and [3]; before the reply to [1, 2] the MCU reports 1..4.  The
    report is applied as a report, the poll still gets its own reply, and nothing goes
    Invalid (it used to be taken as the reply: "byte count does not match")."""
    mcu = EagerMcu()
    seen: list[tuple[str, Any, ItemStatus]] = []
    try:
        cfg = em.load_device_config({
            "organization": {"deviceCode": "eager"},
            "communication": {"framing": "wrapped-report", "transport": "rtu-over-tcp",
                              "tcpHost": "127.0.0.1", "tcpPort": mcu.port, "slaveId": 1,
                              "readTimeout": 500, "readCycle": 50, "byteTimeout": 50,
                              # cycle: every read and report sets the items, so the
                              # callbacks show which frame each value came from
                              "maxBlockReadRegisterCount": 2, "reportMode": "cycle"},
            "addressList": [{"name": f"r{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                            for a in (1, 2, 3)],
        })
        with running(cfg, address_updated_callback=lambda it: seen.append(
                (it.name, it.value, it.status))) as drv:
            assert [(b["start"], b["count"]) for b in drv.read_plan()] == [(1, 2), (3, 1)]

            def reports_seen(name: str) -> int:
                return sum(1 for n, v, _ in list(seen) if n == name and v >= 9000)

            def invalid() -> bool:
                return any(status is not ItemStatus.OK for _, _, status in list(seen))

            wait_for(lambda: invalid() or all(reports_seen(n) >= 6 for n in ("r1", "r2", "r3")),
                     what="six polls answered behind a report")
        stats = drv.stats()
    finally:
        mcu.close()
    assert all(status is ItemStatus.OK for _, _, status in seen), \
        [s for s in seen if s[2] is not ItemStatus.OK]
    assert stats["protocolErrors"] == 0 and stats["timeouts"] == 0
    assert stats["reports"] >= 6
    for name, address in (("r1", 1), ("r2", 2), ("r3", 3)):
        values = [v for n, v, _ in seen if n == name]
        reported = [v for v in values if v >= 9000]
        assert len(reported) >= 6, (name, values)  # every report reached the item
        assert all(v == EagerMcu.polled(address) or (v - 9000) % 10 == address
                   for v in values), (name, values)
        # each report is followed by the polled value: the poll's reply was its own
        for before, after in itertools.pairwise(values):
            if before >= 9000:
                assert after == EagerMcu.polled(address), (name, values)


def test_a_report_right_after_the_reply_is_applied_after_it() -> None:
    """The MCU answers the read and, in the same TCP segment, reports newer values of the
    same registers: the items must end with the report's values (it came later on the
    wire), not be set back to the reply's by applying the reply last."""
    mcu = EagerMcu(report_after=True)
    seen: list[tuple[str, Any]] = []
    try:
        cfg = em.load_device_config({
            "organization": {"deviceCode": "late"},
            "communication": {"framing": "wrapped-report", "transport": "rtu-over-tcp",
                              "tcpHost": "127.0.0.1", "tcpPort": mcu.port, "slaveId": 1,
                              "readTimeout": 500, "readCycle": 60000, "byteTimeout": 50,
                              "reportMode": "cycle"},
            "addressList": [{"name": f"r{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                            for a in (1, 2)],
        })
        with running(cfg, address_updated_callback=lambda it: seen.append(
                (it.name, it.value))) as drv:
            wait_for(lambda: len(seen) >= 4, what="the reply and the report applied")
            values = {it.name: it.value for it in cfg.address_list}
            assert drv.stats()["cycles"] == 1
    finally:
        mcu.close()
    assert seen == [("r1", 501), ("r2", 502), ("r1", 9001), ("r2", 9002)], seen
    assert values == {"r1": 9001, "r2": 9002}
