"""``edgemodbus check`` on a folder of files that are not device files
(docs/fault-checklist.md "`edgemodbus check` and bulk start"): a FIFO, a symlink loop,
a broken link, a folder, a 1 GB sparse file, thousands of files, a file removed while
the folder is read.  One line each, in bounded time and memory, never a block (a FIFO's
open blocks: a child process with a deadline runs the folder's check)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.cli import main
from edgemodbus.gateway.service import Gateway

# the check, then its own peak RSS (KiB, VmHWM: of its own image since the exec) on
# stderr's last line; getrusage's ru_maxrss counts the forked test process before the
# exec too, and RUSAGE_CHILDREN's is the largest child the suite ever had
CHECK = """import sys
from edgemodbus.cli import main
try:
    code = main(['check', sys.argv[1]])
finally:
    with open('/proc/self/status') as status:
        hwm = next(line.split()[1] for line in status if line.startswith('VmHWM:'))
    sys.stderr.write(f"peak {hwm}\\n")
sys.exit(code)
"""


def device(code: str) -> dict[str, Any]:
    return {"organization": {"deviceCode": code},
            "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": 9, "slaveId": 1},
            "addressList": [{"name": f"t{i}", "address": f"hr:{i}",
                             "deviceDataType": "UInt16"} for i in range(10)]}


def run_check(path: Path, deadline: float = 120.0) -> tuple[int, list[str], float, float]:
    """The check in a child process: exit code, stdout lines, seconds, peak RSS (MB)."""
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-c", CHECK, str(path)], capture_output=True,
                          text=True, timeout=deadline, check=False)
    took = time.monotonic() - start
    *err, last = done.stderr.splitlines() or [""]
    assert not err and last.startswith("peak "), done.stderr  # never a traceback
    return done.returncode, done.stdout.splitlines(), took, int(last.split()[1]) / 1024


def test_special_files_in_a_folder_are_one_line_each_and_never_opened(tmp_path: Path) -> None:
    (tmp_path / "good.json").write_text(json.dumps(device("good")))
    os.mkfifo(tmp_path / "fifo.json")
    (tmp_path / "loop1.json").symlink_to("loop2.json")
    (tmp_path / "loop2.json").symlink_to("loop1.json")
    (tmp_path / "broken.json").symlink_to(tmp_path / "nowhere")
    (tmp_path / "sub.json").mkdir()
    with open(tmp_path / "sparse.json", "wb") as f:
        f.truncate(1 << 30)  # 1 GB, no block written
    code, lines, took, peak = run_check(tmp_path)
    assert code == 2
    assert sorted(lines) == sorted([
        f"{tmp_path / 'broken.json'}: warning: no such file or directory: not a device "
        "file, the gateway skips it",
        f"{tmp_path / 'fifo.json'}: warning: is a FIFO: not a device file, the gateway "
        "skips it",
        f"{tmp_path / 'loop1.json'}: warning: too many levels of symbolic links: not a "
        "device file, the gateway skips it",
        f"{tmp_path / 'loop2.json'}: warning: too many levels of symbolic links: not a "
        "device file, the gateway skips it",
        f"{tmp_path / 'sub.json'}: warning: is a directory: not a device file, the gateway "
        "skips it",
        f"{tmp_path / 'sparse.json'}: 1,073,741,824 bytes: a JSON file we read has at most "
        "33,554,432",
    ]), lines
    assert took < 60 and peak < 300, (took, peak)  # the 1 GB file never read


def test_a_symlink_loop_given_is_named_as_one(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """It was "no such file or directory" (Path.exists() is False for ELOOP)."""
    (tmp_path / "a.json").symlink_to("b.json")
    (tmp_path / "b.json").symlink_to("a.json")
    assert main(["check", str(tmp_path / "a.json")]) == 2
    assert capsys.readouterr().out.splitlines() == [
        f"{tmp_path / 'a.json'}: too many levels of symbolic links"]


def test_a_file_removed_while_the_folder_is_read_is_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    for code in ("a", "b", "c"):
        (tmp_path / f"{code}.json").write_text(json.dumps(device(code)))
    listed = Gateway.device_files

    def list_then_remove(self: Gateway) -> list[Path]:
        files = listed(self)
        (tmp_path / "b.json").unlink()  # gone between the listing and its read
        return files

    monkeypatch.setattr(Gateway, "device_files", list_then_remove)
    assert main(["check", str(tmp_path)]) == 2
    assert capsys.readouterr().out.splitlines() == [
        f"{tmp_path / 'b.json'}: no such file or directory"]


def test_thousands_of_files_in_bounded_time_and_memory(tmp_path: Path) -> None:
    """2,000 device files of one address list (10,000 took 6.1 s and 50 MB here: the
    list's items are validated once, config/item_cache.py)."""
    text = json.dumps(device("d"))
    for i in range(2000):
        (tmp_path / f"d{i:05}.json").write_text(text.replace('"d"', f'"d{i}"'))
    code, lines, took, peak = run_check(tmp_path)
    assert (code, lines) == (0, ["ok: 2000 device files (20000 items, 2000 requests per "
                                 "cycle), 0 gateway files"])
    assert took < 60 and peak < 200, (took, peak)


def test_a_fifo_put_in_place_after_the_stat_never_blocks_a_read(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """config/jsonfile.py and gateway/config.py's file_bytes stat a file, then open it:
    a FIFO put there in between blocked the open forever (the reload thread, a check).
    The stat is played here by one of a regular file; the open must not block."""
    import threading

    from edgemodbus.config import ConfigError, load_device_config
    from edgemodbus.gateway.config import file_bytes

    regular = tmp_path / "regular.json"
    regular.write_text("{}")
    fifo = tmp_path / "dev.json"
    os.mkfifo(fifo)
    real_stat = os.stat

    def stat_before_the_swap(path: Any, *args: Any, **kwargs: Any) -> os.stat_result:
        return real_stat(regular if os.fspath(path) == str(fifo) else path, *args, **kwargs)

    monkeypatch.setattr(os, "stat", stat_before_the_swap)
    outcomes: list[object] = []

    def read() -> None:
        try:
            load_device_config(fifo)
        except ConfigError as exc:
            outcomes.append(str(exc))
        outcomes.append(file_bytes(fifo))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(20)
    if reader.is_alive():  # let the blocked open go, then fail
        with open(fifo, "wb"):
            pass
        reader.join(5)
        raise AssertionError("a read of the FIFO blocked")
    assert outcomes[0] == f"{fifo}: is a FIFO: give a JSON file", outcomes
    assert isinstance(outcomes[1], bytes) and outcomes[1].startswith(b"not a regular file")


@pytest.mark.parametrize("kind", ["fifo", "broken link", "symlink loop", "directory"])
def test_a_gateway_file_that_is_no_regular_file_is_a_problem_not_none(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str) -> None:
    """gateway.json as a FIFO, a broken link, a symlink loop or a folder: the gateway
    and check took it as no gateway file (defaults: no MQTT, no console) without a word.
    Now check says what it is (exit 2) and the gateway does not start (exit 2)."""
    from edgemodbus.gateway.run import run_service

    gateway = tmp_path / "gateway.json"
    if kind == "fifo":
        os.mkfifo(gateway)
    elif kind == "broken link":
        gateway.symlink_to(tmp_path / "nowhere")
    elif kind == "symlink loop":
        gateway.symlink_to("gateway.json")
    else:
        gateway.mkdir()
    assert main(["check", str(tmp_path)]) == 2
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{gateway}: "), lines
    assert run_service(tmp_path, seconds=0.1) == 2
    assert str(gateway) in capsys.readouterr().err
