"""The console's credentials: password hashes (hashlib.scrypt: the standard library's,
no extra package), the bearer token check, login sessions and the CSRF rules.

Pure bookkeeping, no I/O: the server (server.py, routes.py) asks it.  A hash is the text
``scrypt$<log2 n>$<r>$<p>$<salt, base64>$<key, base64>`` so that the cost can be raised
later without invalidating the hashes already in gateway files; ``python -m
edgemodbus.console hash-password`` makes one."""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import ipaddress
import secrets
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

SCHEME = "scrypt"
LOG2_N = 14  # n = 16384, r = 8: 16 MiB and about 50 ms per check (RFC 7914 section 2)
R = 8
P = 1
KEY_BYTES = 32
SALT_BYTES = 16
MAX_LOG2_N = 20  # what a hash may ask for: at most 1 GiB of memory (128 * r * n)
MAX_R = 32
MAX_P = 16
SESSION_SECONDS = 12 * 3600.0
MAX_SESSIONS = 256  # the oldest session is forgotten past this many
SESSION_COOKIE = "emb_session"
CSRF_HEADER = "X-CSRF-Token"


def hash_password(password: str, *, log2_n: int = LOG2_N, salt: bytes | None = None) -> str:
    """The stored form of ``password`` (a new random salt unless one is given)."""
    if not password:
        raise ValueError("password: empty; give at least one character")
    salt = secrets.token_bytes(SALT_BYTES) if salt is None else salt
    key = _derive(password, salt, log2_n, R, P)
    return "$".join((SCHEME, str(log2_n), str(R), str(P), _b64(salt), _b64(key)))


@dataclass(frozen=True)
class PasswordHash:
    """A parsed ``scrypt$...`` hash."""

    log2_n: int
    r: int
    p: int
    salt: bytes
    key: bytes

    @classmethod
    def parse(cls, text: str) -> PasswordHash:
        """ValueError says what is wrong with ``text`` (the hash itself is not shown)."""
        parts = text.split("$")
        if len(parts) != 6 or parts[0] != SCHEME:
            raise ValueError("is not a password hash of the form scrypt$<log2 n>$<r>$<p>$"
                             "<salt>$<key> (make one with: python -m edgemodbus.console "
                             "hash-password)")
        try:
            log2_n, r, p = (int(x) for x in parts[1:4])
            salt, key = _unb64(parts[4]), _unb64(parts[5])
        except (ValueError, binascii.Error):
            raise ValueError("scrypt hash: log2 n, r and p must be integers and salt and "
                             "key base64") from None
        if not (1 <= log2_n <= MAX_LOG2_N and 1 <= r <= MAX_R and 1 <= p <= MAX_P):
            raise ValueError(f"scrypt hash: log2 n {log2_n}, r {r}, p {p}: allowed log2 n "
                             f"1..{MAX_LOG2_N}, r 1..{MAX_R}, p 1..{MAX_P}")
        if len(salt) < 8 or len(key) < 16:
            raise ValueError(f"scrypt hash: salt of {len(salt)} bytes and key of {len(key)}:"
                             " at least 8 and 16")
        return cls(log2_n, r, p, salt, key)

    def matches(self, password: str) -> bool:
        """Whether ``password`` is the one hashed (constant-time comparison)."""
        key = _derive(password, self.salt, self.log2_n, self.r, self.p, len(self.key))
        return hmac.compare_digest(key, self.key)


def _derive(password: str, salt: bytes, log2_n: int, r: int, p: int,
            length: int = KEY_BYTES) -> bytes:
    n = 1 << log2_n
    return hashlib.scrypt(password.encode(), salt=salt, n=n, r=r, p=p, dklen=length,
                          maxmem=128 * r * n + (1 << 20))


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode().rstrip("=")


def _unb64(text: str) -> bytes:
    return base64.b64decode(text + "=" * (-len(text) % 4), validate=True)


def token_matches(given: str, token: str) -> bool:
    """The bearer token check, constant-time."""
    return hmac.compare_digest(given.encode(), token.encode())


@dataclass
class Session:
    """A logged-in browser: who, its CSRF token (sent back in ``X-CSRF-Token`` with every
    change), until when."""

    user: str
    csrf: str
    expires: float


class Sessions:
    """Login sessions by random id (the cookie), at most :data:`MAX_SESSIONS`, each
    :data:`SESSION_SECONDS` long.  Used on the server's loop only (no lock)."""

    def __init__(self, clock: Callable[[], float] | None = None) -> None:
        self._clock = clock or time.monotonic
        self._by_id: OrderedDict[str, Session] = OrderedDict()

    def create(self, user: str) -> tuple[str, Session]:
        now = self._clock()
        while len(self._by_id) >= MAX_SESSIONS:
            self._by_id.popitem(last=False)
        sid = secrets.token_urlsafe(32)
        session = Session(user, secrets.token_urlsafe(32), now + SESSION_SECONDS)
        self._by_id[sid] = session
        return sid, session

    def get(self, sid: str | None) -> Session | None:
        if not sid:
            return None
        session = self._by_id.get(sid)
        if session is None:
            return None
        if session.expires <= self._clock():
            del self._by_id[sid]
            return None
        return session

    def drop(self, sid: str | None) -> None:
        if sid:
            self._by_id.pop(sid, None)

    def __len__(self) -> int:
        return len(self._by_id)


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a listen address or a name) is reachable from this machine
    only: 127.0.0.0/8, ::1 or ``localhost``."""
    text = host.strip().strip("[]").lower()
    if text in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(text).is_loopback
    except ValueError:
        return False


def origin_allowed(origin: str | None, host_header: str | None) -> bool:
    """CSRF: a request that changes something must come from our own pages.  Browsers
    send ``Origin`` with every POST (Fetch standard, "Origin header"); it must name the
    host and port the request was sent to.  No Origin (a non-browser client, which
    cannot be made to send a cookie by a foreign page) passes."""
    if origin is None:
        return True
    if host_header is None:
        return False
    _, sep, rest = origin.partition("://")
    return bool(sep) and rest.rstrip("/").lower() == host_header.lower()


def host_allowed(host_header: str | None, listen_host: str, port: int) -> bool:
    """DNS rebinding: a console bound to loopback answers only requests addressed to a
    loopback name (a foreign name resolving to 127.0.0.1 is refused).  Other listen
    addresses need credentials anyway (settings.py), so any Host passes there."""
    if not is_loopback(listen_host):
        return True
    if not host_header:
        return False
    name = host_header
    if name.startswith("["):
        name = name[1:].partition("]")[0]
    elif name.count(":") == 1:
        name = name.partition(":")[0]
    return is_loopback(name)


__all__ = [
    "CSRF_HEADER",
    "SESSION_COOKIE",
    "PasswordHash",
    "Session",
    "Sessions",
    "hash_password",
    "host_allowed",
    "is_loopback",
    "origin_allowed",
    "token_matches",
]
