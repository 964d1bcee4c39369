"""Thousands of DTUs from one process: :class:`DtuFleet` plays a fleet of 4G/Ethernet
DTUs that dial in to a master listening in ``rtu-over-tcp-server`` mode.

Each DTU dials ``host:port``, sends its registration packet (text, e.g. ``DTU00042``),
answers the RTU requests for its slaves from its own register maps (one :class:`Slave`
each: the simulator's slave model, fault knobs included), optionally sends a heartbeat
every few seconds, and dials again when its connection drops (after ``reconnect``
seconds, doubling up to ``reconnect_max`` while its connections end before any request
came, as when a listener refuses it).

Everything runs on one asyncio event loop, no thread per DTU: a task per DTU keeps it
dialled, an :class:`asyncio.Protocol` per connection cuts requests out of the byte
stream (:func:`edgemodbus.protocol.rtu.split_frames`, the same rule as the
:class:`Simulator`'s lines) and hands them to the slaves.  Run it on a thread of its own
(:meth:`DtuFleet.start` / :meth:`DtuFleet.stop`, or ``with DtuFleet(...)``) or in an
event loop of yours (``await fleet.serve()`` until cancelled).

A fleet needs one file descriptor per DTU: :func:`raise_open_files_limit` raises the
soft ``RLIMIT_NOFILE`` to the hard limit when the soft one is too low, and says what to
do when the hard one is.  And one ephemeral port per DTU of each source address: Linux
gives a source address about 28,000 (``net.ipv4.ip_local_port_range``), so a fleet
larger than that dials from several (``sources``, e.g. :func:`loopback_sources`: the
DTUs bind to them in turn before they connect).  Several processes, each a fleet of its
own, share larger fleets out (sim/fleet_procs.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import random
import socket
import struct
import threading
from collections.abc import Callable, Iterable, Sequence

from ..datatypes import Area
from ..protocol import rtu
from .actions import _Reset
from .dialling import FD_MARGIN, check_sources, raise_open_files_limit
from .slave import Slave, answer

log = logging.getLogger("edgemodbus.simulator")

FLEET_SIZE = 1000
"""Points per data area of each slave of a fleet (a :class:`Simulator`'s are
:data:`DEFAULT_SIZE`): 5,000 DTUs of 10,000-point slaves would take 300 MB."""

_RX_LIMIT = 4096  # a request is at most 256 bytes (Serial Line 2.5.1); more is garbage


class FleetDtu:
    """One DTU of a fleet: its number, registration packet and slaves (each with its own
    register map; thread-safe), and its counters (written by the fleet's loop)."""

    def __init__(self, number: int, registration: bytes, slaves: dict[int, Slave]) -> None:
        self.number = number
        self.registration = registration
        self.slaves = slaves
        self.connections = 0  # TCP connections made
        self.dial_failures = 0  # connects refused or timed out
        self.requests = 0  # request frames cut out of the stream
        self.unknown_slave = 0  # requests for a slave id this DTU does not have
        self.discarded_bytes = 0  # garbage between requests
        self.heartbeats = 0
        self._connection: _Connection | None = None

    def __repr__(self) -> str:
        return f"FleetDtu({self.number}, {self.registration!r}, slaves={list(self.slaves)})"

    @property
    def connected(self) -> bool:
        return self._connection is not None

    def slave(self, slave_id: int) -> Slave:
        return self.slaves[slave_id]


class _Connection(asyncio.Protocol):
    """One TCP connection of one DTU: the registration, requests in, replies out, and
    heartbeats (all on the fleet's loop)."""

    def __init__(self, fleet: DtuFleet, dtu: FleetDtu, loop: asyncio.AbstractEventLoop) -> None:
        self.fleet = fleet
        self.dtu = dtu
        self.loop = loop
        self.transport: asyncio.Transport | None = None
        self.rx = bytearray()
        self.last_rx = 0.0
        self.idle_pending = False
        self.requests = 0
        self.closed: asyncio.Future[None] = loop.create_future()
        self._heartbeat: asyncio.TimerHandle | None = None

    # -- asyncio.Protocol
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        dtu, fleet = self.dtu, self.fleet
        dtu.connections += 1
        dtu._connection = self
        fleet._live.add(self)
        if dtu.registration:
            transport.write(dtu.registration)
        if fleet.heartbeat and fleet.heartbeat_interval > 0:
            first = fleet._rng.uniform(0.0, fleet.heartbeat_interval)  # spread the fleet's
            self._heartbeat = self.loop.call_later(first, self._beat)

    def data_received(self, data: bytes) -> None:
        self.last_rx = self.loop.time()
        self.rx += data
        if len(self.rx) > _RX_LIMIT:
            self.dtu.discarded_bytes += len(self.rx) - _RX_LIMIT
            del self.rx[: len(self.rx) - _RX_LIMIT]
        self._parse(idle=False)
        if self.rx and not self.idle_pending and not self.closing:
            self.idle_pending = True
            self.loop.call_at(self.last_rx + self.fleet.silence, self._idle_check)

    def connection_lost(self, exc: Exception | None) -> None:
        if self._heartbeat is not None:
            self._heartbeat.cancel()
        if self.dtu._connection is self:
            self.dtu._connection = None
        self.fleet._live.discard(self)
        if not self.closed.done():
            self.closed.set_result(None)

    # -- serving
    @property
    def closing(self) -> bool:
        return self.transport is None or self.transport.is_closing()

    def _idle_check(self) -> None:
        """The line has been silent for ``silence``: resolve what is left (as
        :meth:`Simulator._parse` does after t3.5)."""
        self.idle_pending = False
        if self.closing or not self.rx:
            return
        due = self.last_rx + self.fleet.silence
        if self.loop.time() < due:
            self.idle_pending = True
            self.loop.call_at(due, self._idle_check)
            return
        self._parse(idle=True)

    def _parse(self, idle: bool) -> None:
        frames, consumed, discarded = rtu.split_frames(self.rx, idle)
        del self.rx[:consumed]
        self.dtu.discarded_bytes += discarded
        for raw in frames:
            if self.closing:
                return
            self._serve(raw)

    def _serve(self, raw: bytes) -> None:
        self.requests += 1
        self.dtu.requests += 1
        actions = answer(self.dtu.slaves, raw, self.fleet._rng, True)
        if actions is None:
            self.dtu.unknown_slave += 1
            return  # nobody behind this DTU has the address: silence
        for after, data in actions:
            if after <= 0:
                self._act(data)
            else:
                self.loop.call_later(after, self._act, data)

    def _act(self, data: bytes | _Reset | None) -> None:
        transport = self.transport
        if transport is None or transport.is_closing():
            return
        if data is None:
            transport.close()
        elif isinstance(data, _Reset):  # linger 0: the close sends RST, not FIN
            sock = transport.get_extra_info("socket")
            if sock is not None:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            transport.abort()
        else:
            transport.write(data)

    def _beat(self) -> None:
        if self.closing:
            return
        assert self.transport is not None
        self.transport.write(self.fleet.heartbeat)
        self.dtu.heartbeats += 1
        self._heartbeat = self.loop.call_later(self.fleet.heartbeat_interval, self._beat)

    def abort(self) -> None:
        if self.transport is not None:
            self.transport.abort()

    def reset(self) -> None:
        """Close with a reset (RST, not FIN), as a network that drops it would."""
        self._act(_Reset())


class DtuFleet:
    """``count`` DTUs, numbered from ``first``, that dial ``host:port``.

    ``registration``: each DTU's registration packet, a template formatted with the
    DTU's number as ``n`` (``"DTU{n:05d}"`` -> ``DTU00042``, UTF-8), or a function of
    the number; ``""`` sends none (one DTU only).  ``slaves``, ``size``: the slave ids
    behind every DTU and the points per data area of each (their values derived from
    their address, as a :class:`Simulator`'s).  ``heartbeat`` is sent every
    ``heartbeat_interval`` seconds (0: never).  ``dial_rate``: new connections per
    second for the whole fleet (0: no limit).  ``sources``: local addresses the DTUs
    bind to before they connect, DTU ``n`` to ``sources[n % len(sources)]`` (empty: the
    kernel picks; see the module for when a fleet needs several).  ``mark``: a holding
    register address at which every slave holds its DTU's number (its low 16 bits), so
    that a master can tell the DTUs apart (None: every DTU the same values).

    >>> with DtuFleet("127.0.0.1", 9502, 1000) as fleet:   # doctest: +SKIP
    ...     fleet.dtu(7).slave(1).set_registers(Area.HOLDING_REGISTER, 0, [7])
    """

    def __init__(
        self,
        host: str,
        port: int,
        count: int,
        *,
        registration: str | Callable[[int], bytes] = "DTU{n:05d}",
        first: int = 0,
        slaves: Iterable[int] = (1,),
        size: int = FLEET_SIZE,
        heartbeat: bytes = b"",
        heartbeat_interval: float = 0.0,
        dial_rate: float = 0.0,
        reconnect: float = 1.0,
        reconnect_max: float = 30.0,
        connect_timeout: float = 5.0,
        silence: float = 0.02,
        seed: int | None = None,
        sources: Sequence[str] = (),
        mark: int | None = None,
    ) -> None:
        if count < 1:
            raise ValueError(f"a fleet of {count} DTUs: must be at least 1")
        if not 1 <= port <= 65535:
            raise ValueError(f"port {port}: must be 1..65535")
        if reconnect <= 0 or reconnect_max < reconnect:
            raise ValueError("reconnect must be > 0 and reconnect_max >= reconnect")
        self.host, self.port = host, port
        self.sources = check_sources(sources, host)
        self.heartbeat, self.heartbeat_interval = heartbeat, heartbeat_interval
        self.dial_rate, self.reconnect, self.reconnect_max = dial_rate, reconnect, reconnect_max
        self.connect_timeout, self.silence = connect_timeout, silence
        self._rng = random.Random(seed)
        packet = _packet_maker(registration)
        ids = list(slaves)
        self.dtus = [FleetDtu(n, packet(n), {sid: Slave(sid, size) for sid in ids})
                     for n in range(first, first + count)]
        if mark is not None:
            if not 0 <= mark < size:
                raise ValueError(f"mark {mark}: must be a register address 0..{size - 1}")
            for dtu in self.dtus:
                for slave in dtu.slaves.values():
                    slave.set_registers(Area.HOLDING_REGISTER, mark, [dtu.number & 0xFFFF])
        if count > 1 and self.dtus[0].registration == self.dtus[1].registration:
            raise ValueError(f"registration {registration!r} gives every DTU the same packet "
                             f"({self.dtus[0].registration!r}): put {{n}} in it")
        self._first = first
        self._live: set[_Connection] = set()  # loop only
        self._next_dial = 0.0
        self._stopping = False
        self._lock = threading.Lock()
        self._state = "new"
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._main: asyncio.Task[None] | None = None

    def __len__(self) -> int:
        return len(self.dtus)

    def dtu(self, number: int) -> FleetDtu:
        """The DTU numbered ``number`` (``first`` .. ``first + count - 1``)."""
        index = number - self._first
        if not 0 <= index < len(self.dtus):
            raise KeyError(f"no DTU number {number} in this fleet")
        return self.dtus[index]

    @property
    def connected(self) -> int:
        """DTUs whose TCP connection is up now."""
        return sum(1 for d in self.dtus if d.connected)

    def stats(self) -> dict[str, int]:
        """dtus, connected (up now), connections (made in all), reconnects (connections
        after each DTU's first), dial_failures, requests, unknown_slave, discarded_bytes,
        heartbeats: sums over the fleet."""
        out = dict.fromkeys(("connections", "dial_failures", "requests", "unknown_slave",
                             "discarded_bytes", "heartbeats"), 0)
        reconnects = connected = 0
        for d in self.dtus:
            for key in out:
                out[key] += getattr(d, key)
            reconnects += max(0, d.connections - 1)
            connected += d.connected
        return {"dtus": len(self.dtus), "connected": connected, "reconnects": reconnects, **out}

    # -- on a thread of its own

    def start(self) -> DtuFleet:
        """Start dialling on a thread of its own (one event loop for the whole fleet)."""
        with self._lock:
            if self._state == "running":
                return self
            if self._state == "stopped":
                raise RuntimeError("fleet stopped; create a new one")
            raise_open_files_limit(len(self.dtus) + FD_MARGIN)  # here, to raise in the caller
            ready = threading.Event()
            self._thread = threading.Thread(target=self._run_thread, args=(ready,),
                                            name="edgemodbus-dtu-fleet", daemon=True)
            self._state = "running"
            self._thread.start()
        if not ready.wait(10.0):
            raise RuntimeError("DTU fleet loop did not start")
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Close every connection, end every task and join the thread. Idempotent."""
        with self._lock:
            if self._state != "running":
                self._state = "stopped"
                return
            self._state = "stopped"
        loop, main, thread = self._loop, self._main, self._thread
        if loop is not None and main is not None:
            with contextlib.suppress(RuntimeError):  # the loop already ended
                loop.call_soon_threadsafe(main.cancel)
        if thread is not None:
            thread.join(timeout)
            if thread.is_alive():
                raise RuntimeError(f"DTU fleet did not stop within {timeout} s")

    def reset_all(self) -> None:
        """Every DTU's connection is reset at once (any thread), as after a network
        outage; each dials again after ``reconnect`` seconds (spread over its second
        half).  Returns once the resets are done."""
        loop = self._loop
        if loop is None:
            return

        def reset() -> None:
            for conn in list(self._live):
                conn.reset()

        with contextlib.suppress(RuntimeError):  # the loop already ended
            asyncio.run_coroutine_threadsafe(_call(reset), loop).result(30.0)

    def drop(self, number: int) -> None:
        """DTU ``number`` loses its connection (any thread); it dials again after
        ``reconnect`` seconds."""
        dtu, loop = self.dtu(number), self._loop
        if loop is None:
            return

        def close() -> None:
            if dtu._connection is not None:
                dtu._connection.abort()

        loop.call_soon_threadsafe(close)

    def __enter__(self) -> DtuFleet:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run_thread(self, ready: threading.Event) -> None:
        async def main() -> None:
            self._main = asyncio.current_task()
            ready.set()
            with contextlib.suppress(asyncio.CancelledError):
                await self.serve()

        try:
            asyncio.run(main())
        except Exception:
            log.exception("DTU fleet loop crashed")
        finally:
            ready.set()

    # -- in any event loop

    async def serve(self) -> None:
        """Keep every DTU dialled, in the running event loop, until cancelled; then close
        every connection."""
        raise_open_files_limit(len(self.dtus) + FD_MARGIN)
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._stopping = False
        # Resolved once, here: a numeric address lets asyncio connect without its
        # resolver thread pool.
        family, _, _, _, address = socket.getaddrinfo(self.host, self.port,
                                                      type=socket.SOCK_STREAM)[0]
        target = (family, str(address[0]))
        tasks = [loop.create_task(self._keep_dialled(dtu, target)) for dtu in self.dtus]
        try:
            await loop.create_future()  # until cancelled
        finally:
            # Cancelled again until done: before Python 3.12, wait_for() swallows a
            # cancellation that arrives as its connect fails (it raises the OSError).
            self._stopping = True
            pending = set(tasks)
            while pending:
                for task in pending:
                    task.cancel()
                _, pending = await asyncio.wait(pending, timeout=0.1)
            live = list(self._live)
            for conn in live:
                conn.abort()
            if live:
                await asyncio.wait([c.closed for c in live], timeout=5.0)
            self._loop = None

    async def _keep_dialled(self, dtu: FleetDtu, target: tuple[int, str]) -> None:
        loop = asyncio.get_running_loop()
        family, host = target
        delay = self.reconnect
        factory = functools.partial(_Connection, self, dtu, loop)
        local = (self.sources[dtu.number % len(self.sources)], 0) if self.sources else None
        while not self._stopping:
            await self._dial_turn(loop)
            served = 0
            try:
                _, conn = await asyncio.wait_for(
                    loop.create_connection(factory, host, self.port, family=family,
                                           local_addr=local),
                    self.connect_timeout)
            except (OSError, asyncio.TimeoutError) as exc:
                dtu.dial_failures += 1
                log.debug("DTU %d: dial failed: %s", dtu.number, exc)
            else:
                try:
                    await conn.closed
                finally:
                    conn.abort()  # cancelled: the fleet stops
                served = conn.requests
            # A connection that served requests was a good one: dial again soon.  Failed
            # dials and connections that ended before any request (refused, an unknown
            # id) back off.
            if served:
                delay = self.reconnect
            await asyncio.sleep(delay * self._rng.uniform(0.5, 1.0))
            if not served:
                delay = min(2 * delay, self.reconnect_max)

    async def _dial_turn(self, loop: asyncio.AbstractEventLoop) -> None:
        """Wait for this dial's turn under ``dial_rate``."""
        if self.dial_rate <= 0:
            return
        now = loop.time()
        at = max(now, self._next_dial)
        self._next_dial = at + 1.0 / self.dial_rate
        if at > now:
            await asyncio.sleep(at - now)


async def _call(fn: Callable[[], None]) -> None:
    fn()


def _packet_maker(registration: str | Callable[[int], bytes]) -> Callable[[int], bytes]:
    if callable(registration):
        return registration
    template = registration

    def packet(n: int) -> bytes:
        try:
            return template.format(n=n).encode()
        except (KeyError, IndexError, ValueError) as exc:
            raise ValueError(f"registration {template!r}: not a template of {{n}} "
                             f"(the DTU's number): {exc}") from None

    return packet


__all__ = ["FLEET_SIZE", "DtuFleet", "FleetDtu"]
