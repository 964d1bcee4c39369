"""Configuration models of the seed's files (device file, ``modbusRtu.json``).

Keys are accepted in camelCase (device file), PascalCase (``modbusRtu.json``) and
snake_case: matching ignores case and underscores.  Python attribute names are the
snake_case of the JSON keys.  Unknown keys are ignored and logged as warnings on logger
``edgemodbus.config`` (path and key); when the load fails anyway they are lines of the
error instead, so that each problem is told once.  Invalid input raises
:class:`ConfigError`, one line per problem: path, value given and what is allowed.

Limits are those of the layers that use the values (one source of truth): item
quantities and block sizes come from the codec and the planner, offsets and bits from
the address parser, and :func:`validate_items` runs the codec's own item check.

Parity is stored as :class:`Parity` (a str enum of libmodbus's ``"N"``, ``"O"``,
``"E"``); ``"None"/"Odd"/"Even"``, ``0/1/2`` and ``N/O/E`` are accepted.
"""

from __future__ import annotations

import codecs
import difflib
import enum
import json
import logging
import math
import os
import re
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from contextvars import ContextVar
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    GetCoreSchemaHandler,
    ValidationError,
    field_serializer,
    field_validator,
    model_validator,
)
from pydantic.alias_generators import to_camel
from pydantic_core import CoreSchema, core_schema

from .address import MAX_OFFSET, Address, check_span, parse_address
from .codec import MAX_QUANTITY, ValueSpec, check_spec
from .datatypes import Area, DataFormat, DataType, ItemStatus
from .planner import BIT_CAP, REGISTER_CAP

logger = logging.getLogger("edgemodbus.config")

MAX_MS = 86_400_000
"""Upper bound of every time setting (one day, in milliseconds)."""

Transport = Literal["rtu-over-tcp-server", "rtu", "rtu-over-tcp", "tcp"]
Framing = Literal["rtu", "wrapped-report"]
Registration = Literal["none", "text", "hex", "regex"]
AddressPrefixOption = Literal["function-code", "modicon"]
ReportMode = Literal["change", "cycle"]
Rs485Mode = Literal["none", "kernel", "rts-up", "rts-down"]


# --------------------------------------------------------------------------- errors


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
    """The value as given; a long list or object is cut (the path says where it is)."""
    text = repr(value)
    if _is_scalar(value) or len(text) <= _SHOW_MAX:
        return text
    return text[: _SHOW_MAX - 3] + "..."


_SHOW_MAX = 60

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


# Unknown keys met while a load is under way (None: log them at once, see load_model).
_unknown_keys: ContextVar[list[Problem] | None] = ContextVar("edgemodbus_unknown_keys",
                                                             default=None)


def _unknown_key(where: str, key: Any) -> None:
    problem = Problem(where, NO_VALUE, f"unknown key {key!r} ignored")
    sink = _unknown_keys.get()
    if sink is None:
        logger.warning("%s", problem)
    else:
        sink.append(problem)


def _with_unknown_keys(error: ConfigError, unknown: Sequence[Problem]) -> ConfigError:
    """The error's problems plus the unknown keys: a key that looks like a misspelling
    of a field the error says is missing joins that line; the others get a line each."""
    problems = list(error.problems)
    for extra in unknown:
        key = extra.message.removeprefix("unknown key ").removesuffix(" ignored")
        for i, problem in enumerate(problems):
            parent, _, field = problem.path.rpartition(".")
            if (
                problem.value is NO_VALUE
                and parent == extra.path
                and difflib.get_close_matches(_norm_key(key.strip("'\"")), [_norm_key(field)],
                                              cutoff=0.5)
            ):
                problems[i] = Problem(problem.path, NO_VALUE,
                                      f"{problem.message} (the unknown key {key} was ignored)")
                break
        else:
            problems.append(extra)
    return ConfigError(problems)


# --------------------------------------------------------------------------- field helpers


def _field_kinds(source: Any) -> tuple[bool, bool, bool]:
    """(numeric, integer, optional) of a field's type (``int``, ``float | None`` ...)."""
    origin = typing.get_origin(source)
    args = typing.get_args(source) if origin in (typing.Union, types.UnionType) else (source,)
    kinds = [a for a in args if a is not type(None)]
    numeric = bool(kinds) and all(k in (int, float) for k in kinds)
    return numeric, numeric and int in kinds and float not in kinds, len(kinds) < len(args)


def _number(value: Any, integer: bool, optional: bool, allowed: str) -> Any:
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
        schema = core_schema.no_info_after_validator_function(self.check, handler(source))
        numeric, integer, optional = _field_kinds(source)
        if not numeric:
            return schema
        allowed = f"{'a whole number' if integer else 'a number'} {self.describe()}"

        def precheck(value: Any) -> Any:
            return _number(value, integer, optional, allowed)

        return core_schema.no_info_before_validator_function(precheck, schema)


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
        schema = core_schema.no_info_after_validator_function(self.check, handler(source))
        numeric, integer, optional = _field_kinds(source)
        if not numeric:
            return schema
        allowed = self.describe()

        def precheck(value: Any) -> Any:
            return _number(value, integer, optional, allowed)

        return core_schema.no_info_before_validator_function(precheck, schema)


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else str(x)


MS_RANGE = Range(1, MAX_MS)
READ_CYCLE_RANGE = Range(0, MAX_MS)
"""readCycle: 0 = report-only (communication's and the organisation's alike)."""

Ms = Annotated[int, MS_RANGE]
OptionalMs = Annotated[int | None, MS_RANGE]


def _check_encoding(value: str) -> str:
    """A text codec Python knows (the codec's rule: bytes codecs such as base64 are not
    text encodings)."""
    try:
        text = getattr(codecs.lookup(value), "_is_text_encoding", True)
    except LookupError:
        text = False
    if not text:
        raise ValueError("unknown text encoding (use a codec Python knows, e.g. utf-8, gbk)")
    return value


def _lower_literal(value: Any) -> Any:
    return value.strip().lower() if isinstance(value, str) else value


