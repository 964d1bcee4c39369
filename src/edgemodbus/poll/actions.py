"""Running an action (NG's ``Action``): its parameters checked and turned into the write
requests of its function code, all before anything is sent.

:func:`plan_action` raises ValueError naming the action, the parameter, the value and
what is allowed; the requests it returns are sent by the poll's
:class:`~edgemodbus.poll.writes.Writer` with ``whole=True`` (the first failure stops
the action; the result is one ok or one error for the whole action).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from concurrent.futures import Future
from typing import Any

from ..codec import normalize_value
from ..config import DeviceAction
from ..config.actions import ACTION_VALUE
from ..datatypes import DataType
from .items import ItemState
from .writes import WriteOp, merge_writes, prepare_writes

__all__ = [
    "address_values",
    "describe_parameter",
    "find_action",
    "plan_action",
    "prefix_errors",
    "resolve_parameters",
]


def find_action(actions: Sequence[DeviceAction], name: str) -> DeviceAction:
    for action in actions:
        if action.name == name:
            return action
    known = ", ".join(repr(a.name) for a in actions) or "none configured"
    raise ValueError(f"unknown action {name!r} (actions: {known})")


def describe_parameter(action: DeviceAction, name: str,
                       by_name: Mapping[str, ItemState] | None = None) -> str:
    """What a parameter takes, for messages and ``--help``-like listings."""
    param = next(p for p in action.parameters if p.name == name)
    kind = _kind(param.data_type, param.item, by_name)
    text = kind.value if kind is not None else "the item's type"
    if param.min_value is not None or param.max_value is not None:
        lo = "" if param.min_value is None else f"{param.min_value:g}"
        hi = "" if param.max_value is None else f"{param.max_value:g}"
        text += f", {lo}..{hi}"
    if param.default_value is not None:
        text += f", default {param.default_value!r}"
    elif param.is_required:
        text += ", required"
    return f"{param.name} -> {param.item} ({text})"


def _kind(declared: DataType | None, item: str,
          by_name: Mapping[str, ItemState] | None) -> DataType | None:
    if declared is not None or by_name is None or item not in by_name:
        return declared
    spec = by_name[item].spec
    if spec.converted_type is not None:
        return spec.converted_type
    if spec.multiplier != 1 and spec.data_type.is_numeric:
        # a scaled value is a float (docs/library.md, "Values as text and JSON")
        return DataType.DOUBLE
    return spec.data_type


def resolve_parameters(
    action: DeviceAction, given: Mapping[str, Any], by_name: Mapping[str, ItemState]
) -> list[tuple[str, Any]]:
    """(item, value) for every parameter of ``action``: the value given, else the
    default; each checked against the parameter's type and bounds."""
    head = f"action {action.name!r}"
    if not isinstance(given, Mapping):
        raise ValueError(f"{head}: parameters must be a mapping of names to values, "
                         f"not {type(given).__name__}")
    known = {p.name for p in action.parameters}
    unknown = [str(k) for k in given if k not in known]
    if unknown:
        raise ValueError(
            f"{head}: unknown parameter{'s' if len(unknown) > 1 else ''} "
            f"{', '.join(map(repr, unknown))} (parameters: "
            f"{'; '.join(describe_parameter(action, p.name, by_name) for p in action.parameters)})"
        )
    pairs: list[tuple[str, Any]] = []
    for param in action.parameters:
        label = f"{head}: parameter {param.name!r}"
        if param.name in given:
            value = given[param.name]
        elif param.default_value is not None:
            value = param.default_value
        elif param.is_required:
            raise ValueError(f"{label} is missing ("
                             f"{describe_parameter(action, param.name, by_name)})")
        else:
            continue  # optional, no default: the item is not written
        state = by_name.get(param.item)
        if state is None:  # validate_actions checked the file; an update may drop items
            raise ValueError(f"{label}: item {param.item!r} is not in the address list")
        kind = _kind(param.data_type, param.item, by_name)
        assert kind is not None
        checked = normalize_value(label, kind, value)
        _check_number(label, kind, value, checked, param.min_value, param.max_value)
        pairs.append((param.item, checked))
    if not pairs:
        raise ValueError(f"{head}: nothing to write (no parameter given and none has a "
                         "default)")
    return pairs


def _check_number(label: str, kind: DataType, raw: Any, value: Any,
                  lo: float | None, hi: float | None) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    if kind.is_integer:
        if isinstance(value, float) and not value.is_integer():
            raise ValueError(f"{label}: {raw!r} is not allowed: {kind.value} takes a whole "
                             "number")
        first, last = kind.integer_range
        if not first <= value <= last:
            raise ValueError(f"{label}: {raw!r} is not allowed: {kind.value} takes "
                             f"{first}..{last}")
    elif isinstance(value, float) and not math.isfinite(value) and (
            lo is not None or hi is not None):
        raise ValueError(f"{label}: {raw!r} is not allowed: a finite number is needed")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        bounds = f"{'' if lo is None else f'{lo:g}'}..{'' if hi is None else f'{hi:g}'}"
        raise ValueError(f"{label}: {raw!r} is out of range ({bounds})")


