"""The start cases of `make soak-gateway` (tools/soak_cases_config.py) as integration
tests: each is a hostile gateway folder (a 10 MB gatewayId or mqtt.host, 200,000 unknown
keys, a FIFO as the spool's path, idleTimeoutS 1e-12, a bdSeqFile naming a file that is
not a bdSeq) that the gateway, started through its CLI, must end with exit status 2 and
one short line naming the field (the unknown keys: a bounded warning, then it runs),
never a traceback or megabytes of log, leaving a foreign file as it was.  They take a
second or two each, so the soak's checks run here too (issue #25, "config" and
"Sparkplug" rows); the soak's other cases need tens of seconds each and stay there."""

from __future__ import annotations

from pathlib import Path

import pytest
from tools.soak_cases_config import StartCase, run_start_case, start_cases


@pytest.mark.parametrize("case", start_cases(), ids=lambda c: c.name)
def test_a_hostile_gateway_folder_is_refused_in_one_line(case: StartCase,
                                                         tmp_path: Path) -> None:
    figures = run_start_case(case, tmp_path)
    assert figures["failures"] == [], figures
    assert figures["logBytes"] < 8192, figures
