"""The engine a listen-mode test's DTU lines run on (the ``engine`` fixture of
tests/conftest.py): "thread" (a line worker thread per DTU) or "loop" (line/loop.py, the
default).  Device helpers pass their communication settings through :func:`with_engine`,
so that a test marked ``@pytest.mark.usefixtures("engine")`` runs once per engine."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

ENGINES = ("thread", "loop")

_chosen: list[str] = []


@contextmanager
def chosen(engine: str) -> Iterator[str]:
    """Devices made through :func:`with_engine` meanwhile ask for ``engine``."""
    if engine not in ENGINES:
        raise ValueError(f"engine {engine!r}: must be one of {', '.join(ENGINES)}")
    _chosen.append(engine)
    try:
        yield engine
    finally:
        _chosen.pop()


def with_engine(comm: dict[str, Any]) -> dict[str, Any]:
    """``comm`` with the ``engine`` key of the engine chosen now (none chosen, or the
    settings naming one themselves: unchanged)."""
    if _chosen and "engine" not in comm:
        comm["engine"] = _chosen[-1]
    return comm
