"""Secret config values (``registrationKey``): a field of type :data:`Secret` (a pydantic
``SecretStr``) is never shown in a repr, an error or a log line, and is masked
(``"**********"``) in ``to_dict()`` unless asked for (``to_dict(secrets=True)``).

The value is wrapped by :func:`hide_secrets` as soon as its key is known, before any
validation, so that no error later (not even pydantic's own text) shows it; a secret
given as anything but text is refused without being shown, and so is one longer than
:data:`~.limits.MAX_TEXT` (the length check of other strings runs after the wrap and
did not see a secret: a 30 MB ``console.token`` was taken).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

from pydantic import PlainSerializer, SecretStr, SerializationInfo

from .compat import norm_key
from .limits import MAX_TEXT
from .problems import NO_VALUE, ConfigError, Problem, join_path

SECRETS_CONTEXT = "edgemodbus.secrets"
"""The key of a dump's context that asks for secrets themselves (``to_dict``)."""


def _dump(value: SecretStr, info: SerializationInfo) -> str:
    """A secret in a JSON dump: masked as SecretStr masks it ("" stays ""), itself only
    when the dump's context asks for secrets."""
    context = info.context
    if isinstance(context, Mapping) and context.get(SECRETS_CONTEXT):
        return value.get_secret_value()
    return str(value)


Secret = Annotated[SecretStr, PlainSerializer(_dump, return_type=str, when_used="json")]
"""A secret text field: never in a repr or an error; masked in ``to_dict()``."""

_secret_keys: dict[type, frozenset[str]] = {}


def secret_keys(model: type[Any]) -> frozenset[str]:
    """The canonical keys of ``model``'s secret fields (its ``model_fields``)."""
    keys = _secret_keys.get(model)
    if keys is None:
        keys = frozenset(f.alias or n for n, f in model.model_fields.items()
                         if f.annotation in (SecretStr, Secret | None))
        _secret_keys[model] = keys
    return keys


def hide_secrets(data: Mapping[Any, Any], table: Mapping[str, str], keys: frozenset[str],
                 prefix: str) -> Mapping[Any, Any]:
    """``data`` with the values of secret keys (``keys``, canonical; ``table`` maps a
    normalised key to its canonical one) wrapped in SecretStr; ConfigError (paths from
    ``prefix``, no value shown) for one that is not text."""
    if not keys:
        return data
    out = dict(data)
    problems: list[Problem] = []
    for key, value in data.items():
        canon = table.get(norm_key(key)) if isinstance(key, str) else None
        if canon not in keys or value is None or isinstance(value, SecretStr):
            continue
        if isinstance(value, str) and len(value) > MAX_TEXT:
            problems.append(Problem(join_path(prefix, canon), NO_VALUE,
                                    f"{len(value):,} characters: at most {MAX_TEXT:,} "
                                    "(the value is not shown: a secret)"))
        elif isinstance(value, str):
            out[key] = SecretStr(value)
        else:
            problems.append(Problem(join_path(prefix, canon), NO_VALUE,
                                    "must be a string (the value given, of type "
                                    f"{type(value).__name__}, is not shown: a secret)"))
    if problems:
        raise ConfigError(problems)
    return out


__all__ = ["SECRETS_CONTEXT", "Secret", "hide_secrets", "secret_keys"]
