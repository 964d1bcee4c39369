"""Cases of `make soak-gateway` for the northbound (issue #25's rows "store-and-forward",
"Sparkplug commands", "MQTT commands"; the DCMD storm of "line scheduling" uses the
broker set-up here): a mosquitto of the case's own (tests/mosquitto.py), the gateway
publishing to it, and an independent paho client as the attacker or the subscriber that
counts what arrived."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from tests import sparkplug_wire as wire
from tests.mosquitto import Mosquitto, MqttProbe
from tools.soak_gw_base import (
    OWN,
    Attack,
    Case,
    Prep,
    Run,
    own_device,
    repeat,
    served_and_scraped,
)

GROUP, NODE = "G", "n1"
SP = f"spBv1.0/{GROUP}"
PREFIX = "edgemodbus"
MAX_REPLY = 64 * 1024
SPOOL_DISK = "2m"
SPOOL_FREE = 48 * 1024  # what the filler leaves of the small disk once the gateway runs
CHANGE_S = 0.3  # the spool case's slave changes its registers this often


def broker(prep: Prep, **extra: Any) -> Mosquitto:
    folder = prep.workdir / f"{prep.conf.name}-broker"
    started = prep.stack.enter_context(Mosquitto(folder, **extra))
    prep.extras["broker"] = started
    return started


def sparkplug_broker(prep: Prep, own: bool = True) -> None:
    """A broker, the gateway a Sparkplug edge node on it (group G, node n1), device
    dev4 (slave 4) on the bystanders' line for the commands (``own``), and a probe of
    births."""
    port = broker(prep).port
    if own:
        own_device(prep)
    prep.gateway["mqtt"] = {"port": port, "mode": "sparkplug", "sparkplug": {
        "groupId": GROUP, "edgeNodeId": NODE, "bdSeqFile": "bdseq"}}
    prep.extras["probe"] = prep.stack.enter_context(
        MqttProbe(port, [f"{SP}/NBIRTH/#", f"{SP}/DBIRTH/#"]))


def per_item_broker(prep: Prep) -> None:
    port = broker(prep).port
    own_device(prep)
    prep.gateway["mqtt"] = {"port": port, "mode": "per-item"}
    prep.extras["probe"] = prep.stack.enter_context(
        MqttProbe(port, [f"{PREFIX}/dev4/$reply"]))


def publisher(run: Run) -> Any:
    """A paho client of the attacker's (its own network thread)."""
    import paho.mqtt.client as paho

    client = paho.Client(callback_api_version=paho.CallbackAPIVersion.VERSION2,
                         client_id=f"soak-attacker-{os.getpid()}")
    client.max_queued_messages_set(1000)
    client.connect("127.0.0.1", run.extras["broker"].port)
    client.loop_start()
    return client


@contextlib.contextmanager
def publishing(run: Run, topic: str, payloads: Iterator[bytes], pause: float = 0.0,
               once: bool = False) -> Iterator[None]:
    """Publish ``payloads`` (QoS 1) to ``topic``, one after another (``pause`` between),
    while the window lasts; ``once``: the first only.  Their count is the case's events."""
    client = publisher(run)
    sent = [0]

    def send() -> None:
        payload = None if once and sent[0] else next(payloads, None)
        if payload is None:  # all sent: the window goes on
            time.sleep(0.05)
            return
        info = client.publish(topic, payload, qos=1)
        info.wait_for_publish(10)
        sent[0] += 1

    try:
        with repeat(run, send, "soak-publisher", pause):
            yield
    finally:
        client.loop_stop()
        client.disconnect()
        run.notes["events"] = sent[0]
        probe = run.extras.get("probe")
        if probe is not None and any("BIRTH" in t for t in probe.topics):
            run.notes["x_births"] = {
                kind: len([m for m in probe.messages() if f"/{kind}/" in m.topic])
                for kind in ("NBIRTH", "DBIRTH")}


def forever(payload: bytes) -> Iterator[bytes]:
    while True:
        yield payload


def dcmd_storm(device: str) -> Attack:
    """DCMD writes of ``device``'s t0 back-to-back (each waits for the broker's PUBACK)."""
    def values() -> Iterator[bytes]:
        n = 0
        while True:
            n = (n + 1) & 0xFFFF
            yield wire.encode([wire.encode_metric(name="t0", datatype="UInt16", value=n)])
    return lambda run, seconds: publishing(run, f"{SP}/DCMD/{NODE}/{device}", values())


