"""The ``console`` section of the gateway file: where the web console listens, who may
use it (a token, users with password hashes), TLS; checked like every section (the
field, the value, what is allowed).  No import of the server: a gateway file with a
console section loads without the optional packages (edgemodbus[console])."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Annotated, Any, ClassVar

from pydantic import AfterValidator, Field, field_validator, model_validator

from ..config import Model, Problem, Range
from ..config.limits import MAX_HOST, MAX_NAME, check_host
from ..config.secret import Secret
from ..northbound.mqtt import TlsSettings
from .auth import PasswordHash, is_loopback

DEFAULT_PORT = 8099
MIN_TOKEN = 16  # characters: a token is a password nobody types; guessable ones refused


class ConsoleUser(Model):
    """One user: name and the scrypt hash of the password (auth.py)."""

    _where: ClassVar[str] = "console.users[]"
    _max_lengths: ClassVar[dict[str, int]] = {"name": MAX_NAME}

    name: str = Field(description="The login name")
    password_hash: str = Field(description="scrypt$<log2 n>$<r>$<p>$<salt>$<key> of the "
                               "password: python -m edgemodbus.console hash-password")

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("empty: give the user's login name")
        return value

    @field_validator("password_hash")
    @classmethod
    def _hash(cls, value: str) -> str:
        PasswordHash.parse(value)
        return value


class ConsoleTls(Model):
    """HTTPS: the server's certificate and key, checked as ``mqtt.tls``'s files are."""

    _where: ClassVar[str] = "console.tls"

    enabled: bool = Field(default=True, description="false: the section is kept, plain HTTP")
    cert_file: str = Field(description="The server certificate (PEM; relative to the "
                           "gateway file's folder)")
    key_file: str | None = Field(default=None, description="Its private key (PEM); left out: the "
                                 "key is in certFile")

    def resolved(self, base: str | os.PathLike[str]) -> ConsoleTls:
        """A copy whose relative file paths are taken from folder ``base``."""
        update = {name: str(Path(base, path)) for name, path in
                  (("cert_file", self.cert_file), ("key_file", self.key_file))
                  if path is not None and not os.path.isabs(path)}
        return self.model_copy(update=update) if update else self

    def problems(self) -> list[Problem]:
        """What is wrong with the files (northbound/mqtt/settings.py TlsSettings.problems:
        missing, unreadable, not PEM, a key that does not fit the certificate)."""
        if not self.enabled:
            return []
        return TlsSettings(cert_file=self.cert_file,
                           key_file=self.key_file).problems("console.tls")


class ConsoleSettings(Model):
    """The ``console`` section (docs/console.md)."""

    _where: ClassVar[str] = "console"
    _max_lengths: ClassVar[dict[str, int]] = {"host": MAX_HOST}

    enabled: bool = Field(default=True, description="false: the section is kept but no console "
                          "runs")
    host: Annotated[str, AfterValidator(check_host)] = Field(
        default="127.0.0.1", description="The listen address; other than loopback only with a "
        "token or users")
    port: Annotated[int, Range(0, 65535)] = Field(
        default=DEFAULT_PORT, description="Its port (0: any free one, logged)")
    token: Secret | None = Field(default=None, description="A bearer token (at least 16 "
                                 "characters): a login, or Authorization: Bearer")
    users: list[ConsoleUser] = Field(default_factory=list,
                                     description="Users who may log in (name, passwordHash)")
    tls: ConsoleTls | None = Field(default=None, description="HTTPS: certFile and keyFile")
    max_streams: Annotated[int, Range(1, 1000)] = Field(
        default=16, description="Live tag streams open at once (one per open tag page); more "
        "are answered 503")
    max_connections: Annotated[int, Range(2, 4096)] = Field(
        default=64, description="Connections open at once; more are closed at accept")

    @field_validator("host")
    @classmethod
    def _listen_host(cls, value: str) -> str:
        """An empty host passed the host rule (it means "required elsewhere") and the
        start failed with getaddrinfo's "Name or service not known"."""
        if not value.strip():
            raise ValueError("empty: give the address to listen on (127.0.0.1 for this "
                             "machine only; another with a token or users)")
        return value

    @model_validator(mode="after")
    def _checks(self) -> ConsoleSettings:
        token = self.token.get_secret_value() if self.token is not None else None
        if token is not None and len(token) < MIN_TOKEN:
            raise ValueError(f"token: {len(token)} characters: at least {MIN_TOKEN} (a "
                             "random one: python -c 'import secrets; "
                             "print(secrets.token_urlsafe(24))')")
        names = [user.name for user in self.users]
        twice = sorted({name for name in names if names.count(name) > 1})
        if twice:
            raise ValueError(f"users: {', '.join(map(repr, twice))} given twice: one entry "
                             "per user name")
        if self.host and not is_loopback(self.host) and not self.has_credentials:
            raise ValueError(f"host {self.host!r} is reachable from other machines: give "
                             "a token or users (with password hashes), or listen on "
                             "127.0.0.1")
        if self.max_streams >= self.max_connections:
            raise ValueError(f"maxStreams {self.max_streams} must be less than "
                             f"maxConnections {self.max_connections} (streams are "
                             "connections too; the pages need some)")
        return self

    @property
    def has_credentials(self) -> bool:
        """Whether logging in is required (a token or a user is configured)."""
        return self.token is not None or bool(self.users)

    @property
    def scheme(self) -> str:
        return "https" if self.tls is not None and self.tls.enabled else "http"

    def resolved(self, base: str | os.PathLike[str]) -> ConsoleSettings:
        """A copy with the TLS files' relative paths taken from folder ``base``."""
        if self.tls is None:
            return self
        return self.model_copy(update={"tls": self.tls.resolved(base)})

    def problems(self) -> list[Problem]:
        return self.tls.problems() if self.tls is not None else []

    def files_digest(self) -> str:
        """A digest of the TLS files' contents ("" without TLS): a renewed certificate
        restarts the console on SIGHUP."""
        tls = self.tls
        if tls is None or not tls.enabled:
            return ""
        digest = hashlib.sha256()
        for name in (tls.cert_file, tls.key_file):
            if name is not None:
                try:
                    digest.update(Path(name).read_bytes())
                except OSError as exc:  # reported when the gateway file is loaded
                    digest.update(str(exc).encode())
        return digest.hexdigest()


def console_key(settings: ConsoleSettings | None) -> dict[str, Any] | None:
    """What the console is made from (secrets, TLS paths and their contents included): a
    change of it restarts the console on reload."""
    if settings is None or not settings.enabled:
        return None
    return {**settings.to_dict(secrets=True), "tlsFiles": settings.files_digest()}


__all__ = ["ConsoleSettings", "ConsoleTls", "ConsoleUser", "console_key"]
