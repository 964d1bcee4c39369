"""cffi build script (out-of-line API mode) for ``edgemodbus._native``.

The module links Debian's libmodbus (found with pkg-config) and compiles our C in csrc/.
cdefs live in csrc/cdefs/NN_*.h, one file per C library or module we bind, so the binding layer
declares only what it uses. A fingerprint of the sources is compiled in so that an
extension built from older sources fails loudly at import (see src/edgemodbus/_ffi/native.py).
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

from cffi import FFI

ROOT = Path(__file__).resolve().parent
CSRC = ROOT / "csrc"
CFLAGS = ["-Wall", "-Wextra", "-O2", "-std=c11", "-D_DEFAULT_SOURCE"]
# Warnings are errors in development and CI builds only (the Makefile and .ci set
# EDGEMODBUS_WERROR=1): a user building the sdist with a newer compiler gets a warning,
# not a failed install.
WERROR = os.environ.get("EDGEMODBUS_WERROR", "") == "1"
INSTALL_HINT = "apt-get install libmodbus-dev pkg-config"


def _source_hash() -> str:
    spec = importlib.util.spec_from_file_location(
        "_emb_sourcehash", ROOT / "src" / "edgemodbus" / "_ffi" / "sourcehash.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return str(module.source_hash(ROOT))


def _pkg_config(*args: str) -> list[str]:
    if shutil.which("pkg-config") is None:
        sys.exit(f"edgemodbus: pkg-config is missing; install it: {INSTALL_HINT}")
    proc = subprocess.run(
        ["pkg-config", *args, "libmodbus"], capture_output=True, text=True, check=False
    )
    if proc.returncode != 0:
        sys.exit(
            f"edgemodbus: libmodbus not found by pkg-config ({proc.stderr.strip()}); "
            f"install it: {INSTALL_HINT}"
        )
    return proc.stdout.split()


def _make_builder() -> FFI:
    cflags = _pkg_config("--cflags")
    libs = _pkg_config("--libs")
    version = _pkg_config("--modversion")[0]
    if not version.startswith("3.1."):
        sys.exit(f"edgemodbus: needs libmodbus 3.1.x (Debian bookworm ships 3.1.6), found {version}")

    builder = FFI()
    # cdefs/NN_name.h: the number orders them (libmodbus types before our helpers).
    builder.cdef("\n".join(p.read_text() for p in sorted((CSRC / "cdefs").glob("*.h"))))
    builder.cdef("const char *emb_source_hash(void);")

    headers = "".join(f'#include "{p.name}"\n' for p in sorted(CSRC.glob("*.h")))
    preamble = (
        "#include <modbus.h>\n"
        f"{headers}"
        f'const char *emb_source_hash(void) {{ return "{_source_hash()}"; }}\n'
    )
    sources = [os.path.relpath(p, Path.cwd()) for p in sorted(CSRC.glob("*.c"))]
    builder.set_source(
        "edgemodbus._native",
        preamble,
        sources=sources,
        include_dirs=[str(CSRC)] + [f[2:] for f in cflags if f.startswith("-I")],
        libraries=[f[2:] for f in libs if f.startswith("-l")],
        library_dirs=[f[2:] for f in libs if f.startswith("-L")],
        extra_compile_args=CFLAGS + (["-Werror"] if WERROR else []),
    )
    return builder


ffibuilder = _make_builder()

if __name__ == "__main__":
    ffibuilder.compile(tmpdir=str(ROOT / "build"), verbose=True)
