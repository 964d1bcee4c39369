"""The base of every config model (:class:`Model`), field limits and loading.

Keys are accepted in every spelling compat.py matches (camelCase is canonical); Python
attribute names are the snake_case of the JSON keys.  Unknown keys are ignored and
logged as warnings on logger ``edgemodbus.config`` (path and key), misspelt ones refused
(keys.py); when the load fails anyway they are lines of the error instead, so that each
problem is told once (:func:`load_model`).  Files are read by jsonfile.py (size and
depth limits), strings bounded by limits.py.  :class:`Range` and :class:`Choice` limit
a field; a value outside raises :class:`ConfigError` saying what is allowed.
Secrets: secret.py.
"""

from __future__ import annotations

import codecs
import enum
import logging
import math
import os
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    GetCoreSchemaHandler,
    ValidationError,
    model_validator,
)
from pydantic.alias_generators import to_camel
from pydantic.fields import FieldInfo
from pydantic_core import (
    CoreSchema,
    core_schema,
)

from ..datatypes import DataFormat, DataFormat64
from .compat import norm_key
from .jsonfile import check_depth, parse_json, read_json_file
from .keys import UI_KEYS, collecting, log_unknown, normalize, with_unknown_keys
from .limits import length_problems
from .problems import NO_VALUE, ConfigError, Problem, WrongType, join_path
from .secret import SECRETS_CONTEXT, hide_secrets, secret_keys

# One logger for the whole package (the name the CLI and the tests listen to).
logger = logging.getLogger("edgemodbus.config")

MAX_MS = 86_400_000
"""Upper bound of every time setting (one day, in milliseconds)."""


# --------------------------------------------------------------------------- field helpers


def _field_kinds(source: Any) -> tuple[bool, bool, bool]:
    """(numeric, integer, optional) of a field's type (``int``, ``float | None`` ...)."""
    origin = typing.get_origin(source)
    args = typing.get_args(source) if origin in (typing.Union, types.UnionType) else (source,)
    kinds = [a for a in args if a is not type(None)]
    numeric = bool(kinds) and all(k in (int, float) for k in kinds)
    return numeric, numeric and int in kinds and float not in kinds, len(kinds) < len(args)


def as_number(value: Any, integer: bool, optional: bool, allowed: str) -> Any:
    """A JSON number (or numeric text) for a numeric field; anything else, true/false
    included (pydantic would take true as 1), raises ``must be <allowed>``."""
    if value is None and optional:
        return None
    number: Any = value
    if isinstance(value, str):
        text = value.strip()
        try:
            number = int(text)
        except ValueError:
            try:
                number = float(text)
            except ValueError:
                number = None
    if isinstance(number, bool) or not isinstance(number, (int, float)):
        raise WrongType(f"must be {allowed}")
    if integer and isinstance(number, float):
        if not number.is_integer():
            raise WrongType(f"must be {allowed}")
        number = int(number)
    return number


@dataclass(frozen=True, slots=True)
class Range:
    """Inclusive numeric range of a field (``hi=None``: no upper bound); ``None`` passes
    on optional fields.  Values of the wrong type are refused with the range."""

    lo: float
    hi: float | None = None

    def check(self, value: Any) -> Any:
        if value is None:
            return value
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError("must be a finite number")
        if value < self.lo or (self.hi is not None and value > self.hi):
            raise ValueError(f"must be {self.describe()}")
        return value

    def describe(self) -> str:
        lo = _num(self.lo)
        return f"{lo} or more" if self.hi is None else f"{lo}..{_num(self.hi)}"

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> CoreSchema:
        return _checked_schema(self.check, source, handler,
                               lambda integer: f"{'a whole number' if integer else 'a number'} "
                                               f"{self.describe()}")


@dataclass(frozen=True, slots=True)
class Choice:
    """The only values a field accepts."""

    values: tuple[Any, ...]

    def check(self, value: Any) -> Any:
        # 1 == True: a bool is only one of the values if it is one of them as a bool
        if value not in self.values or (
            isinstance(value, bool) and not any(v is value for v in self.values)
        ):
            raise ValueError(f"must be {self.describe()}")
        return value

    def describe(self) -> str:
        return " or ".join(repr(v) for v in self.values)

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> CoreSchema:
        return _checked_schema(self.check, source, handler, lambda _integer: self.describe())


