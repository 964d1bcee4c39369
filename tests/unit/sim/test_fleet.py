"""DtuFleet's set-up rules and the open-files limit (no network)."""

from __future__ import annotations

import resource
import subprocess
import sys

import pytest

from edgemodbus.sim import DtuFleet


def run_with_limit(soft: int, hard: int, code: str) -> subprocess.CompletedProcess[str]:
    """``code`` in a fresh interpreter whose RLIMIT_NOFILE is (soft, hard)."""
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))

    return subprocess.run(
        [sys.executable, "-c", "import resource\n"
         "from edgemodbus.sim import raise_open_files_limit as r\n" + code],
        capture_output=True, text=True, timeout=30, preexec_fn=limit, check=False,
    )


def test_the_soft_limit_is_raised_to_the_hard_one_only_when_needed() -> None:
    out = run_with_limit(100, 300, "print(r(50), r(100), r(101), "
                         "resource.getrlimit(resource.RLIMIT_NOFILE))")
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["100", "100", "300", "(300,", "300)"]


def test_a_hard_limit_too_low_is_named_with_what_to_do() -> None:
    out = run_with_limit(100, 300, "r(5064)")
    assert out.returncode == 1
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("OSError: [Errno 24] 5064 open files needed, but this process may "
                           "open at most 300 (the hard RLIMIT_NOFILE)")
    assert "ulimit -Hn 5064" in last and "LimitNOFILE=5064" in last


def test_registration_packets_follow_the_template_and_must_differ() -> None:
    fleet = DtuFleet("127.0.0.1", 9502, 3, first=8, registration="IMEI:86{n:013d}\r\n",
                     slaves=[1, 4], size=8)
    assert [d.registration for d in fleet.dtus] == [
        b"IMEI:860000000000008\r\n", b"IMEI:860000000000009\r\n", b"IMEI:860000000000010\r\n"]
    assert fleet.dtu(9).number == 9 and sorted(fleet.dtu(9).slaves) == [1, 4]
    assert fleet.dtu(9).slave(4) is not fleet.dtu(10).slave(4)  # a register map per DTU
    with pytest.raises(KeyError):
        fleet.dtu(11)
    assert DtuFleet("h", 1, 1, registration="").dtus[0].registration == b""
    assert DtuFleet("h", 1, 2, registration=lambda n: bytes([n])).dtus[1].registration == b"\1"
    with pytest.raises(ValueError, match="same packet"):
        DtuFleet("127.0.0.1", 9502, 2, registration="DTU")
    with pytest.raises(ValueError, match="not a template of"):
        DtuFleet("127.0.0.1", 9502, 2, registration="DTU{id}")
    with pytest.raises(ValueError, match="at least 1"):
        DtuFleet("127.0.0.1", 9502, 0)
    assert fleet.stats() == {"dtus": 3, "connected": 0, "reconnects": 0, "connections": 0,
                             "dial_failures": 0, "requests": 0, "unknown_slave": 0,
                             "discarded_bytes": 0, "heartbeats": 0}
    fleet.stop()  # never started: nothing to stop
