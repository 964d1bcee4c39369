"""The ``mqtt.sparkplug`` section of the gateway file (used when ``mqtt.mode`` is
``"sparkplug"``): the Sparkplug group, edge node and primary host ids, and where bdSeq
is kept between runs.

The broker, TLS, credentials, keepalive and reconnect backoff are the ``mqtt`` section's
own fields (northbound/mqtt/settings.py); the topic templates, QoS and retain flags of
the per-item mode do not apply: Sparkplug fixes its topics and QoS."""

from __future__ import annotations

import os
from pathlib import Path
from typing import ClassVar

from pydantic import field_validator

from ...config import Model, Problem
from ...config.limits import MAX_NAME

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


class SparkplugSettings(Model):
    """``mqtt.sparkplug``: who this edge node is in Sparkplug B (v3.0)."""

    _where: ClassVar[str] = "mqtt.sparkplug"
    _max_lengths: ClassVar[dict[str, int]] = {
        "groupId": MAX_NAME, "edgeNodeId": MAX_NAME, "primaryHostId": MAX_NAME}

    group_id: str
    edge_node_id: str | None = None  # default: the gateway id
    primary_host_id: str | None = None  # wait for spBv1.0/STATE/<id> online before births
    bd_seq_file: str | None = None  # keeps bdSeq across restarts (else it starts at 0)

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

    def resolved(self, base: str | os.PathLike[str]) -> SparkplugSettings:
        """A copy whose relative ``bdSeqFile`` is taken from folder ``base``."""
        path = self.bd_seq_file
        if path is None or os.path.isabs(path):
            return self
        return self.model_copy(update={"bd_seq_file": str(Path(base, path))})

    def problems(self, where: str = "mqtt.sparkplug") -> list[Problem]:
        """What keeps ``bdSeqFile`` from being kept: its folder missing or not writable,
        or the path a folder; [] when it can be written."""
        path = self.bd_seq_file
        if path is None:
            return []
        field = f"{where}.bdSeqFile"
        if not path:
            return [Problem(field, path, "must not be empty (leave it out to keep bdSeq "
                                         "in memory only)")]
        folder = Path(path).absolute().parent
        if os.path.exists(path) and not os.path.isdir(path) and not os.path.isfile(path):
            return [Problem(field, path, "is not a regular file (a FIFO, socket or device): "
                                         "give a file path")]
        if os.path.isdir(path):
            return [Problem(field, path, "is a directory; give a file path in it, e.g. "
                                         f"{Path(path, 'bdseq')}")]
        if not folder.is_dir():
            return [Problem(field, path, f"its directory {folder} does not exist")]
        if not os.access(folder, os.W_OK | os.X_OK):
            return [Problem(field, path, f"its directory {folder} is not writable by this "
                                         f"process (uid {os.geteuid()})")]
        return []