def _timestamp(value: Any) -> Any:
    """Cut ISO 8601 fractions to 6 digits (.NET writes 7: ...58.9644719Z)."""
    if isinstance(value, str) and "." in value:
        head, _, tail = value.partition(".")
        digits = len(tail) - len(tail.lstrip("0123456789"))
        if digits > 6:
            value = f"{head}.{tail[:6]}{tail[digits:]}"
    return value


# --------------------------------------------------------------------------- key handling


def _norm_key(key: str) -> str:
    return key.replace("_", "").replace("-", "").lower()


class Model(BaseModel):
    """Base of every config model: forgiving key spelling, warnings for unknown keys,
    to_dict().  A subclass may set ``_where`` (the place unknown-key warnings name) and
    ``_extra_keys`` (keys accepted besides the fields, for its own validators)."""

    model_config = ConfigDict(
        alias_generator=to_camel,
        extra="ignore",
        ser_json_bytes="base64",
    )

    _extra_keys: ClassVar[tuple[str, ...]] = ()
    _where: ClassVar[str] = ""
    _key_tables: ClassVar[dict[type, dict[str, str]]] = {}

    @classmethod
    def key_table(cls) -> dict[str, str]:
        """Normalised key -> canonical camelCase key (fields and accepted aliases)."""
        table = Model._key_tables.get(cls)
        if table is None:
            table = {_norm_key(f.alias or n): f.alias or n for n, f in cls.model_fields.items()}
            table.update({_norm_key(k): k for k in cls._extra_keys})
            Model._key_tables[cls] = table
        return table

    @classmethod
    def normalize_keys(
        cls, data: Mapping[Any, Any], where: str, prefix: str = ""
    ) -> dict[str, Any]:
        """Canonical keys; unknown keys are logged (``where`` names the place) and dropped.
        A key given twice in different spellings is a ConfigError (paths from ``prefix``)."""
        table = cls.key_table()
        out: dict[str, Any] = {}
        spelled: dict[str, str] = {}
        problems: list[Problem] = []
        for key, value in data.items():
            canon = table.get(_norm_key(key)) if isinstance(key, str) else None
            if canon is None:
                _unknown_key(where, key)
                continue
            if canon in out:
                problems.append(
                    Problem(
                        join_path(prefix, canon), value, f"given twice (also as {spelled[canon]!r})"
                    )
                )
                continue
            out[canon] = value
            spelled[canon] = key
        if problems:
            raise ConfigError(problems)
        return out

    @model_validator(mode="before")
    @classmethod
    def _accept_keys(cls, data: Any) -> Any:
        if isinstance(data, Mapping):
            return cls.normalize_keys(data, cls._where or cls.__name__)
        return data

    def to_dict(self) -> dict[str, Any]:
        """camelCase, JSON-able dict (loads back to an equal model)."""
        result: dict[str, Any] = self.model_dump(mode="json", by_alias=True)
        return result


# --------------------------------------------------------------------------- enums


class Parity(str, enum.Enum):
    """Serial parity, as libmodbus spells it."""

    NONE = "N"
    ODD = "O"
    EVEN = "E"

    @classmethod
    def parse(cls, value: Any) -> Parity:
        if isinstance(value, Parity):
            return value
        if isinstance(value, int) and not isinstance(value, bool):
            found = _PARITY_NUMBERS.get(value)
        elif isinstance(value, str):
            found = _PARITY_NAMES.get(value.strip().lower())
        else:
            found = None
        if found is None:
            raise WrongType("use None|Odd|Even, 0|1|2 or N|O|E")
        return found

    @property
    def number(self) -> int:
        """The seed descriptor's numbering: 0 = None, 1 = Odd, 2 = Even."""
        return {Parity.NONE: 0, Parity.ODD: 1, Parity.EVEN: 2}[self]


_PARITY_NUMBERS = {0: Parity.NONE, 1: Parity.ODD, 2: Parity.EVEN}
_PARITY_NAMES = {
    "none": Parity.NONE,
    "n": Parity.NONE,
    "0": Parity.NONE,
    "odd": Parity.ODD,
    "o": Parity.ODD,
    "1": Parity.ODD,
    "even": Parity.EVEN,
    "e": Parity.EVEN,
    "2": Parity.EVEN,
}


_E = TypeVar("_E", bound=enum.Enum)


def _parse_enum_ci(enum_cls: type[_E], value: Any) -> Any:
    """Case-insensitive lookup of a str enum by value; other input passes through."""
    if isinstance(value, str) and not isinstance(value, enum_cls):
        for member in enum_cls:
            if member.value.lower() == value.strip().lower():
                return member
    return value


def _parse_format(value: Any) -> Any:
    if isinstance(value, str):
        return DataFormat.parse(value)
    return value


# --------------------------------------------------------------------------- communication


BAUD_RATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
"""Baud rates offered by the descriptor (any 1200..921600 is accepted)."""


def _ui(
    label: str,
    category: str,
    control: str,
    *,
    type_: str | None = None,
    options: list[Any] | None = None,
    data_source: str | None = None,
    serial: bool = False,
    tcp: bool = False,
) -> dict[str, Any]:
    """Descriptor metadata of one parameter (see descriptor.py)."""
    ui: dict[str, Any] = {"label": label, "category": category, "controlType": control}
    if type_ is not None:
        ui["type"] = type_
    if options is not None:
        ui["options"] = options
    if data_source is not None:
        ui["dataSource"] = data_source
    if serial or tcp:
        ui["visibleWhen"] = {"useTcp": tcp}
    return ui


