"""What a fleet of simulated DTUs needs of the operating system: a file descriptor per
DTU (:func:`raise_open_files_limit`) and an ephemeral port per DTU of each source
address it dials from (:func:`loopback_sources`, :func:`check_sources`)."""

from __future__ import annotations

import errno
import ipaddress
import logging
import resource
from collections.abc import Sequence

log = logging.getLogger("edgemodbus.simulator")

FD_MARGIN = 64
"""File descriptors a fleet needs besides one per DTU (stdio, the event loop, logs)."""


PORTS_PER_SOURCE = 20_000
"""DTUs :func:`loopback_sources` puts on one source address: under Linux's default
ephemeral range (32768-60999, 28,232 ports), with room for the other sockets."""


def loopback_sources(count: int) -> tuple[str, ...]:
    """Enough loopback source addresses (127.0.0.1, 127.0.0.2, ...) for ``count`` DTUs
    dialling a listener on loopback, :data:`PORTS_PER_SOURCE` each (Linux routes all of
    127.0.0.0/8 to the loopback device)."""
    if count < 1:
        raise ValueError(f"loopback sources for {count} DTUs: must be at least 1")
    needed = -(-count // PORTS_PER_SOURCE)
    if needed > 254:
        raise ValueError(f"loopback sources for {count} DTUs: at most "
                         f"{254 * PORTS_PER_SOURCE} (254 addresses of 127.0.0.x)")
    return tuple(f"127.0.0.{k}" for k in range(1, needed + 1))


def check_sources(sources: Sequence[str], host: str) -> tuple[str, ...]:
    """The ``sources`` as given, each checked to be an IP address of ``host``'s family
    (when ``host`` is an address itself)."""
    checked = []
    family: int
    try:
        family = ipaddress.ip_address(host).version
    except ValueError:
        family = 0  # a host name: its family is known once resolved
    for source in sources:
        try:
            version = ipaddress.ip_address(source).version
        except ValueError:
            raise ValueError(f"sources: {source!r} is not an IP address (the DTUs bind "
                             "to it before they connect)") from None
        if family and version != family:
            raise ValueError(f"sources: {source!r} is IPv{version}, host {host!r} IPv{family}")
        checked.append(str(source))
    return tuple(checked)


def raise_open_files_limit(needed: int) -> int:
    """Make room for ``needed`` open files: raise the soft ``RLIMIT_NOFILE`` to the hard
    limit when the soft one is lower than ``needed``; returns the soft limit now.

    OSError (EMFILE) when the hard limit itself is lower: only root (or the service
    manager) can raise it."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    infinite = resource.RLIM_INFINITY
    if soft == infinite or needed <= soft:
        return soft
    if hard != infinite and hard < needed:
        raise OSError(
            errno.EMFILE,
            f"{needed} open files needed, but this process may open at most {hard} "
            f"(the hard RLIMIT_NOFILE): raise it (`ulimit -Hn {needed}` as root, "
            f"LimitNOFILE={needed} in a systemd unit, `--ulimit nofile={needed}` for "
            "docker) or use fewer DTUs per process",
        )
    new = hard if hard != infinite else needed
    resource.setrlimit(resource.RLIMIT_NOFILE, (new, hard))
    log.info("open files limit raised from %d to %d", soft, new)
    return new


__all__ = ["FD_MARGIN", "PORTS_PER_SOURCE", "check_sources", "loopback_sources",
           "raise_open_files_limit"]
