"""``edgemodbus demo | head -3`` (and ``run``): when the reader of stdout goes away the
command stops polling and exits with 1, without a traceback per item update (it logged
one BrokenPipeError traceback per value and polled on to the end of --seconds)."""

from __future__ import annotations

import subprocess
import sys
import time


def test_polling_stops_when_stdout_closes() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "edgemodbus.cli", "demo", "--seconds", "120"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stderr is not None
        first = proc.stdout.readline()
        assert first.startswith("simulator: "), first
        assert proc.stdout.readline()  # a value line: polling runs
        proc.stdout.close()  # the reader goes away, as `head` does
        started = time.monotonic()
        code = proc.wait(timeout=60)  # a generous deadline; --seconds is 120
        took = time.monotonic() - started
        stderr = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
    assert code == 1, stderr
    assert took < 60
    assert "Traceback" not in stderr and "Broken pipe" not in stderr, stderr
