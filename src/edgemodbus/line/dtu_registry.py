"""The DTU listeners of a process: one :class:`DtuListener` per listen port, refcounted by
its DTU slots, and one :class:`DtuSlot` per DTU id, refcounted by the devices that name
it (:data:`registry` is the process's; the driver acquires from it)."""

from __future__ import annotations

import threading
from collections import Counter
from typing import Any

from .admission import Networks
from .dtu_listener import DtuListener
from .dtu_slot import DtuSlot
from .endpoint import DtuEndpoint
from .loop_pool import pool
from .registration import DtuAccess, PortSettings

ENGINES = ("thread", "loop")


class DtuRegistry:
    """One listener per listen port, refcounted by its DTU slots; one slot per DTU id,
    refcounted by the devices that name it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._listeners: dict[tuple[str, int], DtuListener] = {}
        self._slots: dict[tuple[str, int, str], tuple[DtuSlot, int]] = {}
        self._balancers = Networks((), "fleet.loadBalancers")
        self.engine = "loop"  # what serves the lines of DTUs acquired from now on
        self._loop_threads: int | None = None  # set_engine's (None: one per core)
        self._asked: Counter[int] = Counter()  # loopThreads of the open DTUs that set it

    def set_engine(self, engine: str, loop_threads: int | None = None) -> None:
        """``engine``: "thread" (a thread per DTU line) or "loop" (the DTU lines on
        loop threads: line/loop.py), for the DTU lines started from now on, where the
        port's settings name none; ``loop_threads``: the loop threads while no open DTU
        asks for a number (None: one per core).  ValueError names a bad value."""
        if engine not in ENGINES:
            raise ValueError(f"engine {engine!r}: must be one of {', '.join(ENGINES)}")
        pool.configure(loop_threads)  # checks it
        with self._lock:
            self.engine = engine
            self._loop_threads = loop_threads
            self._size_pool()

    def _size_pool(self) -> None:
        """The loop threads of the process: the largest ``loopThreads`` among the open
        DTUs (each DTU's as its first device asked), else set_engine's, else one per
        core; for workers started from now on (running ones stay until their last line
        leaves).  The largest wins, so the order devices start in does not matter."""
        asked = [threads for threads, users in self._asked.items() if users > 0]
        pool.configure(max(asked) if asked else self._loop_threads)

    def set_load_balancers(self, cidrs: tuple[str, ...]) -> None:
        """The load balancers whose connections start with a PROXY v2 header (the
        gateway file's ``fleet.loadBalancers``), for every listen port, now and later.
        ValueError names a bad network."""
        balancers = Networks(cidrs, "fleet.loadBalancers")
        with self._lock:
            self._balancers = balancers
            for listener in self._listeners.values():
                listener.balancers = balancers

    def acquire(self, settings: PortSettings, endpoint: DtuEndpoint,
                access: DtuAccess | None = None) -> DtuSlot:
        access = access or DtuAccess()
        with self._lock:
            listener = self._listeners.get(settings.key)
            if listener is not None:
                diffs = listener.settings.differences(settings)
                if diffs:
                    raise ValueError(f"listenPort {settings.port}: devices on one listen port "
                                     "must agree; this device has " + "; ".join(diffs))
            key = (*settings.key, endpoint.dtu_id)
            entry = self._slots.get(key)
            if entry is not None:
                slot, users = entry
                if slot.endpoint != endpoint:
                    raise ValueError(f"dtuId {endpoint.dtu_id!r}: already open as "
                                     f"'{slot.endpoint.describe()}'; this device asks for "
                                     f"'{endpoint.describe()}': devices on one DTU must agree")
                if slot.access != access:
                    raise ValueError(f"dtuId {endpoint.dtu_id!r}: devices on one DTU must "
                                     "agree on dtuAllowFrom and registrationKey")
                self._slots[key] = (slot, users + 1)
                return slot
            if listener is None:
                listener = DtuListener(settings, self._balancers)
                self._listeners[settings.key] = listener
            elif settings.registration == "none" and listener.slot_count():
                raise ValueError(f"dtuId {endpoint.dtu_id!r}: port {settings.port} has no "
                                 "registration and already serves a DTU; without a "
                                 "registration packet a port serves one DTU")
            slot = DtuSlot(endpoint, settings, access)
            slot.engine = settings.engine or self.engine  # the port's key, else the default
            if settings.engine is None and endpoint.framing == "wrapped-report":
                # auto: a wrapped DTU's reports are applied in C by a line thread's engine
                # (csrc/emb_report.c); on a loop link each still goes to Python
                slot.engine = "thread"
            if slot.engine == "loop" and settings.loop_threads is not None:
                self._asked[settings.loop_threads] += 1
                self._size_pool()
            listener.add_slot(slot)
            self._slots[key] = (slot, 1)
            return slot

    def release(self, slot: DtuSlot) -> None:
        stop: DtuListener | None = None
        with self._lock:
            key = (*slot.port.key, slot.dtu_id)
            entry = self._slots.get(key)
            if entry is None or entry[0] is not slot:
                return
            if entry[1] > 1:
                self._slots[key] = (slot, entry[1] - 1)
                return
            del self._slots[key]
            if slot.engine == "loop" and slot.port.loop_threads is not None:
                self._asked[slot.port.loop_threads] -= 1
                self._size_pool()
            listener = self._listeners[slot.port.key]
            listener.remove_slot(slot)
            if not listener.slot_count():
                del self._listeners[slot.port.key]
                stop = listener
        if stop is not None:
            stop.stop()

    def connected(self, host: str, port: int, dtu_id: str) -> bool:
        """Whether DTU ``dtu_id`` of listen port ``host:port`` is connected (held by
        this process, in a fleet's words); cheap: the MQTT thread asks per device."""
        entry = self._slots.get((host, port, dtu_id))  # one dict read: no lock needed
        return entry is not None and entry[0].connected()

    def listener(self, host: str, port: int) -> DtuListener | None:
        with self._lock:
            return self._listeners.get((host, port))

    def stats(self) -> dict[str, dict[str, int]]:
        """Per listen port ("host:port"): :attr:`DtuListener.stats`."""
        with self._lock:
            listeners = list(self._listeners.items())
        return {f"{h}:{p}": li.stats for (h, p), li in listeners}

    def held(self) -> dict[str, list[dict[str, Any]]]:
        """Per listen port ("host:port"): :meth:`DtuListener.held`."""
        with self._lock:
            listeners = list(self._listeners.items())
        return {f"{h}:{p}": li.held() for (h, p), li in listeners}


registry = DtuRegistry()

__all__ = ["ENGINES", "DtuRegistry", "registry"]
