"""The command line's shape (issue 24): -v after the command, --version, --rtu-over-tcp,
scan's --slaves."""

from __future__ import annotations

import pytest

import edgemodbus
from edgemodbus.cli import build_parser


def test_verbose_before_or_after_the_command() -> None:
    parser = build_parser()
    read = ["read", "--host", "h", "hr:0"]
    assert parser.parse_args(read).verbose == 0
    assert parser.parse_args(["-vv", *read]).verbose == 2
    assert parser.parse_args([*read, "-vv"]).verbose == 2
    assert parser.parse_args(["run", "x.json", "-v"]).verbose == 1
    assert parser.parse_args(["simulate", "-v", "--slaves", "1"]).verbose == 1


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"edgemodbus {edgemodbus.__version__}"


def test_host_transport_options() -> None:
    parser = build_parser()
    base = ["read", "--host", "h", "hr:0"]
    assert parser.parse_args(base).transport is None  # Modbus TCP (cli/oneitem.py)
    assert parser.parse_args([*base, "--rtu-over-tcp"]).transport == "rtu-over-tcp"
    assert parser.parse_args([*base, "--transport", "rtu-over-tcp"]).transport == \
        "rtu-over-tcp"
    scan = parser.parse_args(["scan", "--host", "h", "--slaves", "1-3"])
    assert (scan.transport, scan.slaves, scan.ids) == ("tcp", "1-3", None)
    scan = parser.parse_args(["scan", "--host", "h", "--rtu-over-tcp", "--ids", "4"])
    assert (scan.transport, scan.slaves, scan.ids) == ("rtu-over-tcp", None, "4")
