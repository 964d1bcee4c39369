"""config/jsonfile.py's depth check walks a file once without paths (a device file is
thousands of containers): the same verdict as the walk with paths, which still names
the place of a file nested too deep."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.config import ConfigError, jsonfile
from edgemodbus.config.jsonfile import MAX_JSON_DEPTH, check_depth


def _nested(depth: int, leaf: Any = 1) -> Any:
    value = leaf
    for k in range(depth):
        value = [value] if k % 2 else {"k": value}
    return value


_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.text(max_size=3),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=2), inner,
                                                                max_size=3),
    max_leaves=40)


@settings(max_examples=200, deadline=None)
@given(_json, st.integers(0, MAX_JSON_DEPTH + 3))
def test_the_fast_walk_agrees_with_the_walk_with_paths(value: Any, depth: int) -> None:
    data = [value, _nested(depth)]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(jsonfile, "_within_depth", lambda _data: False)  # the walk with paths
        try:
            check_depth(data, "x")
            slow = True
        except ConfigError:
            slow = False
    assert jsonfile._within_depth(data) == slow


def test_the_limit_and_the_message() -> None:
    check_depth(_nested(MAX_JSON_DEPTH), "f.json")  # the root is one level of 32
    with pytest.raises(ConfigError, match=r"f\.json: k\[0\]\.k\[0\].*nested more than 32"):
        check_depth(_nested(MAX_JSON_DEPTH + 1), "f.json")
