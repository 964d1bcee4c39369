"""Build ``edgemodbus._native`` with AddressSanitizer and UBSan into build-asan/.

The same sources and cdefs as the normal build (setup.py -> build_ffi.py), compiled with
-fsanitize=address,undefined -fno-omit-frame-pointer -fno-sanitize-recover=undefined, so
any out-of-bounds access or undefined behaviour aborts the test run.  ``edgemodbus._ffi`` loads
this build instead of the installed one when EDGEMODBUS_NATIVE=asan; the Python process
itself is not instrumented, so libasan must be preloaded (``make test-asan`` does it):

    ASAN_OPTIONS=detect_leaks=0 LD_PRELOAD=$(gcc -print-file-name=libasan.so) \\
        EDGEMODBUS_NATIVE=asan python -m pytest tests/unit/codec
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "build-asan"
SANITIZE = "-fsanitize=address,undefined -fno-omit-frame-pointer -fno-sanitize-recover=undefined"


def main() -> int:
    env = dict(os.environ)
    env["CFLAGS"] = f"{SANITIZE} -g {env.get('CFLAGS', '')}".strip()
    env["LDFLAGS"] = f"{SANITIZE} {env.get('LDFLAGS', '')}".strip()
    cmd = [
        sys.executable,
        "setup.py",
        "-q",
        "build_ext",
        "--force",
        "--build-lib",
        str(OUT / "lib"),
        "--build-temp",
        str(OUT / "tmp"),
    ]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, check=False)
    if proc.returncode != 0:
        print("asan_build: the sanitizer build failed", file=sys.stderr)
        return proc.returncode
    built = sorted((OUT / "lib" / "edgemodbus").glob("_native*.so"))
    if not built:
        print(f"asan_build: no extension found under {OUT / 'lib'}", file=sys.stderr)
        return 1
    print(f"asan_build: {built[0].relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
