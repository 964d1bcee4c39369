"""Bounded fuzzing of our C code and Python frame handling (`make fuzz`, `make fuzz-quick`).

Four libFuzzer harnesses in csrc/fuzz/, each built with Debian's clang and
-fsanitize=fuzzer,address,undefined (no UB recovery) into build/fuzz/:
  codec   fuzz_codec.c + csrc/emb_codec.c: plans, register blocks, decode and encode;
  frames  fuzz_frames.c (includes csrc/emb_io.c, the link kinds and the reply check,
          csrc/fuzz/fuzz_io_hooks.h), linked with libmodbus: scripted replies to reads and
          writes through the real transaction code, reply reader and reply check;
  stream  fuzz_stream.c (the same files): DTU streams, heartbeats and wrapped report
          frames, fed, answered or pumped;
  serve   fuzz_serve.c (includes csrc/emb_serve.c), linked with libmodbus: a master's
          byte stream into the Modbus TCP server's connection: MBAP framing, the request
          checks, libmodbus's replies, the answers Python posts.

1. Builds them; proves LeakSanitizer works here (a canary build must report a leak).
2. Runs each for its share of --seconds (codec 25 %, frames 30 %, stream 25 %, serve
   20 %) on
   build/fuzz/corpus-*
   (kept between runs) seeded by tools/fuzz_seeds.py, leak detection on; any crash,
   sanitizer report, leak, timeout or contract violation fails the run and leaves the
   input in build/fuzz/artifacts/.
3. Replays each corpus through a coverage build and reports the line and branch coverage
   of the C files under test (llvm-cov, from Debian's clang).
4. Runs the hypothesis fuzz tests of the write-reply check and the simulator's framing
   (tests/unit/ffi/test_fuzz_reply.py) and of the C wrapped framing against the Python
   parser (tests/unit/ffi/test_stream_framing.py) with --examples examples each.

Exit status 0 only if every step passed.  Full libFuzzer logs: build/fuzz/<name>.log.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "build" / "fuzz"
CSRC = ROOT / "csrc"
STRICT = ["-std=c11", "-D_DEFAULT_SOURCE", "-Wall", "-Wextra", "-Werror"]
SANITIZE = [
    "-fsanitize=fuzzer,address,undefined",
    "-fno-sanitize-recover=all",
    "-fno-omit-frame-pointer",
]
# quarantine kept small: the machine is shared
ASAN_OPTIONS = "detect_leaks=1:quarantine_size_mb=64:malloc_context_size=20:symbolize=1"
UBSAN_OPTIONS = "print_stacktrace=1:halt_on_error=1"
# libFuzzer lines worth showing live; the rest (NEW, REDUCE...) goes to the log only
SHOW = re.compile(
    r"INITED|DONE|ERROR|SUMMARY|runtime error|contract violated|Test unit written|"
    r"^==\d+==|#\d+ 0x"
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fuzz_seeds import write_seeds  # noqa: E402


@dataclass(frozen=True)
class Harness:
    name: str
    sources: tuple[Path, ...]  # compiled together
    covered: tuple[Path, ...]  # the files whose coverage is reported
    share: float  # of --seconds
    libmodbus: bool = False


HARNESSES = (
    Harness("codec", (CSRC / "fuzz" / "fuzz_codec.c", CSRC / "emb_codec.c"),
            (CSRC / "emb_codec.c",), 0.25),
    Harness("frames", (CSRC / "fuzz" / "fuzz_frames.c",),
            (CSRC / "emb_io.c", CSRC / "emb_rtu.c", CSRC / "emb_check.c"), 0.3,
            libmodbus=True),
    Harness("stream", (CSRC / "fuzz" / "fuzz_stream.c",), (CSRC / "emb_stream.c",), 0.25,
            libmodbus=True),
    Harness("serve", (CSRC / "fuzz" / "fuzz_serve.c",), (CSRC / "emb_serve.c",), 0.2,
            libmodbus=True),
)


def log(msg: str) -> None:
    print(f"fuzz: {msg}", flush=True)


def compiler() -> str:
    cc = os.environ.get("FUZZ_CC", "clang")
    if shutil.which(cc) is None:
        sys.exit(f"fuzz: {cc} not found; install Debian's clang (`apt-get install clang`)")
    return cc


def pkg_config(*args: str) -> list[str]:
    proc = subprocess.run(["pkg-config", *args, "libmodbus"], capture_output=True, text=True,
                          check=False)
    if proc.returncode != 0:
        sys.exit(f"fuzz: libmodbus not found by pkg-config: {proc.stderr.strip()}")
    return proc.stdout.split()


def build(cc: str, h: Harness, out: Path, extra: list[str]) -> None:
    flags = pkg_config("--cflags") if h.libmodbus else []
    libs = pkg_config("--libs") if h.libmodbus else []
    cmd = [cc, "-g", "-O1", *STRICT, *extra, *flags, *map(str, h.sources), *libs, "-lm",
           "-o", str(out)]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout + proc.stderr)
        sys.exit(f"fuzz: building {out.name} failed: {' '.join(cmd)}")


def sanitizer_env() -> dict[str, str]:
    env = dict(os.environ)
    env["ASAN_OPTIONS"] = ASAN_OPTIONS
    env["UBSAN_OPTIONS"] = UBSAN_OPTIONS
    env.pop("LD_PRELOAD", None)
    return env


def leak_canary(cc: str) -> None:
    """A deliberate leak must be reported, or a clean run would prove nothing."""
    binary = OUT / "fuzz_codec_canary"
    build(cc, HARNESSES[0], binary, [*SANITIZE, "-DEMB_FUZZ_LEAK_CANARY"])
    probe = OUT / "canary-input"
    probe.write_bytes(b"LEAK!")
    proc = subprocess.run(
        [str(binary), str(probe)], env=sanitizer_env(), capture_output=True, text=True,
        timeout=120, check=False,
    )
    if proc.returncode == 0 or "LeakSanitizer: detected memory leaks" not in proc.stderr:
        sys.stderr.write(proc.stderr[-3000:])
        sys.exit("fuzz: LeakSanitizer did not report the canary leak: leak detection is off")
    log("leak canary: LeakSanitizer reports leaks (detection armed)")


def run_fuzzer(name: str, binary: Path, seconds: int, corpus: Path, seeds: Path) -> dict[str, str]:
    """libFuzzer for `seconds`; returns its final stats. Exits on any finding."""
    artifacts = OUT / "artifacts"
    artifacts.mkdir(parents=True, exist_ok=True)
    cmd = [
        str(binary),
        str(corpus),
        str(seeds),
        f"-max_total_time={seconds}",
        "-timeout=10",
        "-rss_limit_mb=1536",
        "-max_len=4096",
        "-detect_leaks=1",
        "-print_final_stats=1",
        f"-artifact_prefix={artifacts}/{name}-",
    ]
    logfile = OUT / f"{name}.log"
    stats: dict[str, str] = {}
    last_status = ""
    tail: deque[str] = deque(maxlen=80)
    log(f"{name}: libFuzzer for {seconds} s: {binary.relative_to(ROOT)} {' '.join(cmd[3:])}")
    with logfile.open("w") as fh:
        proc = subprocess.Popen(
            cmd, cwd=ROOT, env=sanitizer_env(), stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True, errors="replace",
        )
        assert proc.stdout is not None
        deadline = time.monotonic() + seconds + 300
        for line in proc.stdout:
            fh.write(line)
            tail.append(line)
            stat = re.match(r"stat::(\w+):\s*(\S+)", line)
            if stat:
                stats[stat[1]] = stat[2]
            if " cov: " in line:
                last_status = line.strip()
            if SHOW.search(line) and "NEW_FUNC" not in line:
                print("  " + line.rstrip(), flush=True)
            if time.monotonic() > deadline:
                proc.kill()
        rc = proc.wait()
    if rc != 0:
        sys.stderr.write("".join(tail))
        found = sorted(artifacts.glob(f"{name}-*"), key=lambda p: p.stat().st_mtime)
        where = f"; reproduce: {binary.relative_to(ROOT)} {found[-1]}" if found else ""
        sys.exit(f"fuzz: {name} failed (exit {rc}), log {logfile.relative_to(ROOT)}{where}")
    stats["status"] = last_status
    return stats


def coverage(cc: str, h: Harness, corpus: Path, seeds: Path) -> str:
    """Line and branch coverage of the file under test by the corpus, or why not."""
    profdata, llvm_cov = shutil.which("llvm-profdata"), shutil.which("llvm-cov")
    if profdata is None or llvm_cov is None:
        return "coverage: llvm-profdata/llvm-cov not found (they come with Debian's clang)"
    binary = OUT / f"fuzz_{h.name}_cov"
    build(cc, h, binary, ["-fsanitize=fuzzer", "-fprofile-instr-generate", "-fcoverage-mapping"])
    raw, merged = OUT / f"{h.name}.profraw", OUT / f"{h.name}.profdata"
    raw.unlink(missing_ok=True)
    env = dict(os.environ, LLVM_PROFILE_FILE=str(raw))
    subprocess.run([str(binary), "-runs=0", str(corpus), str(seeds)], env=env,
                   capture_output=True, check=False, timeout=600)
    subprocess.run([profdata, "merge", "-sparse", str(raw), "-o", str(merged)], check=True)
    report = subprocess.run(
        [llvm_cov, "report", str(binary), f"-instr-profile={merged}", *map(str, h.covered)],
        capture_output=True, text=True, check=True,
    ).stdout
    for line in report.splitlines():
        if line.startswith("TOTAL"):
            # Regions Missed Cover Functions Missed Executed Lines Missed Cover Branches ...
            f = line.split()
            covered = int(f[7]) - int(f[8])
            names = ", ".join(str(p.relative_to(ROOT)) for p in h.covered)
            return (f"coverage of {names}: lines {f[9]} "
                    f"({covered}/{f[7]}), branches {f[12]}, functions {f[6]}")
    return "coverage: no report"


def python_fuzz(examples: int) -> None:
    env = dict(os.environ, EDGEMODBUS_FUZZ_EXAMPLES=str(examples))
    env.pop("LD_PRELOAD", None)
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
           "tests/unit/ffi/test_fuzz_reply.py", "tests/unit/ffi/test_stream_framing.py"]
    log(f"hypothesis: {examples} examples per test: {' '.join(cmd[2:])}")
    start = time.monotonic()
    proc = subprocess.run(cmd, cwd=ROOT, env=env, check=False)
    if proc.returncode != 0:
        sys.exit("fuzz: the Python frame fuzz tests failed")
    log(f"hypothesis: passed in {time.monotonic() - start:.1f} s")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=int, default=300, help="libFuzzer time, in all")
    parser.add_argument("--examples", type=int, default=2000, help="hypothesis examples/test")
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    cc = compiler()
    start = time.monotonic()
    for h in HARNESSES:
        build(cc, h, OUT / f"fuzz_{h.name}", SANITIZE)
    leak_canary(cc)
    counts = write_seeds(OUT)
    log("seed corpora: " + ", ".join(f"{n} {h}" for h, n in counts.items()))
    for h in HARNESSES:
        seconds = max(1, round(args.seconds * h.share))
        corpus, seeds = OUT / f"corpus-{h.name}", OUT / f"seeds-{h.name}"
        corpus.mkdir(exist_ok=True)
        stats = run_fuzzer(h.name, OUT / f"fuzz_{h.name}", seconds, corpus, seeds)
        runs = int(stats.get("number_of_executed_units", "0"))
        cov = re.search(r"cov: (\d+) ft: (\d+) corp: (\d+)", stats.get("status", ""))
        edges = f", {cov[1]} edges, {cov[2]} features, corpus {cov[3]}" if cov else ""
        log(
            f"{h.name}: {runs} inputs in {seconds} s, "
            f"{stats.get('average_exec_per_sec', '?')} exec/s{edges}, peak RSS "
            f"{stats.get('peak_rss_mb', '?')} MB: no crash, no sanitizer report, no leak"
        )
        log(f"{h.name}: {coverage(cc, h, corpus, seeds)}")
    python_fuzz(args.examples)
    log(f"all passed in {time.monotonic() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
