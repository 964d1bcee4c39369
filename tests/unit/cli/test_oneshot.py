"""The one-shot ``read`` (cli/oneshot.py, issue 29): it takes only options the device-file
check accepts too, and reads what that one would (differential against the config
models); it reads without pydantic or the config models; what it does not take, and
every failure, goes the polled way with that path's messages."""

from __future__ import annotations

import argparse
import contextlib
import io
import socket
import struct
import subprocess
import sys
from collections.abc import Callable
from functools import partial

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.cli import build_parser
from edgemodbus.cli.exits import CommandFailed
from edgemodbus.cli.oneitem import one_item_config
from edgemodbus.cli.oneshot import one_shot_item, read_once
from edgemodbus.cli.output import CliError, value_text
from edgemodbus.codec import Float32
from edgemodbus.protocol.limits import slave_id_problem
from tests.peers import PymodbusSlave, Transport, default_bit, free_port


def _args(*words: str) -> argparse.Namespace:
    return build_parser("read").parse_args(["read", *words])


_TYPES = ["UInt16", "Int16", "uint16", "Float", "float32", "Int32", "UInt32", "Int64",
          "Double", "Boolean", "String", "Binary", "BCD16", "Int24", "Char", "DateTime",
          "Timestamp", "Byte", "Nope", ""]
_ADDRESSES = ["hr:7", "hr:7.3", "hr:7.16", "ir:65535", "hr:65534", "hr:65535", "coil:5",
              "di:0", "3:00005", "4:1", "40001", "400001", "1", "10001", "30001", "hr:-1",
              "hr:70000", "xx:1", " hr:7", "hr:7 ", "0x:5", "coil:5.1"]
_FORMATS = ["ABCD", "BADC", "CDAB", "DCBA", "abcd", "ABDC", "", "ABCDEFGH"]


@st.composite
def _options(draw: st.DrawFn) -> list[str]:
    words = ["--host", draw(st.sampled_from(["127.0.0.1", "localhost", " "]))]
    words += ["--port", str(draw(st.sampled_from([502, 1, 65535, 0, 65536, -1])))]
    if draw(st.booleans()):
        words.append("--rtu-over-tcp")
    words += ["--slave", str(draw(st.sampled_from([0, 1, 17, 247, 248, 255, 256, -1])))]
    words += ["--timeout", str(draw(st.sampled_from([1, 1000, 60_000, 0, -5, 100_000])))]
    if draw(st.booleans()):
        words += ["--type", draw(st.sampled_from(_TYPES))]
    words += ["--format", draw(st.sampled_from(_FORMATS))]
    if draw(st.booleans()):
        words.append("--byte-swap16")
    multiplier = draw(st.sampled_from(["1", "0.1", "-2", "0", "nan", "inf", "1e300"]))
    words += ["--multiplier", multiplier]
    words += ["--address-prefix", draw(st.sampled_from(["function-code", "modicon",
                                                        "entity"]))]
    words += ["--", draw(st.sampled_from(_ADDRESSES))]
    return words


@settings(max_examples=400, deadline=None)
@given(_options())
def test_the_one_shot_takes_only_what_the_device_check_accepts(words: list[str]) -> None:
    """Whatever the one-shot read takes, the config models accept, with the same address
    and value spec: it never reads something the polled read would refuse or read
    otherwise."""
    try:
        _args(*words)
    except SystemExit:
        return  # argparse refuses it (an empty --format, a blank --host): neither reads
    item = one_shot_item(_args(*words))
    try:
        cfg = one_item_config(_args(*words))
    except CliError as exc:
        assert item is None, (words, exc.lines)
        return
    if item is None:
        return  # the polled way reads it
    addr, spec = item
    parsed = cfg.parsed_items()[0]
    assert (parsed.address.area, parsed.address.offset, parsed.address.bit) == \
        (addr.area, addr.offset, addr.bit)
    assert parsed.value_spec() == spec, words
    assert parsed.registers == (1 if addr.area.is_bit else spec.registers)


