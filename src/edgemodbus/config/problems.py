"""How configuration problems are told: :class:`Problem` (path, value given, what is
allowed) and :class:`ConfigError`, one line per problem; pydantic's errors are translated
into them with JSON-key paths."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import SecretStr, ValidationError


class _NoValue:
    def __repr__(self) -> str:
        return "<no value>"


NO_VALUE: Any = _NoValue()


@dataclass(frozen=True, slots=True)
class Problem:
    """One configuration problem: where (``communication.baudRate``), what, why."""

    path: str
    value: Any
    message: str

    def __str__(self) -> str:
        where = self.path or "<root>"
        if self.value is NO_VALUE:
            return f"{where}: {self.message}"
        return f"{where} {_show(self.value)}: {self.message}"


def _show(value: Any) -> str:
    """The value as given; a long text, list or object is cut (the path says where it
    is); a secret masked."""
    if isinstance(value, SecretStr):
        return repr(str(value))
    if isinstance(value, str) and len(value) > _TEXT_MAX:
        # untrusted text: a 10 MB value is not echoed into every line that names it
        return f"{value[:_TEXT_MAX - 40]!r}... ({len(value):,} characters)"
    text = repr(value[:_SHOW_MAX] if isinstance(value, (bytes, bytearray)) else value)
    if _is_scalar(value) or len(text) <= _SHOW_MAX:
        return text
    return text[: _SHOW_MAX - 3] + "..."


_SHOW_MAX = 60
_TEXT_MAX = 200  # a text value (a path, a host) is shown up to this many characters

# pydantic's type errors -> what the field takes (the value given is shown before it)
_TYPE_MESSAGES = {
    "int_type": "must be a whole number",
    "int_parsing": "must be a whole number",
    "int_from_float": "must be a whole number",
    "int_parsing_size": "must be a whole number",
    "float_type": "must be a number",
    "float_parsing": "must be a number",
    "bool_type": "must be true or false",
    "bool_parsing": "must be true or false",
    "string_type": "must be a string",
    "dict_type": "must be an object ({...})",
    "model_type": "must be an object ({...})",
    "model_attributes_type": "must be an object ({...})",
    "list_type": "must be a list ([...])",
    "datetime_type": "must be a date and time, e.g. 2026-01-18T12:06:26Z",
    "datetime_parsing": "must be a date and time, e.g. 2026-01-18T12:06:26Z",
    "datetime_from_date_parsing": "must be a date and time, e.g. 2026-01-18T12:06:26Z",
    "missing": "required",
}


class WrongType(ValueError):
    """A value of the wrong type (a field validator's refusal; the value is shown)."""


class ConfigError(ValueError):
    """Invalid configuration; ``problems`` lists every problem found, with its path."""

    def __init__(self, problems: Sequence[Problem]) -> None:
        self.problems = list(problems)
        super().__init__("\n".join(str(p) for p in self.problems))

    @classmethod
    def from_validation_error(cls, exc: ValidationError, prefix: str = "") -> ConfigError:
        """Translate pydantic's errors into problems with JSON-key paths, each showing
        the value given and what is allowed."""
        problems: list[Problem] = []
        for err in exc.errors(include_url=False):
            path = join_path(prefix, _loc_path(err["loc"]))
            inner = (err.get("ctx") or {}).get("error")
            if isinstance(inner, ConfigError):
                problems.extend(
                    Problem(join_path(path, p.path), p.value, p.message) for p in inner.problems
                )
                continue
            kind = err["type"]
            if isinstance(inner, WrongType):
                kind = "wrong_type"  # our own type check: show the value, list or not
            message = _TYPE_MESSAGES.get(kind)
            if message is None:
                message = err["msg"]
                for head in ("Value error, ", "Assertion failed, "):
                    message = message.removeprefix(head)
                if message.startswith("Input should be "):
                    message = "must be " + message.removeprefix("Input should be ")
            value = err["input"]
            if kind == "missing" or (
                kind in ("value_error", "assertion_error") and isinstance(value, Mapping)
            ):
                value = NO_VALUE  # a model check's input is the whole object: noise
            problems.append(Problem(path, value, message))
        return cls(problems)


def _is_scalar(value: Any) -> bool:
    return value is None or isinstance(value, (str, int, float, bool))


def _loc_path(loc: Sequence[int | str]) -> str:
    path = ""
    for part in loc:
        path = f"{path}[{part}]" if isinstance(part, int) else join_path(path, part)
    return path


def join_path(prefix: str, rest: str) -> str:
    """``a`` + ``b`` -> ``a.b``; ``a`` + ``[3].b`` -> ``a[3].b``; empty parts vanish."""
    if not prefix:
        return rest
    if not rest:
        return prefix
    return prefix + rest if rest.startswith("[") else f"{prefix}.{rest}"
