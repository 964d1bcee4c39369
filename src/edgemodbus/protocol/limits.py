"""The Modbus protocol's limits, in one place: how much one request may read or write,
the address range, the sizes of a PDU and of each kind of ADU, and the slave ids.

Every layer that checks or plans against one of these imports it from here (config's
ranges, the planner's caps, the writer's batches, the forward checks, the simulator).
The same limits are compiled into the C below us (libmodbus's ``MODBUS_MAX_*`` and
``*_MAX_ADU_LENGTH``, our ``EMB_MAX_ADU``/``EMB_MAX_RTU`` in csrc/emb_check.h and the MBAP
length in csrc/emb_serve.c); tests/unit/protocol/test_limits.py checks that they agree.

References: MODBUS Application Protocol Specification v1.1b3 ("AP", section numbers
below), MODBUS over Serial Line v1.02 ("SL"), MODBUS Messaging on TCP/IP v1.0b ("TCP").
Pure constants: this module imports only the data area names.
"""

from __future__ import annotations

from ..datatypes import Area

__all__ = [
    "BROADCAST_ID",
    "MAX_ADDRESS",
    "MAX_MBAP_ADU",
    "MAX_MBAP_LENGTH",
    "MAX_PDU",
    "MAX_READ_BITS",
    "MAX_READ_REGISTERS",
    "MAX_RTU_ADU",
    "MAX_RW_READ_REGISTERS",
    "MAX_RW_WRITE_REGISTERS",
    "MAX_SLAVE_ID",
    "MAX_UNIT_ID",
    "MAX_WRITE_BITS",
    "MAX_WRITE_REGISTERS",
    "MBAP_HEADER",
    "MIN_SLAVE_ID",
    "TCP_UNIT_ID",
    "max_read",
    "slave_id_problem",
]

# Quantities of one request.
MAX_READ_BITS = 2000
"""Coils or discrete inputs one FC01/FC02 request reads (AP 6.1, 6.2: 1 to 2000, 0x7D0)."""
MAX_READ_REGISTERS = 125
"""Registers one FC03/FC04 request reads (AP 6.3, 6.4: 1 to 125, 0x7D)."""
MAX_WRITE_BITS = 1968
"""Coils one FC15 request writes (AP 6.11: 1 to 1968, 0x7B0)."""
MAX_WRITE_REGISTERS = 123
"""Registers one FC16 request writes (AP 6.12: 1 to 123, 0x7B)."""
MAX_RW_READ_REGISTERS = 125
"""Registers FC23 (read/write multiple registers) reads (AP 6.17: 1 to 125, 0x7D)."""
MAX_RW_WRITE_REGISTERS = 121
"""Registers FC23 writes (AP 6.17: 1 to 121, 0x79)."""

# The data model.
MAX_ADDRESS = 0xFFFF
"""Highest protocol (0-based) address of each area: 0..65535 (AP 4.4)."""

# Frame sizes.
MAX_PDU = 253
"""Bytes of a PDU, function code included (AP 4.1: the RS-485 ADU of 256 bytes less the
slave address and the CRC)."""
MAX_RTU_ADU = 256
"""Bytes of an RTU frame: slave address, PDU, CRC (SL 2.5.1)."""
MBAP_HEADER = 7
"""Bytes of the MBAP header: transaction id, protocol id, length, unit id (TCP 3.1.3)."""
MAX_MBAP_ADU = MBAP_HEADER + MAX_PDU
"""Bytes of a Modbus TCP ADU: the MBAP header and a PDU, 260 (TCP 3.1.3, 4.1)."""
MAX_MBAP_LENGTH = 1 + MAX_PDU
"""The MBAP length field's largest value: the unit id and a PDU, 254 (TCP 3.1.3)."""

# Slave addresses and unit ids.
BROADCAST_ID = 0
"""The broadcast address: every slave acts on a write, none answers (SL 2.2)."""
MIN_SLAVE_ID = 1
MAX_SLAVE_ID = 247
"""Unicast slave addresses on a serial line are 1..247; 248..255 are reserved (SL 2.2)."""
MAX_UNIT_ID = 255
"""A Modbus TCP unit id is one byte, 0..255 (TCP 4.4.2)."""
TCP_UNIT_ID = 0xFF
"""The unit id that addresses a Modbus TCP device itself, no gateway behind it (TCP 4.4.2)."""


def slave_id_problem(slave_id: int, transport: str) -> str | None:
    """What is wrong with ``slave_id`` on a line of ``transport`` ("rtu", "rtu-over-tcp",
    "tcp", ...), None when it is allowed: a Modbus TCP unit id is 0..255 (TCP 4.4.2), a
    slave on an RTU line 1..247 (SL 2.2).  The one rule the device files (config/) and
    the one-shot read (cli/oneshot.py) check."""
    if not 0 <= slave_id <= MAX_UNIT_ID:
        return f"must be 0..{MAX_UNIT_ID}"
    if transport == "tcp" or MIN_SLAVE_ID <= slave_id <= MAX_SLAVE_ID:
        return None
    return (f"must be {MIN_SLAVE_ID}..{MAX_SLAVE_ID} on an RTU line (transport {transport!r}); "
            f"0..{MAX_UNIT_ID} only as a Modbus TCP unit id")


def max_read(area: Area) -> int:
    """The most bits (coils, discrete inputs) or registers one read of ``area`` returns."""
    return MAX_READ_BITS if area.is_bit else MAX_READ_REGISTERS