def test_the_slave_id_rule_is_the_config_models() -> None:
    """protocol/limits.py's rule is the one the device files use: same verdict, same
    words."""
    for transport in ("tcp", "rtu-over-tcp"):
        for slave in (0, 1, 247, 248, 255):
            flag = ["--rtu-over-tcp"] if transport == "rtu-over-tcp" else []
            problem = slave_id_problem(slave, transport)
            try:
                one_item_config(_args("--host", "h", "--slave", str(slave), *flag, "hr:1"))
            except CliError as exc:
                assert problem is not None, (transport, slave)
                assert exc.lines == [f"--slave {slave}: {problem}"]
            else:
                assert problem is None, (transport, slave)


def _f32(registers: list[int]) -> float:
    return float(Float32(struct.unpack(">f", struct.pack(">HH", *registers))[0]))


def test_one_shot_reads_what_an_independent_slave_holds() -> None:
    """pymodbus holds the registers; the one-shot read (not the polled fallback: a
    value comes back from read_once) decodes them as the types and orders say."""
    transports: list[tuple[Transport, list[str]]] = [("rtu-over-tcp", ["--rtu-over-tcp"]),
                                                     ("tcp", [])]
    for transport, flag in transports:
        with PymodbusSlave(transport, units=(3,)) as slave:
            base = ["--host", "127.0.0.1", "--port", str(slave.port), "--slave", "3", *flag]
            slave.set_registers(3, "hr", 20, [0x4049, 0x0FDB, 0xFFFE, 0x0001])
            slave.set_bits(3, "co", 5, [True])

            def once(*words: str, base: list[str] = base) -> object:
                got = read_once(_args(*base, *words))
                assert got is not None, words
                return got[0]

            assert once("hr:20") == 0x4049
            assert once("--type", "Float", "hr:20") == _f32([0x4049, 0x0FDB])
            assert once("--type", "Int32", "--format", "CDAB", "hr:21") == \
                struct.unpack(">i", struct.pack(">HH", 0xFFFE, 0x0FDB))[0]
            assert once("--type", "Int16", "hr:22") == -2
            assert once("--byte-swap16", "hr:23") == 0x0100
            assert once("--multiplier", "0.5", "hr:23") == 0.5
            assert once("hr:22.0") is False
            assert once("hr:22.1") is True
            assert once("coil:5") is True
            assert once("di:6") == bool(default_bit(3, "di", 6))
            assert once("--address-prefix", "entity", "40021") == 0x4049


def test_failures_and_other_options_go_the_polled_way() -> None:
    """No value from the one-shot read: a refused connection, a serial line, --quantity,
    -v (the polled read then says what happened, or logs and traces it)."""
    assert read_once(_args("--host", "127.0.0.1", "--port", str(free_port()), "hr:1")) is None
    assert read_once(_args("--serial", "/dev/null", "hr:1")) is None
    with PymodbusSlave("tcp", units=(3,)) as slave:
        base = ["--host", "127.0.0.1", "--port", str(slave.port), "--slave", "3"]
        assert read_once(_args(*base, "--quantity", "2", "--type", "String", "hr:1")) is None
        assert read_once(_args(*base, "hr:1")) is not None
        assert read_once(_args(*base, "-vv", "hr:1")) is None  # the frame trace is the poller's


def test_the_read_command_loads_no_pydantic() -> None:
    """``edgemodbus read`` of a register imports neither pydantic, the config models nor
    the driver (before: ~110 ms of its start-up)."""
    with PymodbusSlave("tcp", units=(1,)) as slave:
        probe = ("import sys\nfrom edgemodbus.cli import main\n"
                 f"rc = main(['read', '--host', '127.0.0.1', '--port', '{slave.port}', "
                 "'hr:1'])\nprint(rc)\nprint('\\n'.join(sorted(sys.modules)))")
        out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                             timeout=120, check=True)
    lines = out.stdout.split()
    assert lines[1] == "0", out.stderr
    loaded = set(lines[2:])
    heavy = {"pydantic", "edgemodbus.config", "edgemodbus.driver", "edgemodbus.line",
             "edgemodbus.poll"}
    assert not heavy & loaded, sorted(heavy & loaded)


