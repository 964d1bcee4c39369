"""Loading the cffi extension ``edgemodbus._native``: its ``ffi`` and ``lib``, the check
that it was built from this checkout's C sources, and the libmodbus limits."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

# The source checkout this package sits in (src/edgemodbus/_ffi/ -> the top), where
# build-asan/, csrc/ and build_ffi.py are.
_CHECKOUT = Path(__file__).resolve().parents[3]


def _load_native() -> Any:
    """The cffi extension; with EDGEMODBUS_NATIVE=asan the AddressSanitizer build from
    build-asan/ (tools/asan_build.py; run with libasan preloaded, see `make test-asan`)."""
    if os.environ.get("EDGEMODBUS_NATIVE", "") != "asan":
        import edgemodbus._native as native

        return native
    import importlib.util
    import sys

    lib_dir = _CHECKOUT / "build-asan" / "lib" / "edgemodbus"
    found = sorted(lib_dir.glob("_native*.so"))
    if not found:
        raise ImportError(f"EDGEMODBUS_NATIVE=asan but {lib_dir} holds no build")
    spec = importlib.util.spec_from_file_location("edgemodbus._native", found[0])
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules["edgemodbus._native"] = module
    return module


try:
    _native_module = _load_native()
    ffi, lib = _native_module.ffi, _native_module.lib
except ImportError as exc:  # pragma: no cover - depends on the build
    raise ImportError(
        "edgemodbus._native is not built or cannot load libmodbus "
        f"({exc}); build it with `make build` (pip install -e .) after "
        "`apt-get install libmodbus-dev pkg-config`"
    ) from exc


def check_fingerprint(built: str, root: Path) -> None:
    """Refuse an extension compiled from other C sources than ``root`` (a source
    checkout) holds; an installed wheel has no csrc/ next to it and is not checked."""
    if not ((root / "csrc").is_dir() and (root / "build_ffi.py").is_file()):
        return
    from .sourcehash import source_hash

    current = source_hash(root)
    if built != current:
        raise ImportError(
            f"edgemodbus._native was built from other sources (fingerprint {built}) than "
            f"{root / 'csrc'} now holds ({current}); rebuild it: `make build` "
            "(or pip install -e .)"
        )


def _check_build() -> None:
    built = ffi.string(lib.emb_source_hash()).decode()
    check_fingerprint(built, _CHECKOUT)


_check_build()

# libmodbus's own limits, as compiled: the sizes of the buffers it fills.  Above _ffi/ the
# protocol's limits come from protocol/limits.py, which tests/unit/protocol/test_limits.py
# checks against these (and against our C's, lib.EMB_*).
MAX_READ_REGISTERS: int = lib.MODBUS_MAX_READ_REGISTERS
MAX_READ_BITS: int = lib.MODBUS_MAX_READ_BITS
MAX_WRITE_REGISTERS: int = lib.MODBUS_MAX_WRITE_REGISTERS
MAX_WRITE_BITS: int = lib.MODBUS_MAX_WRITE_BITS
MAX_ADU_LENGTH: int = lib.MODBUS_TCP_MAX_ADU_LENGTH
MAX_HEARTBEAT: int = lib.EMB_HB_MAX  # the longest DTU heartbeat a link skips (emb_link.hb)
