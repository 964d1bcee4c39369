"""System calls per block read, ours against libmodbus's own, counted by strace.

Run it: ``.venv/bin/python -m bench.syscalls`` (needs strace and ptrace allowed; not a
pytest module).  It starts our simulator in its own process (bench/slave_process.py,
raw RTU frames over TCP on 127.0.0.1) and, for each reader, runs a child process under
``strace -c -f`` that connects a :class:`edgemodbus._ffi.Context` to it and reads one
120-register block ``--reads`` times: ``libmodbus`` (``Context.read_libmodbus``:
``modbus_read_registers``, a select() and a read() per phase of the reply) and ``ours``
(``Context.read``: csrc/emb_io.c ``emb_read`` over csrc/emb_rtu.c).  The child runs
twice, with no reads and with ``--reads``, and the difference per syscall over the reads
is printed: what one block read costs, without the interpreter's start-up.  The child's
own counter (:attr:`Context.syscalls`, our reader's only) is printed beside it.  The
figures are in docs/performance.md.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
from collections import Counter

from bench.slave_process import SimulatorProcess
from edgemodbus._ffi import Context

READERS = ("libmodbus", "ours")
COUNT = 120  # registers per block, the driver bench's maxBlockReadRegisterCount


def read_blocks(port: int, reader: str, reads: int) -> int:
    """In the child: ``reads`` block reads of slave 1 through ``reader``; returns what
    our reader's counter says it made (0 for libmodbus)."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=5)
    sock.settimeout(None)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    ctx = Context.on_socket(sock.fileno(), "syscalls", mbap=False)
    try:
        ctx.set_timeouts(1.0, 0.2)
        before = ctx.syscalls
        for _ in range(reads):
            if reader == "libmodbus":
                ctx.read_libmodbus(1, 0, COUNT)
            else:
                ctx.read(1, 3, 0, COUNT)
        return ctx.syscalls - before
    finally:
        ctx.close()
        sock.close()


def strace_counts(port: int, reader: str, reads: int) -> tuple[Counter[str], int]:
    """The syscalls of a child doing ``reads`` block reads, by name (strace -c -f), and
    what our reader's counter said."""
    with tempfile.NamedTemporaryFile("r", suffix=".strace") as out:
        child = subprocess.run(
            ["strace", "-c", "-f", "-U", "name,calls", "-o", out.name, sys.executable,
             "-m", "bench.syscalls", "--child", str(port), reader, str(reads)],
            check=True, stdout=subprocess.PIPE, text=True,
            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
        )
        counts: Counter[str] = Counter()
        for line in out.read().splitlines():
            parts = line.split()
            if len(parts) == 2 and parts[1].isdigit() and parts[0] != "total":
                counts[parts[0]] = int(parts[1])
        return counts, int(child.stdout.split()[-1])


def per_read(port: int, reader: str, reads: int) -> tuple[dict[str, float], float]:
    """Syscalls per block read by name: (run with ``reads``) - (run with none), / reads;
    and our reader's own count per read."""
    base, _ = strace_counts(port, reader, 0)
    full, counted = strace_counts(port, reader, reads)
    names = set(base) | set(full)
    diff = {n: (full[n] - base[n]) / reads for n in names}
    return {n: v for n, v in sorted(diff.items()) if v >= 0.05}, counted / reads


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reads", type=int, default=2000)
    parser.add_argument("--child", nargs=3, metavar=("PORT", "READER", "READS"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        port, reader, reads = int(args.child[0]), args.child[1], int(args.child[2])
        print(read_blocks(port, reader, reads))
        return
    with SimulatorProcess([1], size=2000) as sim:
        for reader in READERS:
            counts, per = per_read(sim.port, reader, args.reads)
            total = sum(counts.values())
            shown = ", ".join(f"{n} {v:.2f}" for n, v in counts.items())
            own = f" (the link counted {per:.2f})" if reader == "ours" else ""
            print(f"{reader:10s} {total:5.2f} syscalls per {COUNT}-register read: "
                  f"{shown}{own}")


if __name__ == "__main__":
    main()
