"""The Modbus limits (edgemodbus.protocol.limits) are the spec's, the same as the C's
below us (libmodbus 3.1.6 and csrc/, as compiled, read through the cffi extension), and
nothing else in the package defines its own copy of one of them."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from edgemodbus._ffi.native import lib
from edgemodbus.datatypes import Area
from edgemodbus.protocol import limits

TOP = Path(__file__).resolve().parents[3]
PACKAGE = TOP / "src" / "edgemodbus"


def test_the_limits_are_the_ones_libmodbus_was_compiled_with() -> None:
    assert limits.MAX_READ_BITS == lib.MODBUS_MAX_READ_BITS
    assert limits.MAX_READ_REGISTERS == lib.MODBUS_MAX_READ_REGISTERS
    assert limits.MAX_WRITE_BITS == lib.MODBUS_MAX_WRITE_BITS
    assert limits.MAX_WRITE_REGISTERS == lib.MODBUS_MAX_WRITE_REGISTERS
    assert limits.MAX_RW_READ_REGISTERS == lib.MODBUS_MAX_WR_READ_REGISTERS
    assert limits.MAX_RW_WRITE_REGISTERS == lib.MODBUS_MAX_WR_WRITE_REGISTERS
    assert limits.MAX_PDU == lib.MODBUS_MAX_PDU_LENGTH
    assert limits.MAX_RTU_ADU == lib.MODBUS_RTU_MAX_ADU_LENGTH
    assert limits.MAX_MBAP_ADU == lib.MODBUS_TCP_MAX_ADU_LENGTH
    assert limits.BROADCAST_ID == lib.MODBUS_BROADCAST_ADDRESS
    assert limits.TCP_UNIT_ID == lib.MODBUS_TCP_SLAVE


def test_the_limits_are_the_ones_our_c_was_compiled_with() -> None:
    assert limits.MAX_MBAP_ADU == lib.EMB_MAX_ADU == lib.EMB_SV_ADU  # emb_check.h, emb_serve.h
    assert limits.MAX_RTU_ADU == lib.EMB_MAX_RTU
    assert limits.MBAP_HEADER == lib.EMB_MBAP
    assert limits.MAX_UNIT_ID + 1 == lib.EMB_SV_UNITS  # the server's table of unit ids
    # the server's MBAP length bound is private to csrc/emb_serve.c: read from its text
    found = re.findall(r"#define\s+EMB_SV_MAX_LEN\s+(\d+)", (TOP / "csrc/emb_serve.c").read_text())
    assert [int(n) for n in found] == [limits.MAX_MBAP_LENGTH]


def test_the_limits_are_the_specs() -> None:
    # written out from MODBUS Application Protocol v1.1b3 (6.1-6.4, 6.11, 6.12, 6.17, 4.1,
    # 4.4), Serial Line v1.02 (2.2, 2.5.1) and Messaging on TCP/IP v1.0b (3.1.3, 4.4.2)
    assert (limits.MAX_READ_BITS, limits.MAX_READ_REGISTERS) == (0x7D0, 0x7D)
    assert (limits.MAX_WRITE_BITS, limits.MAX_WRITE_REGISTERS) == (0x7B0, 0x7B)
    assert (limits.MAX_RW_READ_REGISTERS, limits.MAX_RW_WRITE_REGISTERS) == (0x7D, 0x79)
    assert limits.MAX_ADDRESS == 65535
    assert (limits.MAX_PDU, limits.MAX_RTU_ADU, limits.MAX_MBAP_ADU) == (253, 256, 260)
    assert (limits.MBAP_HEADER, limits.MAX_MBAP_LENGTH) == (7, 254)
    assert (limits.BROADCAST_ID, limits.MIN_SLAVE_ID, limits.MAX_SLAVE_ID) == (0, 1, 247)
    assert (limits.MAX_UNIT_ID, limits.TCP_UNIT_ID) == (255, 255)
    assert [limits.max_read(a) for a in Area] == [2000, 2000, 125, 125]


def test_every_register_quantity_is_the_most_a_pdu_holds() -> None:
    """A PDU is at most 253 bytes (AP 4.1): each register limit is the largest quantity
    whose request or reply still fits, and the bit limits fit too."""

    def fits(header: int, registers: int) -> bool:
        return header + 2 * registers <= limits.MAX_PDU

    for header, most in ((2, limits.MAX_READ_REGISTERS),  # FC03/04 reply: fc, byte count
                         (6, limits.MAX_WRITE_REGISTERS),  # FC16: fc, address, qty, count
                         (10, limits.MAX_RW_WRITE_REGISTERS)):  # FC23 request
        assert fits(header, most) and not fits(header, most + 1)
    assert 2 + (limits.MAX_READ_BITS + 7) // 8 <= limits.MAX_PDU  # FC01/02 reply
    assert 6 + (limits.MAX_WRITE_BITS + 7) // 8 <= limits.MAX_PDU  # FC15 request
    assert limits.MAX_RTU_ADU == 1 + limits.MAX_PDU + 2  # slave address and CRC


# Values that are one of the protocol's limits and no common size (256, 253 and 65536
# are also a host name's, a queue's, a buffer's), and names that say "limit".
_LIMIT_VALUES = {2000, 1968, 125, 123, 121, 247, 260}
_LIMIT_NAME = re.compile(r"MAX|CAP|LIMIT", re.IGNORECASE)


def _redefined_limits(root: Path) -> list[str]:
    """``NAME = <a limit's value>`` at module or class level, NAME saying it is a limit,
    outside protocol/limits.py."""
    found = []
    for path in sorted(root.rglob("*.py")):
        if path == root / "protocol" / "limits.py":
            continue
        tree = ast.parse(path.read_text(), str(path))
        bodies = [tree.body] + [n.body for n in ast.walk(tree) if isinstance(n, ast.ClassDef)]
        for node in (n for body in bodies for n in body):
            if isinstance(node, ast.Assign):
                targets, value = node.targets, node.value
            elif isinstance(node, ast.AnnAssign) and node.value is not None:
                targets, value = [node.target], node.value
            else:
                continue
            names = [t.id for t in targets if isinstance(t, ast.Name)]
            if (isinstance(value, ast.Constant) and value.value in _LIMIT_VALUES
                    and any(_LIMIT_NAME.search(n) for n in names)):
                found.append(f"{path.relative_to(root)}:{node.lineno} {names[0]} = {value.value}")
    return found


def test_no_module_keeps_its_own_copy_of_a_limit() -> None:
    assert _redefined_limits(PACKAGE) == []


def test_a_copy_of_a_limit_is_found(tmp_path: Path) -> None:
    (tmp_path / "protocol").mkdir()
    (tmp_path / "protocol" / "limits.py").write_text("MAX_READ_REGISTERS = 125\n")
    (tmp_path / "planner.py").write_text("REGISTER_CAP = 125\nwidth = 125\n")
    (tmp_path / "writes.py").write_text("class W:\n    _MAX_WRITE_COILS: int = 1968\n")
    assert _redefined_limits(tmp_path) == [
        "planner.py:1 REGISTER_CAP = 125", "writes.py:2 _MAX_WRITE_COILS = 1968"]
