"""Fingerprint of the C sources the native module is built from.

build_ffi.py compiles this fingerprint into ``edgemodbus._native``; ``edgemodbus._ffi``
recomputes it in a source checkout and refuses to run an extension built from other sources.
"""

from __future__ import annotations

import hashlib
from pathlib import Path


def source_hash(root: Path) -> str:
    """Hash what the extension is built from (paths and contents): build_ffi.py, the
    top-level csrc/*.c and *.h and the cdefs; not csrc/fuzz/, which it does not include."""
    digest = hashlib.sha256()
    csrc = root / "csrc"
    files = [root / "build_ffi.py"]
    files += sorted([*csrc.glob("*.c"), *csrc.glob("*.h"), *(csrc / "cdefs").glob("*.h")])
    for path in files:
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
        digest.update(b"\0")
    return digest.hexdigest()[:16]