class DriverModbusRtuParameter(Model):
    """Communication parameters (the seed's ``modbusRtu.json`` plus ours).

    Times are int milliseconds.  ``transport`` defaults from ``useTcp`` (true ->
    ``rtu-over-tcp``); NG's ``maxGap``, ``maxBatch`` and ``byteOrder``/``wordOrder`` are
    accepted for ``maxMergeAddressGap``, ``maxBlockReadRegisterCount`` and ``dataFormat``.
    """

    _extra_keys: ClassVar[tuple[str, ...]] = ("maxGap", "maxBatch", "byteOrder", "wordOrder")
    _where: ClassVar[str] = "communication"

    # Field order is the descriptor's order; json_schema_extra holds the descriptor's
    # UI metadata (label, category, controlType, options, visibleWhen, dataSource).
    com_port: str = Field(
        default="COM1",
        description="Serial COM port (e.g. COM1, /dev/ttyUSB0)",
        json_schema_extra=_ui(
            "串口号", "Connection", "dynamic-select", data_source="system:serial-ports", serial=True
        ),
    )
    baud_rate: Annotated[int, Range(1200, 921600)] = Field(
        default=9600,
        description="Baud rate of the serial line",
        json_schema_extra=_ui(
            "波特率", "Connection", "select", options=list(BAUD_RATES), serial=True
        ),
    )
    parity: Parity = Field(
        default=Parity.NONE,
        description="Parity setting (0=None, 1=Odd, 2=Even; also None/Odd/Even or N/O/E)",
        json_schema_extra=_ui(
            "校验位",
            "Connection",
            "select",
            type_="int",
            options=[
                {"label": "None", "value": 0},
                {"label": "Odd", "value": 1},
                {"label": "Even", "value": 2},
            ],
            serial=True,
        ),
    )
    data_bits: Annotated[int, Range(5, 8)] = Field(
        default=8,
        description="Number of data bits",
        json_schema_extra=_ui("数据位", "Connection", "select", options=[5, 6, 7, 8], serial=True),
    )
    stop_bits: Annotated[int, Choice((1, 2))] = Field(
        default=1,
        description="Number of stop bits",
        json_schema_extra=_ui(
            "停止位",
            "Connection",
            "select",
            options=[{"label": "1", "value": 1}, {"label": "2", "value": 2}],
            serial=True,
        ),
    )
    slave_id: Annotated[int, Range(0, 255)] = Field(
        default=1,
        description="Modbus slave id of the device: 1..247 on RTU lines (rtu, rtu-over-tcp), "
        "0..255 as a Modbus TCP unit id",
        json_schema_extra=_ui("站号", "Connection", "number"),
    )
    use_tcp: bool = Field(
        default=False,
        description="If true, use a TCP link (RTU frames over TCP unless transport says tcp) "
        "instead of a serial port",
        json_schema_extra=_ui("使用TCP透传", "Connection", "switch"),
    )
    tcp_host: str = Field(
        default="127.0.0.1",
        description="TCP host for RTU-over-TCP or Modbus TCP",
        json_schema_extra=_ui("TCP主机", "Connection", "text", tcp=True),
    )
    tcp_port: Annotated[int, Range(1, 65535)] = Field(
        default=502,
        description="TCP port for RTU-over-TCP or Modbus TCP",
        json_schema_extra=_ui("TCP端口", "Connection", "number", tcp=True),
    )
    transport: Transport = Field(
        default="rtu",
        description="rtu: serial RTU; rtu-over-tcp: raw RTU frames over TCP (DTU, serial "
        "server); tcp: Modbus TCP (MBAP); rtu-over-tcp-server: listen for DTUs that dial "
        "in (RTU frames over TCP). When absent: rtu-over-tcp if useTcp, else rtu",
        json_schema_extra=_ui("传输方式", "Connection", "select"),
    )
    listen_host: str = Field(
        default="0.0.0.0",
        description="rtu-over-tcp-server: address to listen on for DTUs",
        json_schema_extra=_ui("监听地址", "Connection", "text", tcp=True),
    )
    listen_port: Annotated[int | None, Range(1, 65535)] = Field(
        default=None,
        description="rtu-over-tcp-server: port to listen on (empty = tcpPort); devices "
        "naming one port share its listener",
        json_schema_extra=_ui("监听端口", "Connection", "number", tcp=True),
    )
    dtu_id: str = Field(
        default="",
        description="rtu-over-tcp-server: the registration id of the DTU this device is "
        "behind (text, hex bytes, or what registrationPattern extracts); empty only "
        "with registration none",
        json_schema_extra=_ui("DTU注册包ID", "Connection", "text", tcp=True),
    )
    registration: Registration = Field(
        default="none",
        description="rtu-over-tcp-server: how DTUs identify themselves: none (the port's "
        "only DTU takes the connection), text (the first packet is dtuId), hex (the first "
        "packet is the bytes dtuId spells in hex), regex (registrationPattern's first "
        "group, else its whole match, is the id)",
        json_schema_extra=_ui("注册包方式", "Connection", "select", tcp=True),
    )
    registration_pattern: str = Field(
        default="",
        description="rtu-over-tcp-server with registration regex: a regular expression "
        "searched in the registration packet (Latin-1 text)",
        json_schema_extra=_ui("注册包正则", "Connection", "text", tcp=True),
    )
    registration_length: Annotated[int | None, Range(1, 1024)] = Field(
        default=None,
        description="rtu-over-tcp-server: fixed length of the registration packet in bytes "
        "(empty = as sent)",
        json_schema_extra=_ui("注册包长度", "Connection", "number", tcp=True),
    )
    registration_timeout: Annotated[int, Range(1, MAX_MS)] = Field(
        default=5000,
        description="rtu-over-tcp-server: a DTU that has not registered within this time "
        "is logged and closed (ms)",
        json_schema_extra=_ui("注册超时(ms)", "Connection", "number", tcp=True),
    )
    heartbeat: str = Field(
        default="",
        description="Heartbeat packet DTUs send on idle links, as text (e.g. HB); "
        "discarded wherever it arrives and counted",
        json_schema_extra=_ui("心跳包", "Connection", "text", tcp=True),
    )
    heartbeat_hex: str = Field(
        default="",
        description="Heartbeat packet as hex bytes (e.g. FE); instead of heartbeat",
        json_schema_extra=_ui("心跳包(HEX)", "Connection", "text", tcp=True),
    )
    framing: Framing = Field(
        default="rtu",
        description="rtu: plain RTU frames; wrapped-report: edge-MCU frames "
        "FF AA + register address + RTU frame + 0D, with unsolicited reports "
        "(RTU over TCP, client or listen mode)",
        json_schema_extra=_ui("报文封装", "Connection", "select", tcp=True),
    )
    connect_timeout: Ms = Field(
        default=3000,
        description="Timeout of a TCP connect (ms)",
        json_schema_extra=_ui("连接超时(ms)", "Connection", "number", tcp=True),
    )
    reconnect_interval: Ms = Field(
        default=5000,
        description="Wait before reopening a lost link (ms)",
        json_schema_extra=_ui("重连间隔(ms)", "Connection", "number"),
    )
    read_timeout: Ms = Field(
        default=1000,
        description="Response timeout of one request (ms)",
        json_schema_extra=_ui("读超时(ms)", "Connection", "number"),
    )
    byte_timeout: Ms = Field(
        default=200,
        description="Timeout between two bytes of one reply (ms)",
        json_schema_extra=_ui("字节间超时(ms)", "Connection", "number"),
    )
    read_cycle: Annotated[int, READ_CYCLE_RANGE] = Field(
        default=1000,
        description="Polling cycle (ms); 0 = no polling: report-only (framing "
        "wrapped-report; on other framings nothing would update, which is logged)",
        json_schema_extra=_ui("读取周期(ms)", "Connection", "number"),
    )
    rs485: Rs485Mode = Field(
        default="none",
        description="RS-485 direction control: none, kernel (TIOCSRS485), rts-up, rts-down",
        json_schema_extra=_ui("RS-485 方向控制", "Connection", "select", serial=True),
    )
    echo: bool = Field(
        default=False,
        description="The line echoes our own requests (some 2-wire adapters): skip the echo",
        json_schema_extra=_ui("线路回显", "Connection", "switch"),
    )
    is_enable: bool = Field(
        default=True,
        description="Poll this device",
        json_schema_extra=_ui("启用", "Connection", "switch"),
    )
    data_format: DataFormat = Field(
        default=DataFormat.ABCD,
        description="Default data format for communication (byte order x word order)",
        json_schema_extra=_ui("数据格式", "Advanced", "select", type_="string"),
    )
    max_block_read_register_count: Annotated[int, Range(1, REGISTER_CAP)] = Field(
        default=120,
        description="Maximum number of registers to read in a single block",
        json_schema_extra=_ui("单块最大寄存器数", "Advanced", "number"),
    )
    is_block_read_require_address_continuous: bool = Field(
        default=False,
        description="Indicates if block read requires continuous addresses (gap 0)",
        json_schema_extra=_ui("块读取地址需连续", "Advanced", "switch"),
    )
    max_merge_address_gap: Annotated[int, Range(0, MAX_OFFSET)] = Field(
        default=10,
        description="Maximum merge address gap when combining non-contiguous blocks",
        json_schema_extra=_ui("最大合并空洞", "Advanced", "number"),
    )
    max_block_read_bit_count: Annotated[int, Range(1, BIT_CAP)] = Field(
        default=BIT_CAP,
        description="Maximum number of coils/discrete inputs to read in a single block",
        json_schema_extra=_ui("单块最大位数", "Advanced", "number"),
    )
    address_prefix: AddressPrefixOption = Field(
        default="function-code",
        description="Numeric address types: function-code (3=holding, 4=input) or modicon "
        "(3=input, 4=holding)",
        json_schema_extra=_ui("地址类型编号", "Advanced", "select"),
    )
    address_base: Annotated[int, Choice((0, 1))] = Field(
        default=0,
        description="0: address offsets are protocol (0-based) addresses; 1: they are 1-based",
        json_schema_extra=_ui("地址起始", "Advanced", "select"),
    )
    retries: Annotated[int, Range(0, 10)] = Field(
        default=1,
        description="Retries of a failed read before its items go Invalid",
        json_schema_extra=_ui("重试次数", "Advanced", "number"),
    )
    request_interval: Annotated[int, Range(0, MAX_MS)] = Field(
        default=0,
        description="Silence kept between two requests on the line (ms)",
        json_schema_extra=_ui("请求间隔(ms)", "Advanced", "number"),
    )
    settle_timeout: Annotated[int | None, Range(0, MAX_MS)] = Field(
        default=None,
        description="After a timeout, discard late replies for this long before the next "
        "request (ms); empty = readTimeout, 0 = off",
        json_schema_extra=_ui("超时后静默(ms)", "Advanced", "number"),
    )
    offline_after_failed_cycles: Annotated[int, Range(1, 1000)] = Field(
        default=3,
        description="Failed cycles in a row before the device is reported Offline",
        json_schema_extra=_ui("离线判定周期数", "Advanced", "number"),
    )
    max_backoff: Ms = Field(
        default=60000,
        description="Longest wait between attempts on an offline device or lost link (ms)",
        json_schema_extra=_ui("最大退避(ms)", "Advanced", "number"),
    )
    report_mode: ReportMode = Field(
        default="change",
        description="change: report items whose value or status changed; cycle: every read",
        json_schema_extra=_ui("上报方式", "Advanced", "select"),
    )
    encoding: str = Field(
        default="utf-8",
        description="Text encoding of String items (a Python codec, e.g. utf-8, gbk)",
        json_schema_extra=_ui("字符串编码", "Advanced", "text"),
    )
    write_single_register_function: Annotated[int, Choice((6, 16))] = Field(
        default=6,
        description="Function code for writing a one-register value: 6 or 16",
        json_schema_extra=_ui("单寄存器写功能码", "Advanced", "select"),
    )
    snapshot_interval: Annotated[int, Range(0, MAX_MS)] = Field(
        default=0,
        description="Publish a device snapshot this often (ms); 0 = off",
        json_schema_extra=_ui("快照间隔(ms)", "Advanced", "number"),
    )

    @field_validator("parity", mode="before")
    @classmethod
    def _parity(cls, value: Any) -> Parity:
        return Parity.parse(value)

    @field_validator("data_format", mode="before")
    @classmethod
    def _format(cls, value: Any) -> Any:
        return _parse_format(value)

    @field_validator("transport", "address_prefix", "report_mode", "rs485", "framing",
                     "registration", mode="before")
    @classmethod
    def _lower(cls, value: Any) -> Any:
        return _lower_literal(value)

    @field_validator("encoding")
    @classmethod
    def _encoding(cls, value: str) -> str:
        return _check_encoding(value)

    @model_validator(mode="before")
    @classmethod
    def _ng_aliases(cls, data: Any) -> Any:
        """NG spellings -> ours (after key normalisation); disagreements are errors."""
        if not isinstance(data, Mapping):
            return data
        data = cls.normalize_keys(data, cls._where)
        problems: list[Problem] = []
        for ng, ours in (
            ("maxGap", "maxMergeAddressGap"),
            ("maxBatch", "maxBlockReadRegisterCount"),
        ):
            if ng in data:
                value = data.pop(ng)
                if ours in data and data[ours] != value:
                    problems.append(Problem(ng, value, f"disagrees with {ours} {data[ours]!r}"))
                else:
                    data[ours] = value
        if "byteOrder" in data or "wordOrder" in data:
            byte_order = data.pop("byteOrder", "BigEndian")
            word_order = data.pop("wordOrder", "BigEndian")
            try:
                fmt = DataFormat.from_orders(str(byte_order), str(word_order))
            except ValueError as exc:
                problems.append(Problem("byteOrder/wordOrder", NO_VALUE, str(exc)))
            else:
                given = data.get("dataFormat")
                if given is not None and _parse_format_or_none(given) is not fmt:
                    problems.append(
                        Problem(
                            "dataFormat", given, f"disagrees with byteOrder/wordOrder ({fmt.value})"
                        )
                    )
                data["dataFormat"] = fmt
        if problems:
            raise ConfigError(problems)
        return data

    @model_validator(mode="after")
    def _cross_checks(self) -> DriverModbusRtuParameter:
        problems: list[Problem] = []
        fields_set = self.model_fields_set
        if "transport" not in fields_set:
            self.transport = "rtu-over-tcp" if self.use_tcp else "rtu"
        elif "use_tcp" not in fields_set:
            self.use_tcp = self.transport != "rtu"
        elif self.use_tcp != (self.transport != "rtu"):
            problems.append(
                Problem("useTcp", self.use_tcp, f"contradicts transport {self.transport!r}")
            )
        if self.transport == "tcp":
            pass  # a Modbus TCP unit id may be 0..255
        elif not 1 <= self.slave_id <= 247:
            problems.append(
                Problem(
                    "slaveId",
                    self.slave_id,
                    f"must be 1..247 on an RTU line (transport {self.transport!r}); "
                    "0..255 only as a Modbus TCP unit id",
                )
            )
        if self.transport == "rtu" and not self.com_port.strip():
            problems.append(Problem("comPort", self.com_port, "a serial port is required"))
        if self.transport in ("rtu-over-tcp", "tcp") and not self.tcp_host.strip():
            problems.append(Problem("tcpHost", self.tcp_host, "a host is required"))
        problems += self._dtu_checks()
        if problems:
            raise ConfigError(problems)
        return self

    def _dtu_checks(self) -> list[Problem]:
        """Listen mode, registration, heartbeat and framing options."""
        problems: list[Problem] = []
        server = self.transport == "rtu-over-tcp-server"
        if server:
            if not self.listen_host.strip():
                problems.append(Problem("listenHost", self.listen_host, "a host is required"))
            if self.registration != "none" and not self.dtu_id:
                problems.append(Problem("dtuId", self.dtu_id, f"required with registration "
                                        f"{self.registration!r}"))
            if self.registration == "hex":
                try:
                    if not bytes.fromhex(self.dtu_id):
                        raise ValueError
                except ValueError:
                    problems.append(Problem("dtuId", self.dtu_id, "registration hex needs hex "
                                            "bytes, e.g. '38 36 31 30'"))
            if self.registration == "regex":
                try:
                    re.compile(self.registration_pattern)
                    if not self.registration_pattern:
                        raise re.error("empty pattern")
                except re.error as exc:
                    problems.append(Problem("registrationPattern", self.registration_pattern,
                                            f"not a regular expression: {exc}"))
        if self.heartbeat and self.heartbeat_hex:
            problems.append(Problem("heartbeatHex", self.heartbeat_hex,
                                    "give heartbeat (text) or heartbeatHex, not both"))
        if self.heartbeat_hex:
            try:
                if not bytes.fromhex(self.heartbeat_hex):
                    raise ValueError
            except ValueError:
                problems.append(Problem("heartbeatHex", self.heartbeat_hex,
                                        "must be hex bytes, e.g. 'FE'"))
        if (self.heartbeat or self.heartbeat_hex) and self.transport not in (
            "rtu-over-tcp", "rtu-over-tcp-server"
        ):
            problems.append(Problem("heartbeat", self.heartbeat or self.heartbeat_hex,
                                    "heartbeats apply to RTU over TCP (rtu-over-tcp, "
                                    "rtu-over-tcp-server)"))
        if self.framing == "wrapped-report" and self.transport not in (
            "rtu-over-tcp", "rtu-over-tcp-server"
        ):
            problems.append(Problem("framing", self.framing, "needs transport rtu-over-tcp or "
                                    f"rtu-over-tcp-server, not {self.transport!r}"))
        if self.framing == "wrapped-report" and self.echo:
            problems.append(Problem("echo", self.echo, "no echo option with framing "
                                    "wrapped-report"))
        if self.echo and self.transport == "tcp":
            problems.append(Problem("echo", self.echo, "a Modbus TCP (MBAP) link has no "
                                    "request echo; the option is for RTU lines"))
        return problems

    @property
    def heartbeat_bytes(self) -> bytes:
        """The heartbeat packet as bytes (empty: none configured)."""
        if self.heartbeat_hex:
            return bytes.fromhex(self.heartbeat_hex)
        return self.heartbeat.encode("latin-1", "replace")

    @property
    def effective_listen_port(self) -> int:
        """listenPort, else tcpPort (the issue accepts tcpPort as the listen port)."""
        return self.listen_port if self.listen_port is not None else self.tcp_port

    @field_serializer("parity")
    def _ser_parity(self, value: Parity) -> str:
        return value.value

    @property
    def effective_settle_timeout(self) -> int:
        """Settle time in ms: ``settleTimeout``, or ``readTimeout`` when unset."""
        return self.read_timeout if self.settle_timeout is None else self.settle_timeout


