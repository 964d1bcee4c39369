"""The hypothesis profile of tests/conftest.py: an example that a loaded machine makes
slow is no failure (hypothesis's own default deadline, 200 ms per example, failed tests
under load), also for a test whose @settings name other keys."""

from __future__ import annotations

import time

from hypothesis import given, settings
from hypothesis import strategies as st


@settings(max_examples=2)
@given(st.integers())
def test_an_example_slower_than_200_ms_is_no_failure(n: int) -> None:
    time.sleep(0.25)  # pacing: one example as slow as a loaded machine makes one


def test_the_profile_has_no_deadline_and_prints_the_reproducing_blob() -> None:
    assert settings.default.deadline is None
    assert settings(max_examples=7).deadline is None  # inherited by a test's own settings
    assert settings.default.print_blob