def ncmd_metrics(run: Run, seconds: float) -> Any:
    metrics = [wire.encode_metric(name=f"Node Control/x{i}", datatype="Boolean",
                                  value=True) for i in range(200_000)]
    return publishing(run, f"{SP}/NCMD/{NODE}", forever(wire.encode(metrics)), once=True)


def dcmd_name(run: Run, seconds: float) -> Any:
    metric = wire.encode_metric(name="n" * 5_000_000, datatype="UInt16", value=1)
    return publishing(run, f"{SP}/DCMD/{NODE}/dev4", forever(wire.encode([metric])),
                      once=True)


def rebirths(run: Run, seconds: float) -> Any:
    payload = wire.encode([wire.encode_metric(name="Node Control/Rebirth",
                                              datatype="Boolean", value=True)])
    run.notes.update(x_rebirthsAsked=1000, x_windowS=seconds)
    return publishing(run, f"{SP}/NCMD/{NODE}", iter([payload] * 1000))


def few_births(run: Run) -> list[str]:
    """1,000 rebirth requests fold into one per rebirthInterval (5 s)."""
    births = run.notes.get("x_births", {})
    allowed = 2 + int(run.notes.get("x_windowS", 60) / 5.0) + 1
    if births.get("NBIRTH", 0) > allowed:
        return [f"{births['NBIRTH']} NBIRTH for 1,000 rebirth requests (at most {allowed})"]
    return []


def nested_command(run: Run, seconds: float) -> Any:
    body = b'{"value": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    return publishing(run, f"{PREFIX}/dev4/set/t0", forever(body), pause=0.5)


def huge_id(run: Run, seconds: float) -> Any:
    body = b'{"value": 1, "id": "' + b"i" * 5_000_000 + b'"}'
    return publishing(run, f"{PREFIX}/dev4/set/t0", forever(body), pause=0.5)


def no_echo(run: Run) -> list[str]:
    probe: MqttProbe = run.extras["probe"]
    sizes = [len(m.payload) for m in probe.messages()]
    run.notes["x_replies"] = len(sizes)
    run.notes["x_longestReply"] = max(sizes, default=0)
    if sizes and max(sizes) > MAX_REPLY:
        return [f"a reply of {max(sizes)} bytes (cap {MAX_REPLY})"]
    return []


def nothing(run: Run, seconds: float) -> Any:
    return contextlib.nullcontext()


# -- the spool ---------------------------------------------------------------------------


def spool_prep(prep: Prep, spool: Path, **spool_keys: Any) -> None:
    port = broker(prep, extra_config=[
        "persistence true", f"persistence_location {prep.workdir}/{prep.conf.name}-broker/",
        "autosave_interval 1"]).port
    prep.gateway["mqtt"] = {
        "port": port, "mode": "batch", "qos": 1, "reconnectMin": 100, "reconnectMax": 400,
        "storeAndForward": {"path": str(spool), **spool_keys}}
    prep.extras["spool"] = spool
    # the subscriber keeps its session at the broker (persisted across the restart): it
    # misses nothing the gateway got acknowledged
    prep.extras["probe"] = prep.stack.enter_context(MqttProbe(
        port, [f"{PREFIX}/+/$batch"], client_id="soak-spool-probe", clean_session=False))


def garbage_prep(prep: Prep) -> None:
    spool_prep(prep, prep.conf / "spool.db")
    (prep.conf / "spool.db").write_bytes(b"\x13garbage from a bad shutdown" * 500)


def moved_aside(run: Run) -> list[str]:
    bad = []
    aside = [p for p in run.conf.iterdir() if p.name.startswith("spool.db.corrupt-")]
    if len(aside) != 1 or not aside[0].read_bytes().startswith(b"\x13garbage"):
        bad.append(f"the damaged spool not moved aside: {[p.name for p in aside]}")
    if not run.gw.lines(r"moved aside"):
        bad.append("no line says the spool was moved aside")
    probe: MqttProbe = run.extras["probe"]
    if not probe.on(f"{PREFIX}/dev1/$batch"):
        bad.append("nothing published")
    return bad


@contextlib.contextmanager
def mounted_tmpfs(folder: Path, size: str) -> Iterator[Path | None]:
    """A tmpfs of ``size`` at ``folder`` (None where mounting is not permitted)."""
    folder.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs",
                           str(folder)], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        print(f"cannot mount a tmpfs ({done.stderr.strip()}): the spool case runs on "
              "the work folder's disk, bounded by maxBytes alone", file=sys.stderr)
        yield None
        return
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