def _parse_format_or_none(value: Any) -> DataFormat | None:
    try:
        return DataFormat.parse(value) if isinstance(value, str) else value
    except ValueError:
        return None


# --------------------------------------------------------------------------- organization


class DeviceOrganizationParameter(Model):
    """The device's organisation record; its timing fields override communication's."""

    _where: ClassVar[str] = "organization"

    device_id: str | None = None
    device_code: str | None = None
    device_name: str | None = None
    description: str | None = None
    is_enable: bool | None = None
    # the same ranges and meaning as communication's fields they override
    connect_timeout: OptionalMs = None
    reconnect_interval: OptionalMs = None
    read_cycle: Annotated[int | None, READ_CYCLE_RANGE] = None
    created_at: datetime | None = None
    last_modified: datetime | None = None
    metadata: dict[str, Any] = Field(default_factory=dict)

    @field_validator("created_at", "last_modified", mode="before")
    @classmethod
    def _ts(cls, value: Any) -> Any:
        return _timestamp(value)


_OVERRIDES = ("read_cycle", "connect_timeout", "reconnect_interval")


def effective_parameters(
    org: DeviceOrganizationParameter | None, comm: DriverModbusRtuParameter
) -> DriverModbusRtuParameter:
    """A copy of ``comm`` with the organisation's readCycle/connectTimeout/
    reconnectInterval applied where set."""
    update = (
        {}
        if org is None
        else {name: getattr(org, name) for name in _OVERRIDES if getattr(org, name) is not None}
    )
    return comm.model_copy(update=update)


