"""One line of the simulator: a TCP connection or a pty, with its buffers and state."""

from __future__ import annotations

import contextlib
import os
import socket


class _Line:
    """One half-duplex "line": a TCP client connection or a pty master."""

    def __init__(
        self,
        name: str,
        silence: float,
        sock: socket.socket | None = None,
        fds: tuple[int, int] | None = None,
    ) -> None:
        self.name = name
        self.silence = silence
        self.sock = sock
        self.fds = fds  # pty (master, slave); the slave end is held open so that the
        # master never sees a hangup (EIO) between two clients
        self.path = ""  # pty: the slave side's path
        self.link = ""  # pty: a symlink to it made by serve_pty(link=...)
        self.rx = bytearray()
        self.out = bytearray()
        self.last_rx = 0.0
        self.idle_pending = False
        self.closed = False
        # DTU-client mode (Simulator.dial)
        self.heartbeat = b""
        self.heartbeat_before_reply = False  # put a heartbeat in front of every reply
        self.wrapped = False  # wrapped-report framing: FF AA addr RTU 0D
        self.heartbeats_sent = 0

    @property
    def is_tcp(self) -> bool:
        return self.sock is not None

    def fileno(self) -> int:
        if self.sock is not None:
            return self.sock.fileno()
        assert self.fds is not None
        return self.fds[0]

    def recv(self) -> bytes:
        if self.sock is not None:
            return self.sock.recv(4096)
        assert self.fds is not None
        return os.read(self.fds[0], 4096)

    def send(self, data: bytes | bytearray) -> int:
        if self.sock is not None:
            return self.sock.send(data)
        assert self.fds is not None
        return os.write(self.fds[0], data)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if self.sock is not None:
            self.sock.close()
        if self.fds is not None:
            for fd in self.fds:
                with contextlib.suppress(OSError):
                    os.close(fd)
        if self.link:
            with contextlib.suppress(OSError):
                if os.readlink(self.link) == self.path:
                    os.unlink(self.link)
