"""A simulated MQTT DTU for tests, in its own process: a paho client that bridges a
DTU's topics to a Modbus slave's RTU-over-TCP socket (a pymodbus slave: its RS-485
side), as a real DTU bridges its serial port.

Run as ``python tests/mqtt_dtu_peer.py CONFIG_JSON``; it prints ``READY`` once it is
subscribed and has published its retained ``online`` status (its will: ``offline``,
retained), then bridges until its stdin closes.  ``delay``: seconds it waits before
publishing what the slave answered (a slow DTU).  SIGKILL is a DTU that drops off: the
broker publishes its will.  :class:`MqttDtu` drives it from the test process.
"""

from __future__ import annotations

import json
import os
import selectors
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

SCRIPT = Path(__file__).resolve()


def main() -> int:
    import paho.mqtt.client as paho
    from paho.mqtt.enums import CallbackAPIVersion

    cfg = json.loads(sys.argv[1])
    dtu = cfg["dtu"]
    up, down, status = f"dtu/{dtu}/up", f"dtu/{dtu}/down", f"dtu/{dtu}/status"
    serial = socket.create_connection(("127.0.0.1", cfg["slave_port"]), timeout=5)
    serial.settimeout(None)
    subscribed = threading.Event()
    client = paho.Client(callback_api_version=CallbackAPIVersion.VERSION2,
                         client_id=f"sim-dtu-{dtu}-{os.getpid()}")
    client.will_set(status, b"offline", qos=1, retain=True)
    lock = threading.Lock()

    def on_connect(c: Any, _u: Any, _f: Any, _r: Any, _p: Any) -> None:
        c.subscribe(down, qos=0)

    def on_subscribe(c: Any, _u: Any, _m: Any, _r: Any, _p: Any) -> None:
        c.publish(status, b"online", qos=1, retain=True).wait_for_publish(5)
        subscribed.set()

    def on_message(_c: Any, _u: Any, msg: Any) -> None:
        with lock:
            serial.sendall(msg.payload)  # to RS-485

    client.on_connect = on_connect
    client.on_subscribe = on_subscribe
    client.on_message = on_message
    client.connect("127.0.0.1", cfg["broker_port"], keepalive=10)
    client.loop_start()
    if not subscribed.wait(10):
        return 1

    def from_serial() -> None:
        sel = selectors.DefaultSelector()
        sel.register(serial, selectors.EVENT_READ)
        while True:
            sel.select()
            data = serial.recv(4096)
            if not data:
                return
            if cfg.get("delay"):
                time.sleep(cfg["delay"])  # pacing: the peer's configured delay
            client.publish(up, data, qos=0)

    threading.Thread(target=from_serial, daemon=True).start()
    print("READY", flush=True)
    sys.stdin.read()  # until the test closes our stdin
    client.publish(status, b"offline", qos=1, retain=True).wait_for_publish(5)
    client.disconnect()
    client.loop_stop()
    serial.close()
    return 0


class MqttDtu:
    """The simulated DTU ``dtu`` in a child process: bridges ``dtu/<dtu>/up`` and
    ``/down`` on the broker at ``broker_port`` to the RTU-over-TCP slave at
    ``slave_port``; ``delay`` seconds before each uplink message."""

    def __init__(self, dtu: str, broker_port: int, slave_port: int, delay: float = 0.0) -> None:
        self.config = {"dtu": dtu, "broker_port": broker_port, "slave_port": slave_port,
                       "delay": delay}
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> MqttDtu:
        self.proc = subprocess.Popen(
            [sys.executable, str(SCRIPT), json.dumps(self.config)], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, text=True)
        out: IO[str] | None = self.proc.stdout
        assert out is not None
        sel = selectors.DefaultSelector()
        sel.register(out, selectors.EVENT_READ)
        ready = sel.select(20)
        sel.close()
        line = out.readline() if ready else ""
        if line.strip() != "READY":
            self.kill()
            raise RuntimeError(f"simulated MQTT DTU did not start: {line!r}")
        return self

    def kill(self) -> None:
        """SIGKILL: the DTU drops off the broker without a goodbye (its will)."""
        proc = self.proc
        if proc is not None:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
            self._close(proc)
        self.proc = None

    def stop(self) -> None:
        proc = self.proc
        if proc is not None and proc.poll() is None and proc.stdin is not None:
            proc.stdin.close()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if proc is not None:
            self._close(proc)
        self.proc = None

    @staticmethod
    def _close(proc: subprocess.Popen[str]) -> None:
        for stream in (proc.stdin, proc.stdout):
            if stream is not None and not stream.closed:
                stream.close()

    def __enter__(self) -> MqttDtu:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


if __name__ == "__main__":
    sys.exit(main())