def device_enabled(org: DeviceOrganizationParameter | None, comm: DriverModbusRtuParameter) -> bool:
    """A device is polled when the organisation (if it says) and communication enable it."""
    org_ok = org is None or org.is_enable is None or org.is_enable
    return bool(org_ok and comm.is_enable)


# --------------------------------------------------------------------------- items


class DeviceAddressItem(Model):
    """One tag.  ``value``, ``status``, ``update_ts`` and ``error_reason`` are runtime
    state set by the driver's worker thread: assignment is not validated (cheap)."""

    _where: ClassVar[str] = "addressList[]"

    name: str
    address: str
    device_data_type: DataType
    converted_data_type: DataType | None = None
    data_multiplier: float = 1.0
    description: str = ""
    unit: str = ""
    update_ts: datetime | None = None
    status: ItemStatus = ItemStatus.UNKNOWN
    is_enable: bool = True
    address_changed: bool = False
    data_format: DataFormat | None = None
    quantity: Annotated[int | None, Range(1, MAX_QUANTITY)] = None
    deadband: Annotated[float | None, Range(0)] = None
    encoding: str | None = None
    value: Any = None
    error_reason: str | None = None

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("an item needs a non-empty name")
        return value

    @field_validator("address", mode="before")
    @classmethod
    def _address_text(cls, value: Any) -> Any:
        """A JSON number is the offset it spells (100 means "100", i.e. hr:100)."""
        if isinstance(value, int) and not isinstance(value, bool):
            return str(value)
        if not isinstance(value, str):
            raise WrongType("must be a string like 'hr:100' (or a whole number: an offset)")
        return value

    @field_validator("data_multiplier", mode="before")
    @classmethod
    def _multiplier_number(cls, value: Any) -> Any:
        return _number(value, False, False, "a finite number other than 0")

    @field_validator("address")
    @classmethod
    def _address(cls, value: str) -> str:
        # Syntax only: prefix/base live in communication (checked by validate_items).
        try:
            parse_address(value)
        except ValueError as exc:
            try:
                parse_address(value, base=1)
            except ValueError:
                raise ValueError(_strip_echo(value, exc)) from None
        return value

    @field_validator("device_data_type", mode="before")
    @classmethod
    def _device_type(cls, value: Any) -> Any:
        return DataType.parse(value) if isinstance(value, str) else value

    @field_validator("converted_data_type", mode="before")
    @classmethod
    def _converted_type(cls, value: Any) -> Any:
        if value is None or (isinstance(value, str) and not value.strip()):
            return None
        return DataType.parse(value) if isinstance(value, str) else value

    @field_validator("data_format", mode="before")
    @classmethod
    def _format(cls, value: Any) -> Any:
        if isinstance(value, str) and not value.strip():
            return None
        return _parse_format(value)

    @field_validator("status", mode="before")
    @classmethod
    def _status(cls, value: Any) -> Any:
        return _parse_enum_ci(ItemStatus, value)

    @field_validator("data_multiplier")
    @classmethod
    def _multiplier(cls, value: float) -> float:
        if not math.isfinite(value) or value == 0:
            raise ValueError("must be a finite number other than 0")
        return value

    @field_validator("encoding")
    @classmethod
    def _encoding(cls, value: str | None) -> str | None:
        return None if value is None or not value.strip() else _check_encoding(value)

    @field_validator("update_ts", mode="before")
    @classmethod
    def _ts(cls, value: Any) -> Any:
        return _timestamp(value)

    @field_serializer("converted_data_type")
    def _ser_converted(self, value: DataType | None) -> str:
        return "" if value is None else value.value


