"""One logging rule for every entry point: -v is one step more than the command's default."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from edgemodbus.cli import build_parser
from edgemodbus.logs import configure_logging


@pytest.fixture(autouse=True)
def _restore_logging() -> Iterator[None]:
    root = logging.getLogger()
    ours = logging.getLogger("edgemodbus")
    saved = (root.level, list(root.handlers), ours.level)
    yield
    root.setLevel(saved[0])
    root.handlers[:] = saved[1]
    ours.setLevel(saved[2])


@pytest.mark.parametrize(
    ("verbose", "default", "quiet", "level"),
    [
        (0, logging.WARNING, False, logging.WARNING),
        (1, logging.WARNING, False, logging.INFO),
        (2, logging.WARNING, False, logging.DEBUG),
        (5, logging.WARNING, False, logging.DEBUG),
        (0, logging.INFO, False, logging.INFO),
        (1, logging.INFO, False, logging.DEBUG),
        (3, logging.INFO, True, logging.WARNING),
    ],
)
def test_each_v_is_one_step_from_the_default(
    verbose: int, default: int, quiet: bool, level: int
) -> None:
    configure_logging(verbose, default=default, quiet=quiet)
    assert logging.getLogger("edgemodbus").level == level


def test_one_parser_tree_holds_every_command_and_its_options() -> None:
    """simulate and run --config-dir take their options from the same definitions as
    ``python -m edgemodbus.sim`` and ``python -m edgemodbus.gateway``: no argv rewriting."""
    parser = build_parser()
    sim = parser.parse_args(["-v", "simulate", "--port", "0", "--slaves", "1-3", "--movers"])
    assert (sim.command, sim.port, sim.slaves, sim.movers, sim.verbose) == (
        "simulate", 0, [1, 2, 3], True, 1)
    run = parser.parse_args(["run", "--config-dir", "/tmp", "--seconds", "2", "-q"])
    assert (run.command, str(run.config_dir), run.seconds, run.quiet) == ("run", "/tmp", 2.0, True)
