"""A lease engine reduced to a switch (gateway/lease.py's engine protocol), for tests of
what follows from holding or losing a lease; the Redis engine has tests of its own."""

from __future__ import annotations


class Switch:
    """Acquire and renew succeed while ``free`` is true."""

    def __init__(self) -> None:
        self.free = True

    def acquire(self, token: str, ttl_ms: int) -> int | None:
        return 1 if self.free else None

    def renew(self, token: str, ttl_ms: int) -> bool:
        return self.free

    def release(self, token: str) -> None:
        pass