def _strip_echo(text: str, exc: ValueError) -> str:
    """parse_address's message without its leading ``'text': `` (the path shows it)."""
    message = str(exc)
    return message.removeprefix(f"{text!r}: ")


ALLOWED_QUANTITIES: dict[DataType, tuple[int, ...]] = {
    DataType.BOOLEAN: (1,),
    DataType.BYTE: (1,),
    DataType.SBYTE: (1,),
    DataType.CHAR: (1,),
    DataType.INT16: (1,),
    DataType.UINT16: (1,),
    DataType.BCD16: (1,),
    DataType.INT32: (1, 2),
    DataType.UINT32: (1, 2),
    DataType.FLOAT: (1, 2),
    DataType.BCD32: (1, 2),
    DataType.INT64: (1, 2, 4),
    DataType.UINT64: (1, 2, 4),
    DataType.DOUBLE: (1, 2, 4),
    DataType.DATETIME: (2, 4),
    DataType.TIMESTAMP: (2, 4),
}
"""Register counts an item of each type may read (Smart Cast: fewer registers hold a
smaller integer that is widened).  String and Binary take any quantity >= 1."""

_AREA_NAMES = {
    Area.COIL: "coil",
    Area.DISCRETE_INPUT: "discrete input",
    Area.HOLDING_REGISTER: "holding register",
    Area.INPUT_REGISTER: "input register",
}


