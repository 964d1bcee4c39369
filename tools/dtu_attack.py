"""An attacker, or a broken DTU, against a listen port (``rtu-over-tcp-server``).

An independent peer: the standard library only (asyncio, sockets), nothing of
edgemodbus, so it shares no code, and no bug, with the listener it attacks.  It runs as
its own process until --seconds pass or SIGTERM/SIGINT comes, then prints one JSON
summary of what it did on stdout and exits 0.

Cases (``-n`` connections each; ``--reconnect`` dials a connection again when the peer
closes it, after ``--reconnect-delay`` seconds):

* ``idle``: connect and send nothing.
* ``idle-reconnect``: the same, dialling again as soon as a connection is closed.
* ``random-registration``: send ``--bytes`` random bytes, then wait for the close.
* ``junk-stream``: stream random bytes at full speed from the first moment.
* ``slow-id ID``: send the registration of ID one byte per ``--interval`` seconds, then
  answer as an impostor (below).
* ``impostor ID``: register as ID at once and answer Modbus RTU read holding/input
  registers requests (FC03/FC04) with values of our own, ``(--value-base + address)``,
  never the real device's; other functions get exception 01 (Modbus Application
  Protocol v1.1b3, 7).  A minimal RTU slave with its own CRC-16.
* ``key-guess ID``: register as ID with a wrong key (``--template``'s ``{key}``, random
  hex), one guess per connection; with --reconnect, guess after guess.

``--template`` is the registration packet, ``{id}`` and ``{key}`` filled in (default
``{id}``; for a key, e.g. ``ID:{id};KEY:{key}\\r\\n`` with ``\\r\\n`` as escapes).
``--sources N`` spreads the connections over N local addresses 127.0.1.1, 127.0.1.2, ...
(loopback on Linux), ``--source ADDR`` uses one; by default the kernel picks.

    python tools/dtu_attack.py 127.0.0.1:9502 idle -n 2000 --seconds 20
    python tools/dtu_attack.py 127.0.0.1:9502 impostor DTU00001 --reconnect
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import errno
import ipaddress
import json
import random
import resource
import signal
import socket
import statistics
import struct
import sys
import time
from collections import Counter
from typing import Any

CASES = ("idle", "idle-reconnect", "random-registration", "junk-stream", "slow-id",
         "impostor", "key-guess")
WITH_ID = ("slow-id", "impostor", "key-guess")
JUNK_CHUNK = 64 * 1024


def crc16(data: bytes) -> int:
    """The Modbus RTU CRC (Modbus over Serial Line v1.02, 6.2.2): polynomial 0xA001
    (reflected 0x8005), initial 0xFFFF; sent low byte first."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def with_crc(pdu: bytes) -> bytes:
    return pdu + struct.pack("<H", crc16(pdu))


class RtuImpostor:
    """Cuts 8-byte FC03/FC04 requests out of a byte stream and answers them with values
    the real device does not hold (``base + address``)."""

    def __init__(self, base: int) -> None:
        self.base = base
        self.buf = bytearray()
        self.answered = 0
        self.discarded = 0

    def feed(self, data: bytes) -> bytes:
        self.buf += data
        out = bytearray()
        while len(self.buf) >= 8:
            frame = bytes(self.buf[:8])
            if crc16(frame[:6]) != struct.unpack("<H", frame[6:])[0]:
                del self.buf[0]  # resynchronise one byte on
                self.discarded += 1
                continue
            del self.buf[:8]
            slave, function, address, count = struct.unpack(">BBHH", frame[:6])
            if function in (3, 4) and 1 <= count <= 125:  # Application Protocol 6.3, 6.4
                values = [(self.base + address + i) & 0xFFFF for i in range(count)]
                out += with_crc(struct.pack(f">BBB{count}H", slave, function, 2 * count,
                                            *values))
            else:
                out += with_crc(bytes((slave, function | 0x80, 1)))  # illegal function
            self.answered += 1
        return bytes(out)


