"""The UART model of tests/uart_line.py, which the scan tests rely on to tell settings
apart: what a receiver at one setting makes of characters sent at another."""

from __future__ import annotations

import os
import termios

from edgemodbus.protocol import rtu
from tests.uart_line import UartSettings, character_bits, pty_settings, resample

REQUEST = rtu.frame(1, bytes([3, 0, 0, 0, 1]))  # 01 03 00 00 00 01 84 0A


def test_character_bits() -> None:
    assert character_bits(b"\x01", UartSettings(9600)) == [0, 1, 0, 0, 0, 0, 0, 0, 0, 1]
    # even parity: the parity bit makes the ones even; odd: odd; two stop bits
    assert character_bits(b"\x01", UartSettings(9600, "E", 2))[9:] == [1, 1, 1]
    assert character_bits(b"\x03", UartSettings(9600, "O"))[9:] == [1, 1]


def test_same_settings_and_stop_bits_pass() -> None:
    for s in (UartSettings(9600), UartSettings(19200, "E"), UartSettings(38400, "O", 2)):
        assert resample(REQUEST, s, s) == REQUEST
    # a receiver checks the first stop bit only
    assert resample(REQUEST, UartSettings(9600, "N", 2), UartSettings(9600, "N", 1)) == REQUEST
    assert resample(REQUEST, UartSettings(9600, "N", 1), UartSettings(9600, "N", 2)) == REQUEST


def test_parity_mismatch() -> None:
    # a receiver without parity checking reads 8E1 characters right (the parity bit
    # falls on its stop bit: a framing error, delivered as read)
    assert resample(REQUEST, UartSettings(9600, "E"), UartSettings(9600, "N")) == REQUEST
    # one checking parity reads 8N1 characters as errors (0x00, no PARMRK)
    wrong = resample(REQUEST, UartSettings(9600, "N"), UartSettings(9600, "E"))
    assert wrong != REQUEST and wrong.count(0) >= len(wrong) - 2
    assert resample(REQUEST, UartSettings(9600, "E"), UartSettings(9600, "O")) == bytes(8)


def test_baud_mismatch_is_junk() -> None:
    for tx, rx in ((9600, 19200), (19200, 9600), (9600, 4800), (115200, 9600)):
        out = resample(REQUEST, UartSettings(tx), UartSettings(rx))
        assert out != REQUEST and len(out) != len(REQUEST), (tx, rx, out.hex())
    # at twice the rate, each sent bit is read twice: 0x01 reads as start 0, then 0 1 1 ...
    assert resample(b"\x01", UartSettings(9600), UartSettings(19200))[0] == 0x06


def test_pty_settings_seen_from_the_other_side() -> None:
    master, slave = os.openpty()
    try:
        attrs = termios.tcgetattr(slave)
        attrs[0] |= termios.INPCK
        attrs[2] |= termios.PARENB | termios.PARODD | termios.CSTOPB
        attrs[4] = attrs[5] = termios.B19200
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        assert pty_settings(master) == UartSettings(19200, "O", 2)
    finally:
        os.close(master)
        os.close(slave)