@dataclass(frozen=True, slots=True)
class ParsedItem:
    """An item checked against the communication options, ready for the planner/codec.

    ``registers``: registers (register areas) or bits (1) the item occupies;
    ``data_format`` and ``encoding`` are the effective ones (item's, else comm's)."""

    item: DeviceAddressItem
    address: Address
    data_type: DataType
    converted_type: DataType | None
    data_format: DataFormat
    registers: int
    quantity: int | None
    multiplier: float
    deadband: float | None
    encoding: str

    @property
    def name(self) -> str:
        return self.item.name

    def value_spec(self) -> ValueSpec:
        """The codec's spec of this item (what the driver decodes and encodes with)."""
        return ValueSpec(
            name=self.item.name,
            data_type=self.data_type,
            data_format=self.data_format,
            quantity=self.quantity,
            bit=self.address.bit,
            multiplier=self.multiplier,
            converted_type=self.converted_type,
            deadband=self.deadband or 0.0,
            encoding=self.encoding,
        )


def _item_registers(
    item: DeviceAddressItem, addr: Address, path: str, problems: list[Problem]
) -> int:
    """Registers/bits the item occupies; appends problems for type/area mismatches."""
    dtype, quantity = item.device_data_type, item.quantity
    if addr.area.is_bit or addr.bit is not None:
        where = (
            f"a {_AREA_NAMES[addr.area]} holds one bit"
            if addr.area.is_bit
            else "a bit address (.N) reads one bit"
        )
        if dtype is not DataType.BOOLEAN:
            problems.append(Problem(f"{path}.deviceDataType", dtype.value, f"{where}: use Boolean"))
        if quantity not in (None, 1):
            problems.append(
                Problem(f"{path}.quantity", quantity, f"{where}: use 1 or leave it out")
            )
        return 1
    if dtype.needs_quantity:
        if quantity is None:
            problems.append(
                Problem(
                    f"{path}.quantity",
                    NO_VALUE,
                    f"{dtype.value} needs quantity (its length in registers)",
                )
            )
            return 1
        return quantity
    if quantity is None:
        return dtype.registers
    allowed = ALLOWED_QUANTITIES[dtype]
    if quantity not in allowed:
        problems.append(
            Problem(
                f"{path}.quantity",
                quantity,
                f"{dtype.value} allows quantity {' or '.join(map(str, allowed))} (or leave it out)",
            )
        )
        return dtype.registers
    return quantity


def validate_items(
    items: Sequence[DeviceAddressItem], comm: DriverModbusRtuParameter
) -> list[ParsedItem]:
    """Check every item against ``comm`` (address prefix/base, type vs area, quantity,
    span, unique names), against its own field limits again (an item may have been
    changed after it was loaded) and against the codec's check of the spec the driver
    will build; return them parsed, in order.  Raises one ConfigError listing every
    problem with its path (``addressList[3].address`` ...)."""
    problems: list[Problem] = []
    parsed: list[ParsedItem] = []
    first_index: dict[str, int] = {}
    checked: set[tuple[Any, ...]] = set()
    for i, item in enumerate(items):
        path = f"addressList[{i}]"
        before = len(problems)
        if item.name in first_index:
            problems.append(
                Problem(
                    f"{path}.name",
                    item.name,
                    f"duplicate item name (also addressList[{first_index[item.name]}])",
                )
            )
        else:
            first_index[item.name] = i
        limits = _recheck(item, _ITEM_CHECKS, path)
        if limits:  # the checks below use these values
            problems += limits
            continue
        try:
            addr = parse_address(item.address, comm.address_prefix, comm.address_base)
        except ValueError as exc:
            problems.append(
                Problem(f"{path}.address", item.address, _strip_echo(item.address, exc))
            )
            continue
        registers = _item_registers(item, addr, path, problems)
        try:
            check_span(addr, registers)
        except ValueError as exc:
            message = str(exc).removeprefix(f"{addr}: ")
            problems.append(Problem(f"{path}.address", item.address, message))
        if len(problems) > before:
            continue
        one = ParsedItem(
            item=item,
            address=addr,
            data_type=item.device_data_type,
            converted_type=item.converted_data_type,
            data_format=item.data_format or comm.data_format,
            registers=registers,
            quantity=item.quantity,
            multiplier=item.data_multiplier,
            deadband=item.deadband,
            encoding=item.encoding or comm.encoding,
        )
        # the codec's check depends on everything but the name: check each shape once
        shape = (addr.area, addr.bit, one.data_type, one.data_format, one.quantity,
                 one.multiplier, one.converted_type, one.deadband, one.encoding)
        if shape not in checked:
            spec = one.value_spec()
            try:
                check_spec(spec, addr.area)
            except ValueError as exc:
                problems.append(_codec_problem(exc, spec, item, path))
                continue
            checked.add(shape)
        parsed.append(one)
    if problems:
        raise ConfigError(problems)
    return parsed


_Checks = tuple[tuple[str, str, Callable[[Any], Any]], ...]


def _field_checks(model: type[BaseModel]) -> _Checks:
    """(attribute, JSON key, check) of every Range/Choice-limited field of ``model``."""
    return tuple(
        (name, field.alias or name, meta.check)
        for name, field in model.model_fields.items()
        for meta in field.metadata
        if isinstance(meta, (Range, Choice))
    )


