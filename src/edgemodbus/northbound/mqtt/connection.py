"""The connection to the broker, in words and in the log: why an attempt failed, failures
logged without flooding, dropping a connection that never got its CONNACK, and writing
what paho queued in as few TCP segments as it fits."""

from __future__ import annotations

import contextlib
import logging
import socket
from typing import TYPE_CHECKING, Any

from ...config.tls import connect_error_text

if TYPE_CHECKING:
    from paho.mqtt.client import Client

    from .settings import MqttSettings

log = logging.getLogger("edgemodbus.mqtt")

_CORK: int | None = getattr(socket, "TCP_CORK", None)  # Linux


def authenticate(client: Client, s: MqttSettings) -> None:
    """Give ``client`` the section's credentials and TLS settings (every publisher's)."""
    if s.username is not None:
        client.username_pw_set(
            s.username, s.password.get_secret_value() if s.password is not None else None)
    if s.tls is not None and s.tls.enabled:
        client.tls_set(ca_certs=s.tls.ca_file, certfile=s.tls.cert_file,
                       keyfile=s.tls.key_file)
        client.tls_insecure_set(s.tls.insecure)


class FailureLog:
    """Failed connection attempts, logged without flooding: the first at once, then at
    most one line per ``interval`` seconds with the number of attempts it stands for;
    every attempt at debug level."""

    def __init__(self, where: str, interval: float, retry_max: float) -> None:
        self.where = where
        self.interval = interval
        self.retry_max = retry_max
        self.total = 0  # failures since the last success
        self.unreported = 0  # failures since the last warning line
        self.last_line = 0.0

    def failed(self, reason: str, now: float) -> None:
        self.total += 1
        self.unreported += 1
        log.debug("MQTT broker %s: connection attempt %d failed: %s", self.where, self.total,
                  reason)
        if self.total == 1:
            log.warning("MQTT broker %s: connection failed: %s; retrying with backoff up to "
                        "%g s (repeats logged at most every %g s)", self.where, reason,
                        self.retry_max, self.interval)
        elif now - self.last_line >= self.interval:
            log.warning("MQTT broker %s: still failing: %s (%d failed attempts since the "
                        "last report, %d in all)", self.where, reason, self.unreported,
                        self.total)
        else:
            return
        self.unreported = 0
        self.last_line = now

    def succeeded(self) -> int:
        """Forget the failures; how many there were."""
        total, self.total, self.unreported = self.total, 0, 0
        return total


def error_text(exc: BaseException, tls: bool) -> str:
    """A connect error in words (config/tls.py, shared with the mqtt-dtu links)."""
    return connect_error_text(exc, "mqtt.tls" if tls else None)


def abandon(client: Client) -> None:
    """Drop a connection that never got its CONNACK, through paho's public calls:
    disconnect() queues a DISCONNECT, and paho closes the socket once loop_write() has
    written it (if the socket cannot take it now, the MQTT thread's next loop_write()
    does; the socket is gone in either case before the next attempt)."""
    client.disconnect()
    if client.socket() is not None:
        client.loop_write()


def write(client: Client) -> None:
    """``client.loop_write()`` with the socket corked (Linux TCP_CORK, on the socket
    paho's public ``socket()`` returns): paho writes each queued packet with a send() of
    its own, and every send() on an uncorked socket is a TCP segment of its own, whose
    transmission (and on loopback, the broker's receive) costs far more CPU than the
    send() itself; corked, they leave together when the cork is pulled."""
    sock = client.socket()
    corked = False
    if _CORK is not None and isinstance(sock, socket.socket):  # an SSLSocket is one too
        try:
            sock.setsockopt(socket.IPPROTO_TCP, _CORK, 1)
            corked = True
        except OSError:  # not a TCP socket
            pass
    try:
        client.loop_write()
    finally:
        if corked and _CORK is not None and isinstance(sock, socket.socket):
            with contextlib.suppress(OSError):  # closed meanwhile: nothing left to send
                sock.setsockopt(socket.IPPROTO_TCP, _CORK, 0)


def write_wanted(_client: Client, _userdata: Any, _sock: Any) -> None:
    """paho's ``on_socket_register_write``: paho has bytes to write.  Nothing to do: the
    MQTT thread's select() asks ``want_write()`` before it sleeps; set, the callback
    makes publish() queue a message instead of writing it at once."""
