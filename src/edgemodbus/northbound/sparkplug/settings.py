"""The ``mqtt.sparkplug`` section of the gateway file (used when ``mqtt.mode`` is
``"sparkplug"``): the Sparkplug group, edge node and primary host ids, where bdSeq is
kept between runs and how often a rebirth may be asked for.

The broker, TLS, credentials, keepalive and reconnect backoff are the ``mqtt`` section's
own fields (northbound/mqtt/settings.py); the topic templates, QoS and retain flags of
the per-item mode do not apply: Sparkplug fixes its topics and QoS."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Annotated, ClassVar

from pydantic import field_validator

from ...config import Model, Problem, Range
from ...config.files import path_kind
from ...config.limits import MAX_NAME
from .bdseq import file_problem

log = logging.getLogger("edgemodbus.sparkplug")

DEFAULT_BD_SEQ_FILE = "sparkplug.bdseq"
"""The gateway's bdSeq file when ``bdSeqFile`` is not given: in the first folder of
``$STATE_DIRECTORY`` (systemd's ``StateDirectory=``), else in the gateway file's folder."""

# Sparkplug 3.0, 4.1.1: group_id, edge_node_id and device_id are one topic level each
# and must not contain the MQTT wildcards or the level separator
_FORBIDDEN = ("+", "#", "/", "\0")


def check_id(kind: str, value: str) -> str:
    """A Sparkplug id (group, edge node, device, host): one topic level."""
    if not value:
        raise ValueError(f"{kind} must not be empty")
    bad = [ch for ch in _FORBIDDEN if ch in value]
    if bad:
        raise ValueError(f"{kind} {value!r} cannot be a Sparkplug topic level: it contains "
                         f"{' '.join(repr(c) for c in bad)}; use letters, digits, '-', '_' "
                         "or '.'")
    return value


INSTANCE_FIELD = "{instance}"


def node_id_for(edge_node_id: str | None, gateway_id: str, instance: str | None,
                shared: bool = False) -> str:
    """The edge node id: ``edgeNodeId`` (default the gateway id).  In a dial-in fleet
    (``instance`` given, docs/deploy.md) each instance is its own edge node: ``{instance}``
    in ``edgeNodeId`` is replaced by the instance id, and an ``edgeNodeId`` without it
    gets ``-<instance>`` appended, so two instances never share a node id (Sparkplug 3.0,
    4.1.1: an edge node id is unique in its group).  ``shared`` (``sharedByPair``): the
    two instances of a redundant pair are one edge node, the id as given, and only the
    leader is connected as it (gateway/pair.py)."""
    base = edge_node_id or gateway_id
    if shared and INSTANCE_FIELD in base:
        raise ValueError(f"mqtt.sparkplug.edgeNodeId {base!r} names {INSTANCE_FIELD}, but "
                         "sharedByPair makes both instances of the pair one edge node: "
                         "remove it")
    if instance is None or shared:
        if INSTANCE_FIELD in base:
            raise ValueError(f"mqtt.sparkplug.edgeNodeId {base!r} names {INSTANCE_FIELD}, but "
                             "this gateway is not in a fleet (no enabled fleet section): "
                             "remove it, or add the fleet section")
        return check_id("edgeNodeId", base)
    node = (base.replace(INSTANCE_FIELD, instance) if INSTANCE_FIELD in base
            else f"{base}-{instance}")
    return check_id("edgeNodeId", node)


class SparkplugSettings(Model):
    """``mqtt.sparkplug``: who this edge node is in Sparkplug B (v3.0)."""

    _where: ClassVar[str] = "mqtt.sparkplug"
    _max_lengths: ClassVar[dict[str, int]] = {
        "groupId": MAX_NAME, "edgeNodeId": MAX_NAME, "primaryHostId": MAX_NAME}

    group_id: str
    edge_node_id: str | None = None  # default: the gateway id; in a fleet see node_id_for
    primary_host_id: str | None = None  # wait for spBv1.0/STATE/<id> online before births
    bd_seq_file: str | None = None  # keeps bdSeq across restarts (the gateway's default:
    # DEFAULT_BD_SEQ_FILE; a library caller without one starts at 0 in each process)
    rebirth_interval: Annotated[int, Range(0, 3_600_000)] = 5000  # ms between rebirths
    shared_by_pair: bool = False  # a redundant pair's two instances are one edge node:
    # its bdSeq kept in the pair's Redis (bdseq.py RedisBdSeqStore), the leader connected

    @field_validator("group_id")
    @classmethod
    def _group(cls, value: str) -> str:
        return check_id("groupId", value)

    @field_validator("edge_node_id")
    @classmethod
    def _node(cls, value: str | None) -> str | None:
        return None if value is None else check_id("edgeNodeId", value)

    @field_validator("primary_host_id")
    @classmethod
    def _host(cls, value: str | None) -> str | None:
        return None if value is None else check_id("primaryHostId", value)

    def resolved(self, base: str | os.PathLike[str],
                 state_directory: str | None = None) -> SparkplugSettings:
        """A copy whose relative ``bdSeqFile`` is taken from folder ``base``; without one,
        :data:`DEFAULT_BD_SEQ_FILE` in ``state_directory`` (the first of a colon-separated
        list, as systemd sets ``$STATE_DIRECTORY``) or else in ``base``, when that folder
        is writable (if not, a warning says so and bdSeq is kept in memory only)."""
        path = self.bd_seq_file
        if path is None:
            folder = Path(state_directory.split(":")[0] if state_directory else base)
            if not (folder.is_dir() and os.access(folder, os.W_OK | os.X_OK)):
                log.warning("mqtt.sparkplug.bdSeqFile: not given and %s is not a writable "
                            "folder: bdSeq starts at 0 in each run (set bdSeqFile, or "
                            "$STATE_DIRECTORY)", folder)
                return self
            return self.model_copy(update={"bd_seq_file": str(folder / DEFAULT_BD_SEQ_FILE)})
        if os.path.isabs(path):
            return self
        return self.model_copy(update={"bd_seq_file": str(Path(base, path))})

    def problems(self, where: str = "mqtt.sparkplug") -> list[Problem]:
        """What keeps ``bdSeqFile`` from being kept: its folder missing or not writable,
        the path a folder, or an existing file that is not ours (bdseq.py); [] when it
        can be written."""
        path = self.bd_seq_file
        if path is None:
            return []
        field = f"{where}.bdSeqFile"
        if not path:
            return [Problem(field, path, "must not be empty (leave it out to keep bdSeq "
                                         "in memory only)")]
        folder = Path(path).absolute().parent
        kind = path_kind(path)
        if kind == "a directory":
            return [Problem(field, path, "is a directory; give a file path in it, e.g. "
                                         f"{Path(path, 'bdseq')}")]
        if kind is not None:
            return [Problem(field, path, f"is {kind}, not a regular file: give a file path")]
        if not folder.is_dir():
            return [Problem(field, path, f"its directory {folder} does not exist")]
        if not os.access(folder, os.W_OK | os.X_OK):
            return [Problem(field, path, f"its directory {folder} is not writable by this "
                                         f"process (uid {os.geteuid()})")]
        problem = file_problem(path)
        return [] if problem is None else [Problem(field, path, problem)]