_ITEM_CHECKS = _field_checks(DeviceAddressItem)
_COMM_CHECKS = _field_checks(DriverModbusRtuParameter)
_ORG_CHECKS = _field_checks(DeviceOrganizationParameter)


def _recheck(model: BaseModel, checks: _Checks, path: str) -> list[Problem]:
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


def validate_parameters(
    org: DeviceOrganizationParameter | None, comm: DriverModbusRtuParameter
) -> None:
    """Check the organisation's and communication's field limits on the values they hold
    now; raise one ConfigError (``communication.readCycle ...``) listing every problem."""
    problems = [] if org is None else _recheck(org, _ORG_CHECKS, "organization")
    problems += _recheck(comm, _COMM_CHECKS, "communication")
    if problems:
        raise ConfigError(problems)


def _codec_problem(
    exc: ValueError, spec: ValueSpec, item: DeviceAddressItem, path: str
) -> Problem:
    """codec.check_spec's "item 'x': <field> <value> is not allowed (<why>)" as a
    Problem at the item's JSON key."""
    text = str(exc).removeprefix(f"item {spec.name!r}: ")
    fields: dict[str, tuple[str, Any]] = {
        "quantity": ("quantity", spec.quantity),
        "data type": ("deviceDataType", spec.data_type.value),
        "bit": ("address", item.address),
        "dataMultiplier": ("dataMultiplier", spec.multiplier),
        "convertedDataType": (
            "convertedDataType",
            None if spec.converted_type is None else spec.converted_type.value,
        ),
        "deadband": ("deadband", spec.deadband),
        "encoding": ("encoding", spec.encoding),
    }
    head, sep, why = text.partition(" is not allowed (")
    for field, (key, value) in fields.items():
        if sep and head.startswith(f"{field} "):
            return Problem(f"{path}.{key}", value, f"not allowed: {why.removesuffix(')')}")
    return Problem(path, NO_VALUE, text)


# --------------------------------------------------------------------------- device file


class DeviceConfig(Model):
    """A whole device file: driver type, organisation, communication, address list."""

    driver_type: str = "DriverModbusRtu"
    organization: DeviceOrganizationParameter = Field(default_factory=DeviceOrganizationParameter)
    communication: DriverModbusRtuParameter = Field(default_factory=DriverModbusRtuParameter)
    address_list: list[DeviceAddressItem] = Field(default_factory=list)

    @model_validator(mode="before")
    @classmethod
    def _nested_keys(cls, data: Any) -> Any:
        """Warn about unknown nested keys with their full paths before pydantic sees them."""
        if not isinstance(data, Mapping):
            return data
        data = cls.normalize_keys(data, "")
        for key, model in (
            ("organization", DeviceOrganizationParameter),
            ("communication", DriverModbusRtuParameter),
        ):
            if isinstance(data.get(key), Mapping):
                data[key] = model.normalize_keys(data[key], key, key)
        items = data.get("addressList")
        if isinstance(items, list):
            data["addressList"] = [
                DeviceAddressItem.normalize_keys(it, f"addressList[{i}]", f"addressList[{i}]")
                if isinstance(it, Mapping)
                else it
                for i, it in enumerate(items)
            ]
        return data

    @model_validator(mode="after")
    def _items(self) -> DeviceConfig:
        validate_items(self.address_list, self.communication)
        return self

    def parsed_items(self) -> list[ParsedItem]:
        """The address list checked and parsed against the communication options."""
        return validate_items(self.address_list, self.communication)

    def effective_parameters(self) -> DriverModbusRtuParameter:
        """Communication with the organisation's overrides applied."""
        return effective_parameters(self.organization, self.communication)

    @property
    def enabled(self) -> bool:
        return device_enabled(self.organization, self.communication)


# --------------------------------------------------------------------------- loading

_M = TypeVar("_M", bound=Model)


def _read_json(source: str | os.PathLike[str] | Mapping[str, Any]) -> tuple[Any, str]:
    """(decoded JSON, name of the source for messages)."""
    if isinstance(source, Mapping):
        return dict(source), "<dict>"
    if isinstance(source, str) and source.lstrip("\ufeff \t\r\n").startswith(("{", "[")):
        text, name = source, "<json text>"
    elif isinstance(source, (str, os.PathLike)):
        name = os.fspath(source)
        text = Path(name).read_text(encoding="utf-8-sig")
    else:
        raise TypeError(f"config source {source!r}: use a path, a str of JSON or a dict")
    try:
        return json.loads(text.lstrip("\ufeff")), name
    except json.JSONDecodeError as exc:
        raise ConfigError(
            [
                Problem(
                    name,
                    NO_VALUE,
                    f"invalid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}",
                )
            ]
        ) from None


def load_model(model: type[_M], source: str | os.PathLike[str] | Mapping[str, Any]) -> _M:
    """Load ``model`` from a path, a str of JSON text, or a dict; raises ConfigError.
    Unknown keys are logged once the load succeeded, or else become lines of the
    ConfigError (one line per problem, not a warning and then an error)."""
    data, name = _read_json(source)
    if not isinstance(data, Mapping):
        raise ConfigError([Problem(name, NO_VALUE, "the file must hold a JSON object")])
    unknown: list[Problem] = []
    error: ConfigError | None
    token = _unknown_keys.set(unknown)
    try:
        loaded = model.model_validate(data)
    except ValidationError as exc:
        error = ConfigError.from_validation_error(exc)
    else:
        error = None
    finally:
        _unknown_keys.reset(token)
    if error is not None:
        raise _with_unknown_keys(error, unknown) from None
    for problem in unknown:
        logger.warning("%s", problem)
    return loaded


def load_device_config(source: str | os.PathLike[str] | Mapping[str, Any]) -> DeviceConfig:
    """Load a device file: a path, a str of JSON text, or a dict.  Raises ConfigError."""
    return load_model(DeviceConfig, source)


def load_communication(
    source: str | os.PathLike[str] | Mapping[str, Any],
) -> DriverModbusRtuParameter:
    """Load communication parameters alone (the seed's ``modbusRtu.json``)."""
    return load_model(DriverModbusRtuParameter, source)
