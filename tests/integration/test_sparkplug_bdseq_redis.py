"""The bdSeq a redundant pair keeps in Redis (``sharedByPair``) is ours only while the key
holds a bdSeq: anything else there (another application's value under the key prefix,
a huge or garbage value) is refused with what was found and never overwritten, like the
bdSeq file's rule (northbound/sparkplug/bdseq.py).  Against a real redis-server: the
check and the write are one script there, so the test runs that script."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edgemodbus.northbound.sparkplug.bdseq import RedisBdSeqStore, redis_bd_seq
from tests.redis_server import RedisServer

redis = pytest.importorskip("redis")

KEY = "sp:pair:bdseq"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisServer]:
    with RedisServer(Path(tmp_path_factory.mktemp("redis"))) as started:
        yield started


@pytest.fixture
def client(server: RedisServer) -> Iterator[object]:
    conn = redis.Redis.from_url(server.url, socket_timeout=5.0)
    try:
        yield conn
    finally:
        conn.close()
        conn.connection_pool.disconnect()


def _ours(raw: bytes) -> int | None:
    """An independent statement of the rule: ASCII digits, one to three, 0-255."""
    if 1 <= len(raw) <= 3 and all(0x30 <= b <= 0x39 for b in raw) and int(raw) <= 255:
        return int(raw)
    return None


@pytest.mark.parametrize("found", [b"x", b"1.5", b"-1", b"256", b"0255", b" 7", b"7\n",
                                   "\u0663".encode(), b"\xff\xfe", b"", b"9" * 1_000_000])
def test_a_foreign_value_is_refused_and_never_overwritten(
        client: object, found: bytes, caplog: pytest.LogCaptureFixture) -> None:
    client.set(KEY, found)  # type: ignore[attr-defined]
    store = RedisBdSeqStore(client, KEY, lambda: True)
    with pytest.raises(ValueError, match=f"Redis key {KEY} holds .*not a bdSeq 0-255") as exc:
        store.load()
    assert len(str(exc.value)) < 300  # a short prefix of what was found, not all of it
    with caplog.at_level(logging.ERROR, logger="edgemodbus.sparkplug"):
        store.save(4)
    assert client.get(KEY) == found  # type: ignore[attr-defined]
    assert any(f"bdSeq 4 not kept: Redis key {KEY} holds" in r.getMessage()
               for r in caplog.records), caplog.text
    assert max(len(r.getMessage()) for r in caplog.records) < 400


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.one_of(st.binary(max_size=6), st.integers(0, 400).map(lambda n: str(n).encode()),
                 st.none()))
def test_save_overwrites_only_a_bdseq_differential(client: object, found: bytes | None) -> None:
    """Any value under the key: our number (or no key) is read and replaced by save();
    anything else is refused and stays, byte for byte."""
    if found is None:
        client.delete(KEY)  # type: ignore[attr-defined]
    else:
        client.set(KEY, found)  # type: ignore[attr-defined]
    store = RedisBdSeqStore(client, KEY, lambda: True)
    expected = 0 if found is None else _ours(found)
    if expected is None:
        with pytest.raises(ValueError):
            store.load()
        assert found is not None
        with pytest.raises(ValueError):
            redis_bd_seq(KEY, found)
    else:
        assert store.load() == expected
    store.save(17)
    after = client.get(KEY)  # type: ignore[attr-defined]
    assert after == (b"17" if expected is not None else found)
