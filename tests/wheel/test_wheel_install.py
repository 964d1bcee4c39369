"""The wheel installs without root and without libmodbus (issue 29): ``make wheel-test``
builds the manylinux wheel (``make wheel``: libmodbus bundled by auditwheel), then this
test installs it with pip into a fresh venv inside a bare Debian bookworm root
(``debootstrap --variant=minbase`` with python3 and python3-venv only; made once under
build/ by the Makefile) and runs ``edgemodbus demo --seconds 3`` there, in a clean
environment.  The dependencies' wheels are downloaded beforehand on the host, so the
install inside the root needs no network.

Skipped unless EDGEMODBUS_WHEEL_ROOT names that root (``make test`` does not build it: it
takes about a minute to make and a download of some 60 MB)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT_ENV = os.environ.get("EDGEMODBUS_WHEEL_ROOT")
REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    not ROOT_ENV, reason="needs the bookworm root of `make wheel-test` (EDGEMODBUS_WHEEL_ROOT)")

# no pip cache either: the root stays as debootstrap made it for the next run
_CLEAN_ENV = {"PATH": "/usr/sbin:/usr/bin:/sbin:/bin", "HOME": "/root", "LANG": "C.UTF-8",
              "PIP_NO_CACHE_DIR": "1", "PIP_DISABLE_PIP_VERSION_CHECK": "1"}


def _wheel() -> Path:
    wheels = sorted((REPO / "dist").glob("edgemodbus-*-cp310-abi3-manylinux_*_x86_64.whl"))
    assert len(wheels) == 1, f"expected one manylinux abi3 wheel in dist/ (make wheel): {wheels}"
    return wheels[0]


def _in_root(root: Path, script: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """``sh -c script`` chrooted into ``root``, with a clean environment (no
    LD_LIBRARY_PATH, no pip configuration of the host)."""
    return subprocess.run(["chroot", str(root), "/bin/sh", "-c", script], env=_CLEAN_ENV,
                          capture_output=True, text=True, timeout=timeout, check=False)


@pytest.fixture
def root() -> Iterator[Path]:
    """The bare root, with the wheels copied in; what the test adds is removed after."""
    assert ROOT_ENV is not None
    path = Path(ROOT_ENV).resolve()
    assert (path / "usr/bin/python3").exists(), f"{path}: no python3 (make wheel-test makes it)"
    if os.geteuid() != 0:
        pytest.fail("chroot needs root: run make wheel-test as root (or with sudo)")
    wheels = path / "tmp/edgemodbus-wheels"
    shutil.rmtree(wheels, ignore_errors=True)
    wheels.mkdir(parents=True)
    wheel = _wheel()
    shutil.copy(wheel, wheels)
    # the dependencies' wheels, fetched on the host by its pip (same CPython minor version
    # as bookworm's python3 and the same platform); the wheel itself is already there
    subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--only-binary=:all:",
                    "-d", str(wheels), str(wheel)], check=True, timeout=600)
    try:
        yield path
    finally:
        shutil.rmtree(wheels, ignore_errors=True)
        shutil.rmtree(path / "opt/edgemodbus-venv", ignore_errors=True)


def test_the_wheel_installs_and_runs_the_demo_in_a_bare_root(root: Path) -> None:
    no_lib = _in_root(root, "ls /usr/lib/*/libmodbus* /lib/*/libmodbus* 2>/dev/null; "
                            "command -v edgemodbus; true")
    assert no_lib.stdout.strip() == "", f"the root is not bare: {no_lib.stdout}"
    version = _in_root(root, "python3 -c 'import sys; print(sys.version_info[:2] >= (3, 10))'")
    assert version.stdout.strip() == "True", version

    install = _in_root(root, "python3 -m venv /opt/edgemodbus-venv && "
                             "/opt/edgemodbus-venv/bin/pip install -q --no-index "
                             "--find-links /tmp/edgemodbus-wheels edgemodbus")
    assert install.returncode == 0, install.stderr
    demo = _in_root(root, "/opt/edgemodbus-venv/bin/edgemodbus demo --seconds 3", timeout=120)
    assert demo.returncode == 0, demo.stdout + demo.stderr
    lines = demo.stdout.splitlines()
    assert lines[0].startswith("simulator: slaves 1,2,3 on rtu-over-tcp://127.0.0.1:"), lines
    # values came through the bundled libmodbus: each device polled and summed up
    for code in ("Demo001-1", "Demo001-2", "Demo001-3"):
        assert any(f" {code} " in line and " Counter " in line for line in lines), lines
        summary = [line for line in lines if line.startswith(f"{code}: ")]
        assert len(summary) == 1 and " 0 timeouts" in summary[0], lines

    # the extension found the library auditwheel bundled (RPATH), not a system one
    libs = _in_root(root, "ls /opt/edgemodbus-venv/lib/python3*/site-packages/edgemodbus.libs/")
    assert libs.stdout.startswith("libmodbus-"), libs.stdout + libs.stderr
