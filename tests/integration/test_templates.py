"""Every shipped template: loaded from a device file that names it, planned, and polled
against our simulator and against pymodbus (own process), each seeded with example
values at the addresses the vendor's register table gives; the decoded values must be
the example values.

The addresses below are written from the vendor documents the templates cite (not read
from the templates), so a wrong address in a template fails here.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.codec import Float32
from edgemodbus.config.templates import find_templates
from edgemodbus.datatypes import Area
from edgemodbus.poll.poller import build_plan
from edgemodbus.sim import Simulator
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

IR, CO, DI = Area.INPUT_REGISTER, Area.COIL, Area.DISCRETE_INPUT

# Eastron SDM120 input register table: parameter -> (30001-based register, example value)
SDM120 = {
    "Voltage": (30001, 230.4), "Current": (30007, 5.25), "ActivePower": (30013, 1180.5),
    "ApparentPower": (30019, 1209.6), "ReactivePower": (30025, -261.0),
    "PowerFactor": (30031, 0.976), "PhaseAngle": (30037, -12.5), "Frequency": (30071, 49.98),
    "ImportActiveEnergy": (30073, 1234.56), "ExportActiveEnergy": (30075, 12.5),
    "ImportReactiveEnergy": (30077, 98.25), "ExportReactiveEnergy": (30079, 3.5),
    "TotalActiveEnergy": (30343, 1247.06), "TotalReactiveEnergy": (30345, 101.75),
}  # fmt: skip

# Eastron SDM630 input register table
SDM630 = {
    "L1Voltage": (30001, 231.0), "L2Voltage": (30003, 229.5), "L3Voltage": (30005, 232.25),
    "L1Current": (30007, 10.5), "L2Current": (30009, 8.25), "L3Current": (30011, 12.0),
    "L1ActivePower": (30013, 2300.0), "L2ActivePower": (30015, 1800.5),
    "L3ActivePower": (30017, 2700.25), "L1ApparentPower": (30019, 2425.5),
    "L2ApparentPower": (30021, 1893.4), "L3ApparentPower": (30023, 2787.0),
    "L1ReactivePower": (30025, 150.0), "L2ReactivePower": (30027, -75.5),
    "L3ReactivePower": (30029, 310.0), "L1PowerFactor": (30031, 0.95),
    "L2PowerFactor": (30033, 0.951), "L3PowerFactor": (30035, 0.969),
    "AverageVoltageLN": (30043, 230.9), "AverageCurrent": (30047, 10.25),
    "SumCurrent": (30049, 30.75), "TotalActivePower": (30053, 6800.75),
    "TotalApparentPower": (30057, 7105.9), "TotalReactivePower": (30061, 384.5),
    "TotalPowerFactor": (30063, 0.957), "Frequency": (30071, 50.02),
    "ImportActiveEnergy": (30073, 45678.5), "ExportActiveEnergy": (30075, 0.0),
    "ImportReactiveEnergy": (30077, 1234.0), "ExportReactiveEnergy": (30079, 56.5),
    "L1L2Voltage": (30201, 400.1), "L2L3Voltage": (30203, 399.2),
    "L3L1Voltage": (30205, 401.7), "NeutralCurrent": (30225, 1.75),
    "TotalActiveEnergy": (30343, 45678.5), "TotalReactiveEnergy": (30345, 1290.5),
}  # fmt: skip


def _float_registers(table: dict[str, tuple[int, float]]) -> dict[Area, dict[int, int]]:
    regs: dict[int, int] = {}
    for entity, value in table.values():
        hi, lo = struct.unpack(">2H", struct.pack(">f", value))
        regs[entity - 30001], regs[entity - 30000] = hi, lo
    return {IR: regs}


def _float_values(table: dict[str, tuple[int, float]]) -> dict[str, float]:
    return {name: struct.unpack(">f", struct.pack(">f", v))[0] for name, (_, v) in table.items()}


RELAYS = [True, False, False, True, True, False, True, False]
INPUTS = [False, True, True, False, False, False, True, True]

# template -> (registers and bits to seed, expected decoded values)
CASES: dict[str, tuple[dict[Area, dict[int, Any]], dict[str, Any]]] = {
    "eastron-sdm120": (_float_registers(SDM120), _float_values(SDM120)),
    "eastron-sdm630": (_float_registers(SDM630), _float_values(SDM630)),
    # XY-MD02: input register 1 temperature (signed, 0.1 degC), 2 humidity (0.1 %RH)
    "xy-md02": ({IR: {1: (-125) & 0xFFFF, 2: 473}}, {"Temperature": -12.5, "Humidity": 47.3}),
    # Waveshare Modbus RTU Relay (D): relays at coils 0..7, inputs at discrete inputs 0..7
    "waveshare-relay-d-8ch": (
        {CO: dict(enumerate(RELAYS)), DI: dict(enumerate(INPUTS))},
        {**{f"Relay{i + 1}": v for i, v in enumerate(RELAYS)},
         **{f"Input{i + 1}": v for i, v in enumerate(INPUTS)}}),
}


def test_every_shipped_template_has_a_case_and_cites_its_document() -> None:
    shipped = {t.name: t for t in find_templates() if t.file.parent.name == "templates"}
    assert set(shipped) == set(CASES)
    for info in shipped.values():
        assert info.description
        assert {"vendor", "document", "version"} <= set(info.source), info.name


@contextmanager
def _simulator(seed: dict[Area, dict[int, Any]]) -> Iterator[tuple[str, int]]:
    with Simulator([1]) as sim:
        slave = sim.slave(1)
        for area, values in seed.items():
            for address, value in values.items():
                if area.is_bit:
                    slave.set_bits(area, address, [value])
                else:
                    slave.set_registers(area, address, [value])
        yield "rtu-over-tcp", sim.serve_tcp("127.0.0.1", 0)


_PEER_AREAS = {IR: "ir", CO: "co", DI: "di"}


@contextmanager
def _pymodbus(seed: dict[Area, dict[int, Any]]) -> Iterator[tuple[str, int]]:
    initial = {1: {_PEER_AREAS[area]: dict(values.items()) for area, values in seed.items()}}
    with PymodbusSlave("tcp", units=(1,), fill="zero", initial=initial) as peer:
        yield "tcp", peer.port


@pytest.mark.parametrize("peer", ["simulator", "pymodbus"])
@pytest.mark.parametrize("name", sorted(CASES))
def test_template_loads_plans_and_polls(name: str, peer: str) -> None:
    seed, expected = CASES[name]
    with (_simulator if peer == "simulator" else _pymodbus)(seed) as (transport, port):
        cfg = em.load_device_config({
            "template": name,
            "organization": {"deviceCode": name},
            "communication": {"transport": transport, "tcpHost": "127.0.0.1",
                              "tcpPort": port, "slaveId": 1, "readCycle": 200,
                              "readTimeout": 1000},
        })
        assert cfg.template == name
        assert [i.name for i in cfg.address_list] == list(expected)
        params = cfg.effective_parameters()
        blocks = build_plan(cfg.parsed_items(), params)
        assert blocks and all(b.count <= params.max_block_read_register_count
                              for b in blocks if not b.area.is_bit)
        drv = em.DriverModbusRtu()
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        try:
            wait_for(lambda: all(i.status is em.ItemStatus.OK for i in cfg.address_list),
                     timeout=15, what=f"every item of {name} read")
        finally:
            drv.stop_device()
    got = {i.name: i.value for i in cfg.address_list}
    for item, value in expected.items():
        assert got[item] == pytest.approx(value, rel=1e-9, abs=1e-9), item
        # a Float item's value is a Float32 (a float whose text is the float32's)
        kind = float if isinstance(got[item], Float32) else type(got[item])
        assert kind is type(value), item


def test_eastron_reads_stay_within_the_documents_40_parameters() -> None:
    """The Eastron documents limit a request to 40 parameters (80 registers)."""
    for name in ("eastron-sdm120", "eastron-sdm630"):
        cfg = em.load_device_config({"template": name})
        blocks = build_plan(cfg.parsed_items(), cfg.effective_parameters())
        assert max(b.count for b in blocks) <= 80, name
        assert {b.area for b in blocks} == {IR}
