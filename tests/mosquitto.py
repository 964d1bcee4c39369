"""A real MQTT broker for tests: Debian's ``mosquitto`` on a free loopback port.

`Mosquitto(tmp_dir)` writes a config file into ``tmp_dir`` (listener on 127.0.0.1 only,
anonymous access, no persistence, log to stderr), starts ``/usr/sbin/mosquitto -c`` and
waits until the port accepts connections.  `stop()` (SIGTERM, then SIGKILL) and `kill()`
(SIGKILL) always reap the process; `restart()` comes back on the SAME port, which is what
a "broker restart mid-run" test needs.  Use it as a context manager.

`MqttProbe` is a real subscriber (paho-mqtt with its own network thread) that records
every message it receives, for assertions.  paho is imported only when a probe is made;
pytest never, so benchmarks can use this module too.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tests.peers import free_port

MOSQUITTO_CANDIDATES = ("/usr/sbin/mosquitto", "/usr/bin/mosquitto")


class BrokerError(RuntimeError):
    """The broker could not be found, did not start, or died."""


def mosquitto_binary() -> str:
    """Path of the mosquitto executable; BrokerError with an install hint if missing."""
    for path in MOSQUITTO_CANDIDATES:
        if os.access(path, os.X_OK):
            return path
    found = shutil.which("mosquitto")
    if found:
        return found
    raise BrokerError(
        "mosquitto is not installed: `apt-get install mosquitto` (make test does it)"
    )


class Mosquitto:
    """One mosquitto process listening on 127.0.0.1:`port` (chosen free at first start)."""

    def __init__(self, tmp_dir: str | os.PathLike[str], *, start_timeout: float = 10.0,
                 extra_config: Iterable[str] = ()) -> None:
        self.dir = Path(tmp_dir)
        self.extra_config = list(extra_config)  # more mosquitto.conf lines
        self.dir.mkdir(parents=True, exist_ok=True)
        self.start_timeout = start_timeout
        self.host = "127.0.0.1"
        self._port: int | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._log: Path | None = None
        self.starts = 0

    # -- lifecycle ---------------------------------------------------------------------
    def __enter__(self) -> Mosquitto:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> Mosquitto:
        """Start the broker and wait until it accepts TCP connections.

        The first start picks a free port (racy by nature: retried on a bind failure);
        later starts reuse it."""
        if self.running:
            raise BrokerError("mosquitto already running")
        binary = mosquitto_binary()
        attempts = 3 if self._port is None else 1
        for attempt in range(attempts):
            port = self._port if self._port is not None else free_port(self.host)
            conf = self.dir / "mosquitto.conf"
            lines = [
                f"listener {port} {self.host}",
                "allow_anonymous true",
                "persistence false",
                "log_dest stderr",
                "log_type error",
                "log_type warning",
                "log_type notice",
                "log_type information",
                "connection_messages true",
                *self.extra_config,
            ]
            if os.geteuid() == 0:
                lines.append("user root")  # else it drops to user "mosquitto"
            conf.write_text("\n".join(lines) + "\n")
            self._log = self.dir / "mosquitto.log"
            with open(self._log, "ab") as log:  # O_APPEND: we may read while it writes
                self._proc = subprocess.Popen(
                    [binary, "-c", str(conf)],
                    stdin=subprocess.DEVNULL,
                    stdout=log,
                    stderr=log,
                    start_new_session=True,
                )
            if self._wait_ready(port):
                self._port = port
                self.starts += 1
                return self
            self._reap(kill=True)
            if attempt + 1 == attempts:
                break
        raise BrokerError(f"mosquitto did not start on 127.0.0.1; log:\n{self.log_text}")

    def _wait_ready(self, port: int) -> bool:
        deadline = time.monotonic() + self.start_timeout
        while time.monotonic() < deadline:
            proc = self._proc
            if proc is None or proc.poll() is not None:
                return False
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
                sock.settimeout(0.5)
                if sock.connect_ex((self.host, port)) == 0:
                    return True
            time.sleep(0.05)  # poll: until it listens (deadline above)
        return False

    def stop(self, timeout: float = 5.0) -> None:
        """SIGTERM (clean shutdown), SIGKILL after ``timeout``; always reaps."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self._reap(kill=True)

    def kill(self) -> None:
        """SIGKILL the broker (a crash) and reap it."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        self._reap(kill=True)

    def restart(self) -> Mosquitto:
        """Stop (if running) and start again on the same port; retained messages are lost
        (no persistence), so whatever a client shows after this it republished itself."""
        if self.running:
            self.stop()
        deadline = time.monotonic() + self.start_timeout
        while True:  # the old socket may linger a moment; mosquitto sets SO_REUSEADDR
            try:
                return self.start()
            except BrokerError:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(0.2)  # poll: until the port is free (deadline above)

    def _reap(self, kill: bool) -> None:
        proc = self._proc
        if proc is not None:
            if proc.poll() is None and kill:
                proc.kill()
            proc.wait()
        self._proc = None

    # -- facts -------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    @property
    def port(self) -> int:
        if self._port is None:
            raise BrokerError("mosquitto was never started")
        return self._port

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    @property
    def log_text(self) -> str:
        """The broker's log (every run of this instance)."""
        if self._log is None:
            return ""
        try:
            return self._log.read_text(errors="replace")
        except OSError:
            return ""

    def __repr__(self) -> str:
        state = "running" if self.running else "stopped"
        return f"<Mosquitto 127.0.0.1:{self._port} {state}>"


