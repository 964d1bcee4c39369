"""Store-and-forward: MQTT messages kept on disk until the broker acknowledged them.

store.py holds :class:`Spool` (one SQLite file, stdlib ``sqlite3``, WAL mode), rows.py
what it keeps, file.py its file on disk, and pacer.py :class:`ReplayPacer` (the token
bucket that paces the replay).  Configured by ``mqtt.storeAndForward`` (settings.py:
:class:`StoreAndForwardSettings`).

When a message goes to the spool
  * the broker is unreachable (not connected): every data message the sender would have
    published (item updates, batched payloads) is appended, unclaimed, instead of
    waiting in (and being dropped from) the in-memory queue;
  * connected, QoS 1: the message is appended *claimed* (``append(msgs, claimed=True)``,
    one transaction per turn of the MQTT thread) and then handed to paho; it stays in
    the file until its PUBACK.  So a ``kill -9`` loses nothing that SQLite acknowledged:
    what had been handed to paho without a PUBACK is still in the file;
  * connected, QoS 0: not spooled (QoS 0 promises nothing once it is on the wire).

An id's life (ids grow and are never reused)::

    append()  -> pending      stored, not in flight
    next_batch(n) / append(claimed=True)
              -> in flight    claimed: handed to paho under a message id (mid); the
                              sender keeps mid -> spool id
    ack(ids)  -> deleted      PUBACK (QoS 1) or written out (QoS 0): paho's on_publish
    release(ids) / release_all()
              -> pending      paho refused it, or the client that held it is gone:
                              next_batch returns it again, oldest first
    maxBytes / maxAgeS        the oldest rows are deleted (in flight or not), counted
                              (droppedSize, droppedAge) and logged (at most one line a
                              minute per bound, then a summary)

In flight is kept in memory only.  At start-up every stored row is pending, including
those that were in flight when the process died: they are replayed, so a message whose
PUBACK was lost with the process is published twice, which QoS 1 (at least once)
allows; nothing else is ever published twice.  An acknowledged row is deleted in the
same transaction that counts it; a QoS 0 row replayed but lost with the connection
before paho wrote it is released and sent again.

Replay: in the order messages were appended (one global order by id, which keeps each
device's order; a device that sent more during the outage gets more of the replay, as
it did of the live traffic).  Live data is not held back by a backlog: the sender
publishes live messages first and replays with what is left of paho's window, at most
at the pacer's rate, so a device's live value may arrive before its older replayed
ones (each payload carries its own timestamp).  A sender that needs strict per-device
order can append live messages unclaimed while ``pending_count() > 0``, at the cost of
live latency; the MQTT sender does that per device (``../store_forward.py``: a device
with messages pending queues its live ones behind them, the others publish at once).
A retained message replayed after a newer live one would replace the
broker's retained value with an older one; the MQTT sender, whose live messages queue
behind their device's backlog, replays with the retain flag kept, so the last message
of a topic is its newest and the retained value ends up current.

The file (file.py): database and WAL together stay within ``maxBytes`` (the WAL
checkpointed every few pages and truncated back to its share, the database capped by
``max_page_count``; the oldest rows make room), and the database stops growing while its
disk still has room for a WAL and a checkpoint: an append beyond that raises
:class:`SpoolError` like a full disk (the sender keeps it in memory) while
acknowledgements still find room.  A file SQLite cannot read (corrupt, truncated,
overwritten) is renamed ``<path>.corrupt-<UTC time>`` (never deleted) and a new spool
started, so polling never stops for the spool; a *readable* SQLite database that is not
a spool (another program's, or a newer schema) is refused untouched: renaming it could
break its owner, and the configured path is then the mistake.  FIFOs, devices and
sockets are refused by :func:`path_problem` before anything opens them.

"Acknowledged by SQLite" means committed: ``append`` returned.  With
``synchronous: "normal"`` (the default) the commit is in the kernel's page cache, which
a process crash (``kill -9``) does not lose; only a power loss or kernel crash can lose
the last commits (the file stays consistent).  ``"full"`` adds an fsync per commit
and survives power loss too.  See :class:`Spool`.
"""

from .file import MIN_FILE_BYTES, SpoolError, SpoolUnavailable, file_bound, path_problem
from .pacer import ReplayPacer
from .rows import ROW_OVERHEAD, SYNCHRONOUS, Message, Stored, message_size
from .store import Spool

__all__ = [
    "MIN_FILE_BYTES",
    "ROW_OVERHEAD",
    "SYNCHRONOUS",
    "Message",
    "ReplayPacer",
    "Spool",
    "SpoolError",
    "SpoolUnavailable",
    "Stored",
    "file_bound",
    "message_size",
    "path_problem",
]