class Attack:
    """The connections of one case and their counters (all on one event loop)."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.host, port = args.target.rsplit(":", 1)
        self.port = int(port)
        self.rng = random.Random(args.seed)
        self.junk = self.rng.randbytes(4 * JUNK_CHUNK)  # sent in slices: cheap at full speed
        self.sources = source_addresses(args)
        self.count: Counter[str] = Counter()
        self.errors: Counter[str] = Counter()
        self.lifetimes: list[float] = []  # seconds the peer held each connection it closed
        self.open = 0
        self.max_open = 0
        self.started = time.monotonic()
        self.stopping = asyncio.Event()
        self.last_dial = 0.0

    # -- the connections
    async def slot(self, n: int) -> None:
        """One connection of the case, dialled again while --reconnect says so."""
        args = self.args
        while not self.stopping.is_set():
            await self.pace()
            if self.stopping.is_set():
                return
            self.count["dials"] += 1
            try:
                reader, writer = await asyncio.wait_for(self.dial(n), args.connect_timeout)
            except (OSError, asyncio.TimeoutError) as exc:
                self.count["connect_failed"] += 1
                self.errors[error_name(exc)] += 1
                await asyncio.sleep(max(args.reconnect_delay, 0.05))
                continue
            self.count["connected"] += 1
            self.open += 1
            self.max_open = max(self.max_open, self.open)
            since = time.monotonic()
            try:
                closed = await self.act(reader, writer)
            finally:
                self.open -= 1
                writer.transport.abort()
            if closed is not None:
                self.count["closed_by_peer"] += 1
                self.count[closed] += 1
                life = time.monotonic() - since
                self.lifetimes.append(life)
                if life < 1.0:
                    self.count["closed_within_1s"] += 1
            if not args.reconnect or self.stopping.is_set():
                return
            await asyncio.sleep(args.reconnect_delay)

    async def pace(self) -> None:
        """Wait for this dial's turn under --dial-rate."""
        rate = self.args.dial_rate
        if rate <= 0:
            return
        now = time.monotonic()
        at = max(now, self.last_dial + 1.0 / rate)
        self.last_dial = at
        if at > now:
            await asyncio.sleep(at - now)

    async def dial(self, n: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        local = (self.sources[n % len(self.sources)], 0) if self.sources else None
        reader, writer = await asyncio.open_connection(self.host, self.port, local_addr=local,
                                                       limit=1 << 20)
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return reader, writer

    async def act(self, reader: asyncio.StreamReader,
                  writer: asyncio.StreamWriter) -> str | None:
        """Play the case on one connection until the peer closes it (returns how: "eof",
        "reset") or we stop (None)."""
        case = self.args.case
        stop = asyncio.ensure_future(self.stopping.wait())
        work = asyncio.ensure_future(self.play(case, reader, writer))
        try:
            done, _ = await asyncio.wait({stop, work}, return_when=asyncio.FIRST_COMPLETED)
            if work in done:
                return work.result()
            return None
        finally:
            for task in (stop, work):
                task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await work

    async def play(self, case: str, reader: asyncio.StreamReader,
                   writer: asyncio.StreamWriter) -> str:
        try:
            if case == "random-registration":
                await self.send(writer, self.rng.randbytes(self.args.bytes))
            elif case == "junk-stream":
                return await self.stream(reader, writer)
            elif case == "slow-id":
                for i, byte in enumerate(self.registration()):
                    if i:
                        await asyncio.sleep(self.args.interval)
                    await self.send(writer, bytes((byte,)))
                self.count["registrations_sent"] += 1
                return await self.serve(reader, writer)
            elif case == "impostor":
                await self.send(writer, self.registration())
                self.count["registrations_sent"] += 1
                return await self.serve(reader, writer)
            elif case == "key-guess":
                await self.send(writer, self.registration())
                self.count["registrations_sent"] += 1
            return await self.until_closed(reader)
        except (ConnectionResetError, BrokenPipeError):
            return "reset"
        except OSError as exc:
            self.errors[error_name(exc)] += 1
            return "reset"

    def registration(self) -> bytes:
        key = self.rng.randbytes(8).hex() if self.args.case == "key-guess" else self.args.key
        return self.args.template.format(id=self.args.id, key=key).encode("latin-1")

    async def send(self, writer: asyncio.StreamWriter, data: bytes) -> None:
        writer.write(data)
        await writer.drain()
        self.count["bytes_sent"] += len(data)

    async def until_closed(self, reader: asyncio.StreamReader) -> str:
        """Read (and count) whatever comes until the peer closes: a Modbus request on a
        connection that only registered means the listener took us for the DTU."""
        while True:
            data = await reader.read(65536)
            if not data:
                return "eof"
            self.count["bytes_received"] += len(data)
            self.count["polled"] += 1

    async def stream(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> str:
        closed = asyncio.ensure_future(self.until_closed(reader))
        try:
            at = 0
            while not closed.done():
                chunk = self.junk[at:at + JUNK_CHUNK]
                at = (at + 4099) % (len(self.junk) - JUNK_CHUNK)  # another slice each time
                writer.write(chunk)
                await writer.drain()
                self.count["bytes_sent"] += len(chunk)
            return closed.result()
        finally:
            closed.cancel()

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> str:
        slave = RtuImpostor(self.args.value_base)
        while True:
            data = await reader.read(4096)
            if not data:
                return "eof"
            self.count["bytes_received"] += len(data)
            before = slave.answered
            reply = slave.feed(data)
            self.count["requests_answered"] += slave.answered - before
            if reply:
                await self.send(writer, reply)

    # -- the run
    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self.stopping.set)
        if self.args.seconds > 0:
            loop.call_later(self.args.seconds, self.stopping.set)
        tasks = [asyncio.ensure_future(self.slot(n)) for n in range(self.args.connections)]
        done = asyncio.ensure_future(asyncio.gather(*tasks, return_exceptions=True))
        await asyncio.wait({done, asyncio.ensure_future(self.stopping.wait())},
                           return_when=asyncio.FIRST_COMPLETED)
        self.stopping.set()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(asyncio.shield(done), 5.0)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def summary(self) -> dict[str, Any]:
        life = sorted(self.lifetimes)
        counts = {k: self.count[k] for k in (
            "dials", "connected", "connect_failed", "closed_by_peer", "eof", "reset",
            "closed_within_1s", "bytes_sent", "bytes_received", "registrations_sent",
            "requests_answered", "polled")}
        return {
            "case": self.args.case,
            "target": self.args.target,
            "id": self.args.id,
            "seconds": round(time.monotonic() - self.started, 3),
            "connections": self.args.connections,
            **counts,
            "held_at_end": counts["connected"] - counts["closed_by_peer"],
            "max_open": self.max_open,
            "errors": dict(self.errors),
            "lifetime_s": {"min": round(life[0], 3), "median": round(statistics.median(life), 3),
                           "max": round(life[-1], 3)} if life else None,
        }


def error_name(exc: BaseException) -> str:
    if isinstance(exc, asyncio.TimeoutError):
        return "timeout"
    code = getattr(exc, "errno", None)
    return errno.errorcode.get(code, str(code)) if code else type(exc).__name__


def source_addresses(args: argparse.Namespace) -> list[str]:
    if args.source:
        return [args.source]
    if args.sources:
        first = ipaddress.IPv4Address("127.0.1.1")
        return [str(first + k) for k in range(args.sources)]
    return []


def raise_nofile(needed: int) -> None:
    """One fd per connection: raise the soft open-files limit towards the hard one."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < needed:
        new = needed if hard == resource.RLIM_INFINITY else min(needed, hard)
        resource.setrlimit(resource.RLIMIT_NOFILE, (new, hard))


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("target", help="HOST:PORT of the listen port")
    parser.add_argument("case", choices=CASES)
    parser.add_argument("id", nargs="?", default="", help="the DTU id (slow-id, impostor, "
                        "key-guess)")
    parser.add_argument("-n", "--connections", type=int, default=1)
    parser.add_argument("--bytes", type=int, default=65536, help="random-registration: "
                        "bytes per connection")
    parser.add_argument("--seconds", type=float, default=0.0, help="stop after (0: on a signal)")
    parser.add_argument("--reconnect", action="store_true", help="dial again when closed")
    parser.add_argument("--reconnect-delay", type=float, default=0.0)
    parser.add_argument("--dial-rate", type=float, default=0.0, help="new connections per "
                        "second, all together (0: no limit)")
    parser.add_argument("--connect-timeout", type=float, default=5.0)
    parser.add_argument("--interval", type=float, default=1.0, help="slow-id: s per byte")
    parser.add_argument("--template", default="{id}", help="registration packet; {id}, {key}; "
                        "backslash escapes (\\r\\n) are decoded")
    parser.add_argument("--key", default="", help="the {key} of slow-id and impostor")
    parser.add_argument("--value-base", type=int, default=0xC000, help="impostor: answers "
                        "(base + address) & 0xFFFF")
    parser.add_argument("--sources", type=int, default=0, help="spread over N local "
                        "addresses 127.0.1.1...")
    parser.add_argument("--source", default="", help="one local source address")
    parser.add_argument("--seed", type=int, default=None)
    args = parser.parse_args(argv)
    if args.case in WITH_ID and not args.id:
        parser.error(f"{args.case} needs the DTU id")
    if args.case == "idle-reconnect":
        args.reconnect = True
    if args.connections < 1:
        parser.error("-n: at least 1")
    args.template = args.template.encode("latin-1").decode("unicode_escape")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    raise_nofile(args.connections + 64)
    attack = Attack(args)
    try:
        asyncio.run(attack.run())
    finally:
        print(json.dumps(attack.summary()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
