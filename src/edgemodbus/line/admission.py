"""Who may take a place at the DTU listener, before and while it registers: source
address allow-lists (:class:`Networks`), caps on connections not registered yet
(:class:`Unregistered`), the pre-registration byte budget (:class:`ByteBudget`) and the
registration key check (:func:`key_matches`).  Pure bookkeeping, no I/O: the listener
(:mod:`edgemodbus.line.dtu_listener`) asks, these answer.
"""

from __future__ import annotations

import hmac
import ipaddress
from collections import Counter
from collections.abc import Iterable

IpNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


def parse_networks(cidrs: Iterable[str], field: str) -> tuple[IpNetwork, ...]:
    """CIDR strings (a bare address is one host) as networks; a bad one is a ValueError
    that names ``field``, the value and what is allowed."""
    nets = []
    for text in cidrs:
        try:
            nets.append(ipaddress.ip_network(text.strip(), strict=False))
        except ValueError:
            raise ValueError(f"{field}: {text!r} is not an IPv4 or IPv6 network; use CIDR "
                             "like '10.0.0.0/8', '2001:db8::/32' or one address") from None
    return tuple(nets)


class Networks:
    """An allow-list of networks; empty allows every address."""

    def __init__(self, cidrs: Iterable[str], field: str) -> None:
        self.nets = parse_networks(cidrs, field)

    def allows(self, address: str) -> bool:
        """Whether ``address`` (as accept() gives it) lies in one of the networks.  An
        IPv4 peer on an IPv6 socket (``::ffff:10.0.0.9``) counts as its IPv4 address."""
        if not self.nets:
            return True
        try:
            ip = ipaddress.ip_address(address.split("%", 1)[0])
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return any(ip.version == net.version and ip in net for net in self.nets)


class Unregistered:
    """Connections waiting to register, per port and per source address: a newcomer
    beyond either cap is refused at once."""

    def __init__(self, per_port: int, per_source: int) -> None:
        self.per_port = per_port
        self.per_source = per_source
        self.total = 0
        self._by_source: Counter[str] = Counter()

    def refusal(self, source: str, per_source: bool = True) -> tuple[str, str] | None:
        """Why a new connection from ``source`` is refused, as (the listener's counter,
        the reason), or None: it may wait.  ``per_source`` False: a load balancer's
        connection, whose DTU's address is not known yet (only the port's cap holds)."""
        if self.total >= self.per_port:
            return ("refusedPortCap",
                    f"{self.total} connections are waiting to register (maxUnregistered)")
        waiting = self._by_source.get(source, 0)
        if per_source and waiting >= self.per_source:
            return ("refusedSourceCap", f"{waiting} connections from {source} are waiting "
                    "to register (maxUnregisteredPerSource)")
        return None

    def add(self, source: str) -> None:
        self.total += 1
        self._by_source[source] += 1

    def remove(self, source: str) -> None:
        self.total -= 1
        left = self._by_source[source] - 1
        if left > 0:
            self._by_source[source] = left
        else:
            del self._by_source[source]  # the counter never keeps sources that left


class ByteBudget:
    """What one connection may send before it registers: a token bucket of ``rate``
    bytes/s holding at most ``burst`` bytes (rate 0: no limit)."""

    __slots__ = ("_at", "_level", "burst", "rate")

    def __init__(self, rate: float, burst: int, now: float) -> None:
        self.rate = rate
        self.burst = burst
        self._level = float(burst)
        self._at = now

    def spend(self, n: int, now: float) -> float:
        """Spend ``n`` bytes just read; returns how long to stop reading (0: none)."""
        if not self.rate:
            return 0.0
        self._level = min(self.burst, self._level + (now - self._at) * self.rate) - n
        self._at = now
        return 0.0 if self._level >= 0 else -self._level / self.rate


def key_matches(sent: bytes | None, key: bytes) -> bool:
    """Whether the key a registration carried is the DTU's (constant time in its
    content, so a guesser learns nothing from how long the check took)."""
    return sent is not None and hmac.compare_digest(sent, key)


__all__ = ["ByteBudget", "Networks", "Unregistered", "key_matches", "parse_networks"]
