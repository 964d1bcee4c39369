"""console/auth.py: password hashes, sessions, and the CSRF / Host rules."""

from __future__ import annotations

import hashlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.console.auth import (
    MAX_SESSIONS,
    SESSION_SECONDS,
    PasswordHash,
    Sessions,
    hash_password,
    host_allowed,
    is_loopback,
    origin_allowed,
    token_matches,
)


@settings(max_examples=15, deadline=None)
@given(st.text(min_size=1, max_size=40), st.text(min_size=1, max_size=40))
def test_a_hash_matches_its_password_only(password: str, other: str) -> None:
    stored = PasswordHash.parse(hash_password(password, log2_n=4))
    assert stored.matches(password)
    assert stored.matches(other) == (other == password)


def test_hash_agrees_with_hashlib_scrypt_itself() -> None:
    """A differential check: the stored key is hashlib.scrypt's over the stored salt."""
    salt = bytes(range(16))
    stored = PasswordHash.parse(hash_password("s3cret", salt=salt))
    assert stored.salt == salt
    assert stored.key == hashlib.scrypt(b"s3cret", salt=salt, n=1 << 14, r=8, p=1, dklen=32,
                                        maxmem=64 << 20)


@pytest.mark.parametrize("text, words", [
    ("md5$abc", "is not a password hash"),
    ("scrypt$x$8$1$AAAAAAAAAAA$AAAAAAAAAAAAAAAAAAAAAA", "must be integers"),
    ("scrypt$30$8$1$AAAAAAAAAAA$AAAAAAAAAAAAAAAAAAAAAA", "allowed log2 n 1..20"),
    ("scrypt$14$8$1$AAAA$AAAAAAAAAAAAAAAAAAAAAA", "at least 8 and 16"),
])
def test_bad_hashes_say_what_is_wrong(text: str, words: str) -> None:
    with pytest.raises(ValueError, match=words):
        PasswordHash.parse(text)


def test_empty_password_refused() -> None:
    with pytest.raises(ValueError, match="empty"):
        hash_password("")


def test_token_check() -> None:
    assert token_matches("a" * 20, "a" * 20)
    assert not token_matches("a" * 19, "a" * 20)


def test_sessions_expire_and_are_capped() -> None:
    now = [0.0]
    sessions = Sessions(clock=lambda: now[0])
    sid, session = sessions.create("ops")
    assert sessions.get(sid) is session and session.csrf
    now[0] = SESSION_SECONDS + 1
    assert sessions.get(sid) is None
    first, _ = sessions.create("a")
    for _ in range(MAX_SESSIONS):
        sessions.create("b")
    assert len(sessions) == MAX_SESSIONS and sessions.get(first) is None


@pytest.mark.parametrize("host, loopback", [
    ("127.0.0.1", True), ("127.1.2.3", True), ("::1", True), ("[::1]", True),
    ("localhost", True), ("0.0.0.0", False), ("192.168.1.5", False), ("example.com", False),
])
def test_is_loopback(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback


@pytest.mark.parametrize("header, allowed", [
    ("127.0.0.1:8099", True), ("localhost:8099", True), ("[::1]:8099", True),
    ("evil.example:8099", False), ("evil.example", False), (None, False),
])
def test_host_header_on_loopback(header: str | None, allowed: bool) -> None:
    """DNS rebinding: a name that is not loopback is refused by a loopback console."""
    assert host_allowed(header, "127.0.0.1", 8099) is allowed
    assert host_allowed(header, "0.0.0.0", 8099) is True


@pytest.mark.parametrize("origin, host, allowed", [
    (None, "127.0.0.1:8099", True),
    ("http://127.0.0.1:8099", "127.0.0.1:8099", True),
    ("https://127.0.0.1:8099/", "127.0.0.1:8099", True),
    ("http://evil.example", "127.0.0.1:8099", False),
    ("http://127.0.0.1:9000", "127.0.0.1:8099", False),
    ("null", "127.0.0.1:8099", False),
])
def test_origin(origin: str | None, host: str, allowed: bool) -> None:
    assert origin_allowed(origin, host) is allowed
