"""An independent MQTT publisher for fault tests, in its own process (its CPU and GIL
are not the driver's): paho publishes one payload to one topic at a given rate.

Run as ``python tests/mqtt_flood.py CONFIG_JSON`` with ``port``, ``topic``,
``payload_hex``, ``rate`` (messages per second, 0: as fast as it can), ``seconds`` and
optionally ``retain``; it prints ``SENT <n>`` when done.  :func:`flood` runs it and
returns that count.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

SCRIPT = Path(__file__).resolve()


def main() -> int:
    import paho.mqtt.client as paho
    from paho.mqtt.enums import CallbackAPIVersion

    cfg = json.loads(sys.argv[1])
    payload = bytes.fromhex(cfg["payload_hex"])
    client = paho.Client(callback_api_version=CallbackAPIVersion.VERSION2,
                         client_id=f"flood-{time.monotonic_ns()}")
    client.max_queued_messages_set(1000)
    client.connect("127.0.0.1", cfg["port"], keepalive=30)
    client.loop_start()
    rate, seconds = float(cfg["rate"]), float(cfg["seconds"])
    sent = 0
    start = time.monotonic()
    end = start + seconds
    while (now := time.monotonic()) < end:
        if rate and sent >= (now - start) * rate:
            time.sleep(min(0.002, end - now))  # pacing: the flood's rate
            continue
        info = client.publish(cfg["topic"], payload, qos=0, retain=bool(cfg.get("retain")))
        if info.rc == paho.MQTT_ERR_SUCCESS:
            sent += 1
        else:  # paho's queue is full: let its thread write
            time.sleep(0.001)  # pacing: paho's queue full: let its thread write
    if cfg.get("retain"):
        client.publish(cfg["topic"], payload, qos=1, retain=True).wait_for_publish(10)
    client.disconnect()
    client.loop_stop()
    print(f"SENT {sent}", flush=True)
    return 0


def flood(port: int, topic: str, payload: bytes, *, rate: float, seconds: float,
          retain: bool = False) -> int:
    """Publish ``payload`` to ``topic`` ``rate`` times a second (0: flat out) for
    ``seconds`` from a child process; the number of messages paho accepted."""
    cfg: dict[str, Any] = {"port": port, "topic": topic, "payload_hex": payload.hex(),
                           "rate": rate, "seconds": seconds, "retain": retain}
    done = subprocess.run([sys.executable, str(SCRIPT), json.dumps(cfg)],
                          capture_output=True, text=True, timeout=seconds + 60, check=True)
    return int(done.stdout.split()[-1])


if __name__ == "__main__":
    sys.exit(main())
