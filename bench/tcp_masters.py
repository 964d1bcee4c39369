"""Modbus TCP masters as a benchmark load, in a process of their own (their CPU is not
the server's): ``python -m bench.tcp_masters HOST PORT UNIT MASTERS COUNT SECONDS``.

Each of MASTERS connections reads COUNT holding registers from address 0 of UNIT, one
request in flight per connection (a master waits for its reply), for SECONDS; one
thread drives them all with non-blocking sockets.  Prints one JSON line: replies that
are a normal FC03 reply of the right length (``ok``), any other (``bad``), the seconds
measured, and the first register of the last reply (the caller checks it)."""

from __future__ import annotations

import json
import selectors
import socket
import struct
import sys
import time


def main(argv: list[str]) -> int:
    host, port, unit, masters, count, seconds = (argv[0], int(argv[1]), int(argv[2]),
                                                 int(argv[3]), int(argv[4]), float(argv[5]))
    want = 9 + 2 * count
    sel = selectors.DefaultSelector()
    socks = []
    for k in range(masters):
        sock = socket.create_connection((host, port))
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        socks.append(sock)
        sel.register(sock, selectors.EVENT_READ, [k, b""])
    tid = 0

    def send(sock: socket.socket) -> None:
        nonlocal tid
        tid = (tid + 1) & 0xFFFF
        sock.send(struct.pack(">HHHBBHH", tid, 0, 6, unit, 3, 0, count))

    ok = bad = 0
    first = -1
    for sock in socks:
        send(sock)
    start = time.monotonic()
    end = start + seconds
    while time.monotonic() < end:
        for key, _ in sel.select(timeout=0.5):
            sock = key.fileobj
            assert isinstance(sock, socket.socket)
            state = key.data
            chunk = sock.recv(4096)
            if not chunk:
                print(json.dumps({"error": f"master {state[0]}: connection closed"}))
                return 1
            state[1] += chunk
            if len(state[1]) < want and not (len(state[1]) >= 8 and state[1][7] & 0x80):
                continue
            reply, state[1] = state[1], b""
            if len(reply) == want and reply[7] == 3:
                ok += 1
                first = struct.unpack_from(">H", reply, 9)[0]
            else:
                bad += 1
            send(sock)
    elapsed = time.monotonic() - start
    for sock in socks:
        sock.close()
    print(json.dumps({"ok": ok, "bad": bad, "seconds": elapsed, "first": first}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