def disk_full_prep(prep: Prep) -> None:
    disk = prep.stack.enter_context(mounted_tmpfs(prep.conf / "disk", SPOOL_DISK))
    prep.extras["disk"] = disk
    spool_prep(prep, (disk or prep.conf) / "spool.db", maxBytes=1024 * 1024)
    own_device(prep, tags=60, read_cycle=100)


def file_bytes(spool: Path) -> int:
    return sum(p.stat().st_size for p in spool.parent.glob(spool.name + "*")
               if p.name in (spool.name, spool.name + "-wal", spool.name + "-shm"))


@contextlib.contextmanager
def outage_on_full_disk(run: Run, seconds: float) -> Iterator[None]:
    """The disk filled to its last SPOOL_FREE bytes, the broker stopped for the window
    while dev4's 60 registers change every CHANGE_S; then the broker is back."""
    disk: Path | None = run.extras["disk"]
    spool: Path = run.extras["spool"]
    if disk is not None:
        stat = os.statvfs(disk)
        with open(disk / "filler", "wb") as f:
            f.write(b"\0" * max(0, stat.f_bavail * stat.f_frsize - SPOOL_FREE))
    written: list[int] = run.extras.setdefault("written", [])
    largest = [file_bytes(spool)]
    value = [0]

    def change() -> None:
        value[0] += 1
        run.peer.set_registers(OWN, "hr", 0, [value[0]] * 60)
        written.append(value[0])
        largest[0] = max(largest[0], file_bytes(spool))

    mosquitto: Mosquitto = run.extras["broker"]
    with repeat(run, change, "soak-changer", CHANGE_S):
        mosquitto.stop()
        try:
            yield
        finally:
            mosquitto.restart()
            run.notes["x_outageS"] = round(seconds, 1)
    run.notes.update(x_largestFile=largest[0], x_valuesWritten=len(written),
                     x_diskFree=SPOOL_FREE if disk is not None else None,
                     x_errorLines=len(run.gw.lines(r" ERROR ")))


def seen_values(run: Run) -> set[int]:
    probe: MqttProbe = run.extras["probe"]
    seen = set()
    for message in probe.on(f"{PREFIX}/dev4/$batch"):
        with contextlib.suppress(ValueError, KeyError, TypeError):
            seen.add(int(message.json()["values"]["t0"]))
    return seen


def everything_arrived(run: Run) -> bool:
    written = run.extras.get("written", [])
    return bool(served_and_scraped(run) and written and written[-1] in seen_values(run))


def nothing_lost(run: Run) -> list[str]:
    lost = sorted(set(run.extras.get("written", [])) - seen_values(run))
    run.notes["x_valuesLostToSubscriber"] = len(lost)
    if lost:
        return [f"{len(lost)} values never reached the subscriber (first {lost[:5]})"]
    return []


def north_cases() -> list[Case]:
    return [
        Case("spool-disk-full", "store-and-forward: the spool's disk fills during a "
             "broker outage (2 MB tmpfs)", outage_on_full_disk, everything_arrived,
             prep=disk_full_prep, verdict=nothing_lost),
        Case("spool-garbage", "store-and-forward: the spool file overwritten with garbage "
             "between runs", nothing, served_and_scraped, prep=garbage_prep,
             verdict=moved_aside),
        Case("sparkplug-ncmd-200k", "Sparkplug commands: one NCMD with 200,000 unsupported "
             "metrics", ncmd_metrics, served_and_scraped, prep=sparkplug_broker),
        Case("sparkplug-dcmd-5mb-name", "Sparkplug commands: a DCMD with a 5 MB metric name",
             dcmd_name, served_and_scraped, prep=sparkplug_broker),
        Case("sparkplug-rebirths", "Sparkplug commands: 1,000 Rebirth NCMDs", rebirths,
             served_and_scraped, prep=sparkplug_broker, verdict=few_births),
        Case("mqtt-nested-command", "MQTT commands (per-item): nested JSON, every 0.5 s",
             nested_command, served_and_scraped, prep=per_item_broker, verdict=no_echo,
             log_per_event=1),
        Case("mqtt-huge-id", 'MQTT commands (per-item): a 5 MB "id", every 0.5 s',
             huge_id, served_and_scraped, prep=per_item_broker, verdict=no_echo,
             log_per_event=1),
    ]