def _checked_schema(check: Callable[[Any], Any], source: Any, handler: GetCoreSchemaHandler,
                    allowed: Callable[[bool], str]) -> CoreSchema:
    """The field's schema with ``check`` after it and, for a numeric field, a type check
    before it whose message says what is allowed (``allowed(integer)``)."""
    schema = core_schema.no_info_after_validator_function(check, handler(source))
    numeric, integer, optional = _field_kinds(source)
    if not numeric:
        return schema
    text = allowed(integer)

    def precheck(value: Any) -> Any:
        return as_number(value, integer, optional, text)

    return core_schema.no_info_before_validator_function(precheck, schema)


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else str(x)


MS_RANGE = Range(1, MAX_MS)
READ_CYCLE_RANGE = Range(0, MAX_MS)
"""readCycle: 0 = report-only (communication's and the organisation's alike)."""

Ms = Annotated[int, MS_RANGE]
OptionalMs = Annotated[int | None, MS_RANGE]


def check_encoding(value: str) -> str:
    """A text codec Python knows (the codec's rule: bytes codecs such as base64 are not
    text encodings)."""
    try:
        text = getattr(codecs.lookup(value), "_is_text_encoding", True)
    except LookupError:
        text = False
    if not text:
        raise ValueError("unknown text encoding (use a codec Python knows, e.g. utf-8, gbk)")
    return value


def lower_literal(value: Any) -> Any:
    """Text of a Literal field, stripped and lower-cased (``"RTU "`` -> ``"rtu"``)."""
    return value.strip().lower() if isinstance(value, str) else value


_E = TypeVar("_E", bound=enum.Enum)


def parse_enum_ci(enum_cls: type[_E], value: Any) -> Any:
    """Case-insensitive lookup of a str enum by value; other input passes through."""
    if isinstance(value, str) and not isinstance(value, enum_cls):
        for member in enum_cls:
            if member.value.lower() == value.strip().lower():
                return member
    return value


def parse_format(value: Any, kind: type[DataFormat | DataFormat64] = DataFormat) -> Any:
    """A DataFormat (or ``kind``) from its text (``"ABCD"``, ``"EFGHABCD"`` ...); other
    input passes through."""
    return kind.parse(value) if isinstance(value, str) else value


# --------------------------------------------------------------------------- the model


_GENERATION = 0  # config model classes defined so far (see _exempt)


class KeyRules:
    """The key rules every config model shares: keys in any spelling (case, ``_`` and
    ``-`` ignored), unknown keys logged and dropped, a misspelt key or one given twice in
    different spellings refused (keys.py), strings of bounded length (limits.py).  A
    model may set ``_where`` (the place unknown-key warnings name), ``_extra_keys``
    (keys accepted besides the fields, for its own validators) and ``_max_lengths``."""

    __slots__ = ()

    _extra_keys: ClassVar[tuple[str, ...]] = ()
    _where: ClassVar[str] = ""
    # canonical key -> most characters its text may have (others: limits.MAX_TEXT)
    _max_lengths: ClassVar[dict[str, int]] = {}
    if typing.TYPE_CHECKING:  # pydantic sets it on every model class
        model_fields: ClassVar[dict[str, FieldInfo]]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        global _GENERATION
        _GENERATION += 1  # a new section: the keys _exempt() knows are recounted
        super().__init_subclass__(**kwargs)

    @classmethod
    def key_table(cls) -> dict[str, str]:
        """Normalised key -> canonical camelCase key (fields and accepted aliases)."""
        return _key_table(cls)

    @classmethod
    def normalize_keys(
        cls, data: Mapping[Any, Any], where: str, prefix: str = ""
    ) -> dict[str, Any]:
        """Canonical keys; unknown keys are logged (``where`` names the place) and dropped.
        A key given twice in different spellings is a ConfigError (paths from ``prefix``).
        Secrets are wrapped first (secret.py)."""
        table = cls.key_table()
        out = normalize(table, hide_secrets(data, table, secret_keys(cls), prefix), where,
                        prefix, _exempt)
        problems = length_problems(out, cls._max_lengths, prefix)
        if problems:
            raise ConfigError(problems)
        return out


