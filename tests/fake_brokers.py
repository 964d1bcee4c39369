"""Peers that are not MQTT brokers, for connection-failure tests, and TLS test files.

`FakeBroker(mode)` listens on a free 127.0.0.1 port and, for every connection, either
closes it at once (``"close"``: a port that hangs up, like a TLS-only listener reading
a plain CONNECT) or keeps it open without a word (``"silent"``: no CONNACK ever).  It
counts the connections it accepted.  `stop()` closes everything and joins its thread.

`self_signed_cert(folder)` makes a certificate for 127.0.0.1 and its key with the
``openssl`` command (PEM files ``cert.pem`` and ``key.pem``).
"""

from __future__ import annotations

import contextlib
import selectors
import shutil
import socket
import subprocess
import threading
from pathlib import Path
from typing import Literal

Mode = Literal["close", "silent"]


class FakeBroker:
    """A TCP listener that accepts and then hangs up, or stays silent."""

    def __init__(self, mode: Mode) -> None:
        self.mode = mode
        self.accepted = 0
        self._server = socket.create_server(("127.0.0.1", 0))
        self._server.setblocking(False)
        self.port: int = self._server.getsockname()[1]
        self._wake_r, self._wake_w = socket.socketpair()
        self._held: list[socket.socket] = []
        self._thread = threading.Thread(target=self._serve, name=f"fake-broker-{mode}",
                                        daemon=True)

    def __enter__(self) -> FakeBroker:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _serve(self) -> None:
        with selectors.DefaultSelector() as sel:
            sel.register(self._server, selectors.EVENT_READ)
            sel.register(self._wake_r, selectors.EVENT_READ)
            while True:
                for key, _ in sel.select():
                    if key.fileobj is self._wake_r:
                        return
                    with contextlib.suppress(BlockingIOError):
                        conn, _ = self._server.accept()
                        self.accepted += 1
                        if self.mode == "close":
                            conn.close()
                        else:
                            self._held.append(conn)

    def stop(self) -> None:
        if self._thread.is_alive():
            self._wake_w.send(b"x")
            self._thread.join(5.0)
        for sock in [*self._held, self._server, self._wake_r, self._wake_w]:
            sock.close()
        self._held.clear()


def self_signed_cert(folder: Path) -> tuple[Path, Path]:
    """(cert.pem, key.pem) for CN localhost, IP 127.0.0.1, valid two days."""
    openssl = shutil.which("openssl")
    if openssl is None:
        raise RuntimeError("the openssl command is needed: apt-get install openssl")
    folder.mkdir(parents=True, exist_ok=True)
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(
        [openssl, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
         "-nodes", "-keyout", str(key), "-out", str(cert), "-days", "2",
         "-subj", "/CN=localhost", "-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost"],
        check=True, capture_output=True, timeout=30,
    )
    return cert, key