@dataclass(frozen=True)
class Received:
    """One message as a subscriber saw it."""

    topic: str
    payload: bytes
    retain: bool
    qos: int
    at: float  # time.monotonic() on arrival
    dup: bool = False  # the broker sent it again to us (our session's redelivery)

    def json(self) -> Any:
        return json.loads(self.payload)


class MqttProbe:
    """A subscriber on 127.0.0.1:`port` that records what arrives (thread-safe)."""

    def __init__(self, port: int, topics: Iterable[str] = ("#",), *,
                 client_id: str | None = None, host: str = "127.0.0.1",
                 clean_session: bool = True) -> None:
        import paho.mqtt.client as paho

        self._paho = paho
        self.host, self.port = host, port
        self.topics = list(topics)
        self._cond = threading.Condition()
        self.received: list[Received] = []
        self._subscribed = threading.Event()
        self._client = paho.Client(
            callback_api_version=paho.CallbackAPIVersion.VERSION2,
            client_id=client_id or f"probe-{os.getpid()}-{id(self):x}",
            clean_session=clean_session,  # False: the broker keeps what we miss
        )
        self._client.on_connect = self._on_connect
        self._client.on_message = self._on_message
        self._client.on_subscribe = lambda *_: self._subscribed.set()
        self._client.reconnect_delay_set(0.1, 0.5)

    def __enter__(self) -> MqttProbe:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self, timeout: float = 10.0) -> MqttProbe:
        self._client.connect(self.host, self.port, keepalive=30)
        self._client.loop_start()
        if not self._subscribed.wait(timeout):
            self.stop()
            raise BrokerError(f"probe could not subscribe on 127.0.0.1:{self.port}")
        return self

    def stop(self) -> None:
        self._client.disconnect()
        self._client.loop_stop()
        # paho closes its wake-up socket pair only when the client is garbage collected;
        # a failed test's traceback keeps it alive, so close it now
        reset = getattr(self._client, "_reset_sockets", None)
        if reset is not None:
            reset()

    def _on_connect(self, client: Any, _u: Any, _f: Any, reason: Any, _p: Any) -> None:
        if not reason.is_failure:
            for topic in self.topics:
                client.subscribe(topic, qos=1)

    def _on_message(self, _c: Any, _u: Any, msg: Any) -> None:
        with self._cond:
            self.received.append(Received(msg.topic, bytes(msg.payload), bool(msg.retain),
                                          int(msg.qos), time.monotonic(), bool(msg.dup)))
            self._cond.notify_all()

    def messages(self) -> list[Received]:
        """What arrived so far, in arrival order (a copy)."""
        with self._cond:
            return list(self.received)

    def publish(self, topic: str, payload: bytes | str, qos: int = 1) -> None:
        info = self._client.publish(topic, payload, qos=qos)
        info.wait_for_publish(5.0)

    def on(self, topic: str) -> list[Received]:
        """Messages received so far on one topic."""
        with self._cond:
            return [m for m in self.received if m.topic == topic]

    def wait_for(self, topic: str, match: Callable[[Received], bool] = lambda m: True,
                 timeout: float = 30.0, after: int = 0) -> Received:
        """The first message on ``topic`` (from index ``after`` of all received) that
        ``match`` accepts; AssertionError listing what came instead on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for msg in self.received[after:]:
                    if msg.topic == topic and match(msg):
                        return msg
                left = deadline - time.monotonic()
                if left <= 0:
                    seen = [m.payload[:120] for m in self.received if m.topic == topic]
                    raise AssertionError(f"no matching message on {topic!r} within "
                                         f"{timeout}s; got {seen[-5:]}")
                self._cond.wait(left)

    def mark(self) -> int:
        """Index to pass as ``after=``: only messages from now on."""
        with self._cond:
            return len(self.received)
