"""Which lines the loop engine serves (line/loop.py): every DTU stream kind that
csrc/emb_loop_io.c frames, and the endpoints the gateway connects to without alternates
(line/failover.py's watcher drives a line worker); why not, in the error's words."""

from __future__ import annotations

from .endpoint import DtuEndpoint, TcpEndpoint


def loop_serves(endpoint: DtuEndpoint | TcpEndpoint) -> bool:
    """Whether the loop engine serves this line: a DTU that dials in, with every stream
    framing csrc/emb_loop_link.c serves (plain RTU, with heartbeats or the echo option,
    and wrapped frames with their reports), or an endpoint the gateway connects to,
    plain RTU over TCP or Modbus TCP (MBAP), without alternates (failover.py's watcher
    drives a line worker)."""
    if isinstance(endpoint, TcpEndpoint):
        return not endpoint.alternates and (
            endpoint.transport == "tcp"
            or (endpoint.transport == "rtu-over-tcp" and not endpoint.echo
                and endpoint.framing == "rtu"))
    return endpoint.framing in ("rtu", "wrapped-report")


def why_not(endpoint: DtuEndpoint | TcpEndpoint) -> str:
    """Why the loop engine does not serve ``endpoint`` (see :func:`loop_serves`)."""
    if isinstance(endpoint, DtuEndpoint):
        return (f"framing {endpoint.framing!r}: engine 'loop' serves framing rtu and "
                "wrapped-report")
    if endpoint.alternates:
        return "alternates: engine 'loop' serves endpoints without alternates"
    if endpoint.echo:
        return "echo: engine 'loop' serves rtu-over-tcp endpoints without the echo option"
    return (f"framing {endpoint.framing!r}: engine 'loop' serves rtu-over-tcp endpoints "
            "with framing rtu")


__all__ = ["loop_serves", "why_not"]