def plan_action(
    action: DeviceAction, given: Mapping[str, Any], by_name: Mapping[str, ItemState]
) -> list[WriteOp]:
    """The requests of ``action`` with ``given`` parameters, in its function code: FC15
    and FC16 merge neighbouring coils/registers into one request (up to the protocol's
    limits), FC05 and FC06 send one request per coil/register.  An address action (NG's
    form) writes ``given["value"]`` at its address (:func:`address_values`)."""
    if action.address is not None:
        values = address_values(action, given)
        op = WriteOp(action.area, action.address, function=action.function_code)
        if action.area.is_bit:
            op.bits = [bool(v) for v in values]
        else:
            op.registers = [int(v) for v in values]
        return [op]
    pairs = resolve_parameters(action, given, by_name)
    try:
        ops = prepare_writes(by_name, pairs)
    except ValueError as exc:
        param = {p.item: p.name for p in action.parameters}
        text = str(exc)
        for item, name in param.items():
            if f"{item!r}" in text or text.startswith(f"{item}:"):
                text = f"parameter {name!r}: {text}"
                break
        raise ValueError(f"action {action.name!r}: {text}") from None
    for op in ops:
        if op.area is not action.area or op.bit is not None:
            raise ValueError(f"action {action.name!r}: {op.names} is not a whole "
                             f"{'coil' if action.area.is_bit else 'holding register'} item, "
                             f"which functionCode {action.function_code} writes")
        op.function = action.function_code
    return merge_writes(ops) if action.function_code in (15, 16) else ops


def address_values(action: DeviceAction, given: Mapping[str, Any]) -> list[int] | list[bool]:
    """The coils (bools) or registers (0..65535; -32768..-1 as their two's complement)
    an address action writes: ``given["value"]``, one value or a list of ``quantity``
    (text as the CLI passes it: ``1234``, ``true``, ``1,2,3`` or ``[1, 2, 3]``).
    ValueError names the action and what is allowed."""
    head = f"action {action.name!r}"
    if not isinstance(given, Mapping):
        raise ValueError(f"{head}: parameters must be a mapping of names to values, "
                         f"not {type(given).__name__}")
    bits = action.area.is_bit
    count = action.count
    what = (f"{count} coil{'s' if count > 1 else ''} (true/false)" if bits else
            f"{count} register{'s' if count > 1 else ''} (0..65535 or -32768..-1)")
    unknown = [str(k) for k in given if k != ACTION_VALUE]
    if unknown or ACTION_VALUE not in given:
        problem = (f"unknown parameter {', '.join(map(repr, unknown))}" if unknown
                   else f"parameter {ACTION_VALUE!r} is missing")
        raise ValueError(f"{head}: {problem} (it writes {what} at "
                         f"{action.area.short_name}:{action.address}: give "
                         f"{ACTION_VALUE}=...)")
    raw = given[ACTION_VALUE]
    label = f"{head}: parameter {ACTION_VALUE!r} {_shown(raw)}"
    values = _split(raw, label)
    if len(values) != count:
        raise ValueError(f"{label}: {len(values)} value{'s' if len(values) != 1 else ''}, "
                         f"but it writes {what}")
    return [_coil(v, label) for v in values] if bits else [_register(v, label)
                                                          for v in values]


def _shown(raw: Any) -> str:
    text = repr(raw)
    return text if len(text) <= 60 else text[:57] + "..."


def _split(raw: Any, label: str) -> list[Any]:
    if isinstance(raw, str):
        text = raw.strip()
        if text.startswith("["):
            try:
                raw = json.loads(text)
            except ValueError:
                raise ValueError(f"{label}: not a JSON list") from None
        else:
            return [t for t in text.replace(",", " ").split() if t] or [""]
    return list(raw) if isinstance(raw, (list, tuple)) else [raw]


_COIL_TEXT = {"true": True, "on": True, "1": True, "false": False, "off": False, "0": False}


def _coil(value: Any, label: str) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in _COIL_TEXT:
        return _COIL_TEXT[value.strip().lower()]
    raise ValueError(f"{label}: {value!r} is not a coil value (true/false, on/off, 1/0)")


def _register(value: Any, label: str) -> int:
    number: Any = value
    if isinstance(value, str):
        try:
            number = int(value.strip(), 0)
        except ValueError:
            number = None
    if isinstance(number, float) and number.is_integer():
        number = int(number)
    if isinstance(number, bool) or not isinstance(number, int) or \
            not -32768 <= number <= 65535:
        raise ValueError(f"{label}: {value!r} is not a register value (a whole number "
                         "0..65535, or -32768..-1 as its two's complement)")
    return number & 0xFFFF


def prefix_errors(future: Future[Any], head: str) -> Future[Any]:
    """A future of ``future``'s (ok, error) with ``head`` before the error text."""
    out: Future[Any] = Future()

    def done(f: Future[Any]) -> None:
        try:
            ok, error = f.result()
        except Exception as exc:
            ok, error = False, str(exc)
        out.set_result((ok, None if error is None else head + error))

    future.add_done_callback(done)
    return out