def test_a_fallback_prints_the_entity_notice_once() -> None:
    port = free_port()
    out = subprocess.run([sys.executable, "-m", "edgemodbus.cli", "read", "--host",
                          "127.0.0.1", "--port", str(port), "40001"],
                         capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 1, out.stderr
    assert out.stderr.count("notice:") == 1, out.stderr
    assert f"hr:40001: link down: tcp://127.0.0.1:{port}" in out.stderr or \
        "40001: link down" in out.stderr, out.stderr


_DECODE_TYPES = ["UInt16", "Int16", "Int32", "UInt32", "Float", "Double", "Int64", "UInt64",
                 "BCD16", "BCD32", "Int24", "UInt24", "Byte", "Sbyte", "Char", "Boolean"]


def test_one_shot_and_polled_reads_print_the_same() -> None:
    """Differential: over registers and types, the one-shot read prints what the polled
    read (the one-item device, its poller's decode) prints for the same options."""
    from edgemodbus.cli.polling import read as polled_read

    with PymodbusSlave("tcp", units=(1,)) as slave:
        # a generous timeout: the slave is a process of its own on a loaded machine
        base = ["--host", "127.0.0.1", "--port", str(slave.port), "--timeout", "10000"]

        @settings(max_examples=40, deadline=None)
        @given(st.lists(st.integers(0, 0xFFFF), min_size=4, max_size=4),
               st.sampled_from(_DECODE_TYPES), st.sampled_from(["ABCD", "CDAB", "BADC"]),
               st.booleans(), st.sampled_from(["1", "0.1", "-3"]))
        def same(registers: list[int], data_type: str, fmt: str, swap: bool,
                 multiplier: str) -> None:
            slave.set_registers(1, "hr", 30, registers)
            words = [*base, "--type", data_type, "--format", fmt, "--multiplier", multiplier,
                     *(["--byte-swap16"] if swap else []),
                     "hr:30.5" if data_type == "Boolean" else "hr:30"]
            if one_shot_item(_args(*words)) is None:  # e.g. a multiplier on a Boolean
                with pytest.raises(CliError):  # the config models refuse it too
                    polled_read(_args(*words), notice=False)
                return
            fast = read_once(_args(*words))
            if fast is None:  # the codec refused the value (a BCD nibble over 9): so does
                with pytest.raises(CommandFailed):  # the poller, and says why
                    polled_read(_args(*words), notice=False)
                return
            out = io.StringIO()
            with contextlib.redirect_stdout(out):
                assert polled_read(_args(*words), notice=False) == 0
            assert value_text(fast[0]) == out.getvalue().strip(), words

        same()


def _failure(read: Callable[[argparse.Namespace], object], words: list[str]) -> list[str]:
    with pytest.raises(CommandFailed) as info:
        read(_args(*words))
    return info.value.lines


def test_a_silent_slave_is_told_as_the_polled_read_tells_it() -> None:
    """No answer at all (the wrong framing, a slave id nobody has, a peer that never
    replies): the one-shot read says what the polled read says, framing hint included,
    after one timeout, not two."""
    from edgemodbus.cli.polling import read as polled_read

    cases: list[list[str]] = []
    with PymodbusSlave("rtu-over-tcp", units=(3,)) as rtu, \
            socket.create_server(("127.0.0.1", 0)) as mute:
        cases.append(["--port", str(rtu.port), "--slave", "3", "hr:4"])  # MBAP to RTU
        cases.append(["--port", str(mute.getsockname()[1]), "--type", "Float", "hr:4"])
        told = []
        for words in cases:
            args = ["--host", "127.0.0.1", "--timeout", "300", *words]
            fast = _failure(read_once, args)
            polled = _failure(partial(polled_read, notice=False), args)
            assert fast == polled, words
            told.append(fast)
    assert told[0][0].endswith("add --rtu-over-tcp"), told
    assert told[1] == ["hr:4: device not responding: slave 1 FC03 @4+2: no response "
                       "(timeout)"], told