class Model(KeyRules, BaseModel):
    """Base of every config model: forgiving key spelling (:class:`KeyRules`), warnings
    for unknown keys, to_dict()."""

    model_config = ConfigDict(
        alias_generator=to_camel,
        extra="ignore",
        ser_json_bytes="base64",
    )

    @model_validator(mode="before")
    @classmethod
    def _accept_keys(cls, data: Any) -> Any:
        if isinstance(data, Mapping):
            return cls.normalize_keys(data, cls._where or cls.__name__)
        return data

    def to_dict(self, *, secrets: bool = False) -> dict[str, Any]:
        """camelCase, JSON-able dict; secrets masked unless ``secrets`` (then it loads
        back to an equal model: for a comparison or a file, never for showing)."""
        result: dict[str, Any] = self.model_dump(mode="json", by_alias=True,
                                                 context={SECRETS_CONTEXT: secrets})
        return result


_key_tables: dict[type, dict[str, str]] = {}


def _key_table(cls: type[KeyRules]) -> dict[str, str]:
    table = _key_tables.get(cls)
    if table is None:
        table = {norm_key(f.alias or n): f.alias or n for n, f in cls.model_fields.items()}
        table.update({norm_key(k): k for k in cls._extra_keys})
        _key_tables[cls] = table
    return table


def _exempt() -> frozenset[str]:
    """Keys never taken for a misspelling: the UI's, and every config section's own
    (a key of another section put here is no typo of this one: the device file's
    sections always, the gateway file's once it is imported).  Recounted when a model
    class is added."""
    global _EXEMPT
    if _EXEMPT[0] != _GENERATION:
        found = set(UI_KEYS)
        todo: list[type] = [KeyRules]
        while todo:
            cls = todo.pop()
            todo += cls.__subclasses__()
            if getattr(cls, "model_fields", None):
                found.update(_key_table(cls))
        _EXEMPT = (_GENERATION, frozenset(found))
    return _EXEMPT[1]


_EXEMPT: tuple[int, frozenset[str]] = (-1, frozenset())


# --------------------------------------------------------------------------- checks again


Checks = tuple[tuple[str, str, Callable[[Any], Any]], ...]


def field_checks(model: type[BaseModel]) -> Checks:
    """(attribute, JSON key, check) of every Range/Choice-limited field of ``model``."""
    return tuple(
        (name, field.alias or name, meta.check)
        for name, field in model.model_fields.items()
        for meta in field.metadata
        if isinstance(meta, (Range, Choice))
    )


def recheck(model: object, checks: Checks, path: str) -> list[Problem]:
    """The field limits again, on the values a model holds now (models do not validate
    assignments: a value may have been changed after loading)."""
    problems: list[Problem] = []
    for name, key, check in checks:
        value = getattr(model, name)
        try:
            check(value)
        except (TypeError, ValueError) as exc:
            problems.append(Problem(join_path(path, key), value, str(exc)))
    return problems


# --------------------------------------------------------------------------- loading

_M = TypeVar("_M", bound=Model)


def _read_json(source: str | os.PathLike[str] | Mapping[str, Any],
               checked: bool = False) -> tuple[Any, str]:
    """(decoded JSON, name of the source for messages), within jsonfile.py's limits
    (``checked``: a dict that parse_json or read_json_file decoded is within them)."""
    if isinstance(source, Mapping):
        if not checked:
            check_depth(source, "<dict>")
        return dict(source), "<dict>"
    if isinstance(source, str) and source.lstrip("\ufeff \t\r\n").startswith(("{", "[")):
        return parse_json(source, "<json text>"), "<json text>"
    if isinstance(source, (str, os.PathLike)):
        return read_json_file(source), os.fspath(source)
    raise TypeError(f"config source {source!r}: use a path, a str of JSON or a dict")


def load_model(model: type[_M], source: str | os.PathLike[str] | Mapping[str, Any],
               checked: bool = False) -> _M:
    """Load ``model`` from a path, a str of JSON text, or a dict; raises ConfigError.
    Unknown keys are logged once the load succeeded, or else become lines of the
    ConfigError (one line per problem, not a warning and then an error), a bounded
    number of them and a line counting the rest (keys.py).  ``checked``: ``source`` is
    a dict decoded by config/jsonfile.py (within its limits: not walked again)."""
    data, name = _read_json(source, checked)
    if not isinstance(data, Mapping):
        raise ConfigError([Problem(name, NO_VALUE, "the file must hold a JSON object")])
    error: ConfigError | None
    with collecting() as unknown:
        try:
            loaded = model.model_validate(data)
        except ValidationError as exc:
            error = ConfigError.from_validation_error(exc)
        else:
            error = None
    if error is not None:
        raise with_unknown_keys(error, unknown) from None
    log_unknown(unknown)
    return loaded
