"""Fingerprint of the C sources the native module is built from.

build_ffi.py compiles this fingerprint into ``edgemodbus._native``; ``_binding`` recomputes
it in a source checkout and refuses to run an extension built from other sources.
"""

from __future__ import annotations

import hashlib
from pathlib import Path


def source_hash(root: Path) -> str:
    """Hash build_ffi.py and every .c/.h file under root/csrc (paths and contents)."""
    digest = hashlib.sha256()
    files = [root / "build_ffi.py"]
    files += sorted(p for p in (root / "csrc").rglob("*") if p.suffix in (".c", ".h"))
    for path in files:
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
        digest.update(b"\0")
    return digest.hexdigest()[:16]
