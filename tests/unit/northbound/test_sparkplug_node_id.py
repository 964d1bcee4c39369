"""The edge node id of a fleet instance (northbound/sparkplug/settings.py node_id_for):
two instances of one gateway file never share a node id (Sparkplug 3.0, 4.1.1), checked
for any edgeNodeId, template or not, and any two instance ids."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.northbound.sparkplug.settings import INSTANCE_FIELD, node_id_for

level = st.text(st.characters(blacklist_characters="+#/\0", blacklist_categories=("Cs",)),
                min_size=1, max_size=12)
template = st.lists(st.one_of(level, st.just(INSTANCE_FIELD)), min_size=1,
                    max_size=4).map("".join)


@given(template, level, level, level)
def test_distinct_instances_get_distinct_node_ids(base: str, gateway: str, one: str,
                                                  two: str) -> None:
    if one == two:
        assert node_id_for(base, gateway, one) == node_id_for(base, gateway, two)
    else:
        assert node_id_for(base, gateway, one) != node_id_for(base, gateway, two)


@given(level, level)
def test_without_a_template_the_instance_is_appended(base: str, instance: str) -> None:
    if INSTANCE_FIELD not in base:
        assert node_id_for(base, "gw", instance) == f"{base}-{instance}"
        assert node_id_for(None, base, instance) == f"{base}-{instance}"
