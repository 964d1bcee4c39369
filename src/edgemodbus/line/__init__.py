"""The line layer: talking Modbus to slaves over one medium, one request at a time.

A *line* is the medium (a serial port, a TCP peer, a DTU that dials in to a listen port)
and the worker thread that serves it; a *link* is one open connection on it; an
*endpoint* is its address.  The layer above (the driver and its device pollers) acquires
a line from a registry, attaches a poller, and submits requests; it never touches a
socket or a libmodbus context.

* endpoint.py: endpoints and line timing (plain data), built from a device's
  communication parameters by :func:`endpoint_for`;
* link.py: the worker's blocking view of an open line: the interface (``Link``) and
  the link on a libmodbus context and our C (``ContextLink``), which also frames DTU
  streams (heartbeats, wrapped reports);
* connect.py: opening a link (our TCP connection, a ``ContextLink`` with the line's
  settings);
* worker.py: :class:`LineWorker` (one thread per line, a queue for other threads, the
  line engine's loop; requests.py: its request helpers; poller_api.py: the
  :class:`Poller` it runs; jobs.py: queued jobs, the fair share of polling, the backoff
  from silent slaves); registry.py: :class:`LineRegistry` (one worker per endpoint,
  shared by its users);
* dtu_registry.py, dtu_listener.py, dtu_slot.py, registration.py, admission.py and
  log_limit.py: listen mode, DTUs that dial in and register.
* forward.py: gateway forward mode, a request PDU sent as a job on the line's queue
  (:meth:`LineWorker.forward`).

The counters a worker keeps are :class:`edgemodbus.stats.LineStats`.
"""

from __future__ import annotations

from .dtu_registry import DtuRegistry
from .dtu_registry import registry as dtu_registry
from .dtu_slot import DtuSlot
from .endpoint import DtuEndpoint, Endpoint, LineTiming, SerialPort, TcpEndpoint, endpoint_for
from .link import Link
from .poller_api import Poller
from .registration import DtuAccess, PortSettings
from .registry import LineRegistry
from .registry import registry as line_registry
from .worker import LineWorker

__all__ = [
    "DtuAccess",
    "DtuEndpoint",
    "DtuRegistry",
    "DtuSlot",
    "Endpoint",
    "LineRegistry",
    "LineTiming",
    "LineWorker",
    "Link",
    "Poller",
    "PortSettings",
    "SerialPort",
    "TcpEndpoint",
    "dtu_registry",
    "endpoint_for",
    "line_registry",
]
