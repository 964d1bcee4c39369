"""A minimal MQTT 3.1.1 broker over TLS that plays one DTU and writes several packets in
one TLS record, as brokers that coalesce their writes do (mosquitto writes one record
per packet, so it cannot show this).

`CoalescingBroker(cert, key, dtu)` listens on a free 127.0.0.1 port for one client at a
time: CONNACK, SUBACK for every SUBSCRIBE, PINGRESP; each PUBLISH on ``dtu/<dtu>/down``
(a Modbus RTU request for holding registers, FC03) is answered on ``dtu/<dtu>/up`` with
registers ``address * 3 + 1``, the reply frame cut into two PUBLISH packets sent in one
TLS record.  `stop()` closes everything and joins its thread.
"""

from __future__ import annotations

import contextlib
import socket
import ssl
import struct
import threading
from pathlib import Path

from edgemodbus.protocol.rtu import frame


def register(address: int) -> int:
    """The value the broker's DTU answers for holding register ``address``."""
    return (address * 3 + 1) & 0xFFFF


def _publish(topic: str, payload: bytes) -> bytes:
    body = struct.pack(">H", len(topic)) + topic.encode() + payload
    assert len(body) < 128
    return bytes([0x30, len(body)]) + body


class CoalescingBroker:
    """See the module docstring."""

    def __init__(self, cert: Path, key: Path, dtu: str) -> None:
        self.context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        self.context.load_cert_chain(cert, key)
        self.up, self.down = f"dtu/{dtu}/up", f"dtu/{dtu}/down"
        self.answered = 0
        self._server = socket.create_server(("127.0.0.1", 0))
        self._server.settimeout(0.2)
        self.port: int = self._server.getsockname()[1]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="coalescing-broker",
                                        daemon=True)

    def __enter__(self) -> CoalescingBroker:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10.0)
        self._server.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                raw, _ = self._server.accept()
            except TimeoutError:
                continue
            with contextlib.suppress(OSError, ValueError), raw:
                raw.settimeout(0.2)
                with self.context.wrap_socket(raw, server_side=True) as conn:
                    self._session(conn)

    def _read(self, conn: ssl.SSLSocket, n: int) -> bytes:
        data = b""
        while len(data) < n:
            try:
                chunk = conn.recv(n - len(data))
            except TimeoutError:
                if self._stop.is_set():
                    raise OSError("stopping") from None
                continue
            if not chunk:
                raise OSError("closed")
            data += chunk
        return data

    def _session(self, conn: ssl.SSLSocket) -> None:
        while True:
            kind = self._read(conn, 1)[0]
            length, shift = 0, 0
            while True:  # the remaining length, a variable byte integer
                byte = self._read(conn, 1)[0]
                length |= (byte & 0x7F) << shift
                shift += 7
                if not byte & 0x80:
                    break
            body = self._read(conn, length)
            if kind >> 4 == 1:  # CONNECT
                conn.sendall(b"\x20\x02\x00\x00")
            elif kind >> 4 == 8:  # SUBSCRIBE: grant QoS 0 to each filter
                count, i = 0, 2
                while i < len(body):
                    i += 2 + struct.unpack_from(">H", body, i)[0] + 1
                    count += 1
                conn.sendall(bytes([0x90, 2 + count]) + body[:2] + b"\x00" * count)
            elif kind >> 4 == 12:  # PINGREQ
                conn.sendall(b"\xd0\x00")
            elif kind >> 4 == 14:  # DISCONNECT
                return
            elif kind >> 4 == 3:  # PUBLISH (QoS 0: no packet id)
                size = struct.unpack_from(">H", body)[0]
                if body[2:2 + size].decode() == self.down:
                    self._answer(conn, body[2 + size:])

    def _answer(self, conn: ssl.SSLSocket, request: bytes) -> None:
        slave, function, start, count = struct.unpack_from(">BBHH", request)
        if function != 3:
            return
        values = b"".join(struct.pack(">H", register(start + i)) for i in range(count))
        reply = frame(slave, bytes([3, 2 * count]) + values)
        half = len(reply) // 2
        conn.sendall(_publish(self.up, reply[:half]) + _publish(self.up, reply[half:]))
        self.answered += 1
