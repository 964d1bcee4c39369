"""CPU and wall time per transaction on a baud-paced serial line (not a pytest benchmark:
run it as ``python -m bench.paced_line_cpu``).

A pymodbus serial slave (its own process) sits behind a :class:`tests.paced_relay.PacedLine`
that delivers every byte one character time after the previous one; the master reads
125 holding registers (a 255-byte reply) through the line's link, in this process, and
we count this process's CPU (all threads) per transaction.  Wire efficiency compares the
transaction time with what the wire needs at least: the request and reply frames at one
character time per byte, plus the t3.5 silence the master keeps between frames
(Modbus over Serial Line v1.02, 2.5.1.1).
"""

from __future__ import annotations

import argparse
import tempfile
import time

from tests.paced_relay import PacedLine
from tests.peers import PymodbusSlave, default_register

from edgemodbus._ffi import Context
from edgemodbus.datatypes import Area
from edgemodbus.line import LineTiming, SerialPort
from edgemodbus.line.connect import context_link
from edgemodbus.stats import LineStats

REQUEST_BYTES = 8  # slave fc address quantity crc (Application Protocol 6.3)


def measure(baudrate: int, transactions: int, count: int = 125) -> dict[str, float]:
    """Per transaction: CPU seconds of this process, wall seconds, and the wire minimum."""
    with tempfile.TemporaryDirectory() as tmp, PacedLine(tmp, baudrate) as line, \
            PymodbusSlave("serial", device=line.slave, baudrate=baudrate, units=(1,)):
        port = SerialPort(line.master, baudrate)
        timing = LineTiming(response_timeout=2.0, byte_timeout=0.5)
        ctx = Context.rtu(port.port, baudrate, port.parity, port.data_bits, port.stop_bits)
        ctx.connect()
        link = context_link(ctx, port, timing, LineStats(), None)  # I/O on this thread
        try:
            want = [default_register(1, "hr", a) for a in range(count)]
            assert link.read(1, Area.HOLDING_REGISTER, 0, count).to_list() == want
            cpu0, wall0 = time.process_time(), time.monotonic()
            for _ in range(transactions):
                link.read(1, Area.HOLDING_REGISTER, 0, count)
            cpu = (time.process_time() - cpu0) / transactions
            wall = (time.monotonic() - wall0) / transactions
        finally:
            link.close()
    wire = (REQUEST_BYTES + 5 + 2 * count) * port.char_time + port.frame_gap
    return {"cpu": cpu, "wall": wall, "wire": wire}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transactions", type=int, default=20)
    parser.add_argument("--baud", type=int, nargs="*", default=[9600, 115200])
    args = parser.parse_args()
    for baud in args.baud:
        r = measure(baud, args.transactions)
        print(f"{baud:>6} baud: CPU {r['cpu'] * 1e3:6.3f} ms/transaction, wall "
              f"{r['wall'] * 1e3:7.2f} ms, wire minimum {r['wire'] * 1e3:7.2f} ms "
              f"(efficiency {100 * r['wire'] / r['wall']:.0f} %)")


if __name__ == "__main__":
    main()
