"""Writes, actions and reads from MQTT: the command payloads, and the thread that runs them.

Commands run on one ``edgemodbus-mqtt-cmd`` thread with an asyncio loop through
``write_addresses_async``, ``run_action_async`` or ``read_now`` (many devices' commands in
flight at once; per device in arrival order); the result goes to the device's reply topic.

Commands are untrusted input (any client allowed on the topic sends them): a payload over
:data:`MAX_COMMAND_BYTES` is refused unread, JSON nested too deep is an error reply (not
a traceback), a request ``id`` is echoed only when it is a number, a boolean or a string
of at most :data:`MAX_ID_CHARS` characters, and an error reply quotes at most
:data:`MAX_ERROR_CHARS` characters."""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

from ...errors import ModbusError
from ...line.log_limit import short_text
from ..loop_thread import LoopThread
from .devices import AttachedDevice
from .outbox import Message, Outbox
from .payload import dumps, now

log = logging.getLogger("edgemodbus.mqtt")

MAX_COMMAND_BYTES = 65536
MAX_ID_CHARS = 128
MAX_ERROR_CHARS = 300
_MAX_PENDING_COMMANDS = 256


def _loads(text: str | bytes, what: str) -> Any:
    """JSON of a command; ValueError for bad JSON and for nesting past Python's recursion
    limit (json raises RecursionError there)."""
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError(f"{what} is nested too deeply") from None


def checked_id(value: Any) -> Any:
    """A request id as it may be echoed: null, a number, a boolean or a short string;
    ValueError (without the id) for anything else."""
    if value is None or isinstance(value, (bool, int, float)):
        return value
    if isinstance(value, str):
        if len(value) <= MAX_ID_CHARS:
            return value
        raise ValueError(f'"id" is a string of {len(value)} characters (at most '
                         f"{MAX_ID_CHARS})")
    raise ValueError(f'"id" must be a number or a string, not a JSON {type(value).__name__}')


def request_id_of(payload: bytes) -> Any:
    """The ``id`` of a JSON object payload, if there is one and it may be echoed (for
    error replies); None for an oversized payload (not parsed)."""
    if len(payload) > MAX_COMMAND_BYTES:
        return None
    try:
        obj = _loads(payload, "payload")
        return checked_id(obj.get("id")) if isinstance(obj, dict) else None
    except (ValueError, UnicodeDecodeError):
        return None


def short_error(text: str) -> str:
    """An error for a reply, cut at :data:`MAX_ERROR_CHARS` (it may quote the value)."""
    if len(text) <= MAX_ERROR_CHARS:
        return text
    return f"{text[:MAX_ERROR_CHARS]}... ({len(text)} characters)"


def parse_command(name: str | None, payload: bytes) -> tuple[Any, list[tuple[str, Any]]]:
    """(request id, [(item, value), ...]) from a command payload; ValueError says what
    is wrong.  ``name`` is the item of a single-item topic, None for the batch topic.

    Single item: a JSON value (``12.5``, ``true``, ``"text"``), or ``{"value": v, "id": x}``;
    text that is not JSON is taken as a string.  Batch: ``{"name": value, ...}``, or
    ``{"items": {...} | [{"name": n, "value": v}, ...] | [[n, v], ...], "id": x}``.
    """
    if len(payload) > MAX_COMMAND_BYTES:
        raise ValueError(f"payload of {len(payload)} bytes is too large "
                         f"(at most {MAX_COMMAND_BYTES})")
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError("payload is not UTF-8 text") from None
    if name is not None:
        if not name:
            raise ValueError("no item name in the command topic")
        try:
            value = json.loads(text)
        except RecursionError:
            raise ValueError("payload is nested too deeply") from None
        except ValueError:
            return None, [(name, text)]
        if isinstance(value, dict):
            if "value" not in value:
                raise ValueError('an object payload needs a "value" key, e.g. {"value": 1}')
            return checked_id(value.get("id")), [(name, value["value"])]
        return None, [(name, value)]
    try:
        body = _loads(text, "batch payload")
    except ValueError as exc:
        raise ValueError(f"batch payload is not JSON: {exc}") from None
    request_id: Any = None
    if isinstance(body, dict) and "items" in body:
        request_id = checked_id(body.get("id"))
        body = body["items"]
    items: list[tuple[str, Any]] = []
    if isinstance(body, dict):
        items = [(str(k), v) for k, v in body.items()]
    elif isinstance(body, list):
        for i, entry in enumerate(body):
            if isinstance(entry, dict) and isinstance(entry.get("name"), str) and (
                "value" in entry
            ):
                items.append((entry["name"], entry["value"]))
            elif isinstance(entry, list) and len(entry) == 2 and isinstance(entry[0], str):
                items.append((entry[0], entry[1]))
            else:
                raise ValueError(f'items[{i}] {short_text(repr(entry))}: use {{"name": ..., '
                                 '"value": ...} or [name, value]')
    else:
        raise ValueError(f"batch payload {short_text(repr(body))}: use an object of item "
                         'names to values, or {"items": ..., "id": ...}')
    if not items:
        raise ValueError("batch payload names no items")
    return request_id, items


def parse_action(payload: bytes) -> tuple[Any, str, dict[str, Any]]:
    """(request id, action name, parameters) of an action payload
    ``{"action": "start", "parameters": {"speed": 12.5}, "id": 7}`` (parameters may be
    left out: all take their defaults); ValueError says what is wrong."""
    if len(payload) > MAX_COMMAND_BYTES:
        raise ValueError(f"payload of {len(payload)} bytes is too large "
                         f"(at most {MAX_COMMAND_BYTES})")
    try:
        body = _loads(payload.decode("utf-8"), "action payload")
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"action payload is not JSON: {exc}") from None
    if not isinstance(body, dict) or not isinstance(body.get("action"), str):
        raise ValueError('action payload: use {"action": "<name>", "parameters": {...}, '
                         '"id": ...}')
    params = body.get("parameters", {})
    if params is None:
        params = {}
    if not isinstance(params, dict):
        raise ValueError(f"action payload: parameters {short_text(repr(params))} must be an "
                         "object of parameter names to values")
    return checked_id(body.get("id")), body["action"], params


def parse_read(payload: bytes) -> tuple[Any, list[str] | None]:
    """(request id, item names or None: every item) of a read payload: empty or ``{}``
    (the whole device), ``"name"``, ``["a", "b"]``, or ``{"items": [...], "id": 7}``
    (docs/reporting.md); ValueError says what is wrong."""
    if len(payload) > MAX_COMMAND_BYTES:
        raise ValueError(f"payload of {len(payload)} bytes is too large "
                         f"(at most {MAX_COMMAND_BYTES})")
    if not payload.strip():
        return None, None
    try:
        body = _loads(payload.decode("utf-8"), "read payload")
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"read payload is not JSON: {exc}") from None
    request_id: Any = None
    if isinstance(body, dict):
        unknown = sorted(set(body) - {"items", "id"})
        if unknown:
            raise ValueError(f"read payload: unknown key {short_text(unknown[0])} "
                             '(use {"items": [names], "id": ...})')
        request_id = checked_id(body.get("id"))
        body = body.get("items")
    if body is None:
        return request_id, None
    if isinstance(body, str):
        body = [body]
    if not isinstance(body, list) or not body or not all(isinstance(n, str) for n in body):
        raise ValueError(f"read payload: items {short_text(repr(body))} must be a non-empty "
                         "list of item names (or leave it out: every item)")
    return request_id, body


class CommandRunner:
    """The command thread: a write per command, replies through the outbox."""

    def __init__(self, outbox: Outbox) -> None:
        self._outbox = outbox
        self._runner = LoopThread("edgemodbus-mqtt-cmd")
        self.pending = 0  # commands taken and not yet answered (under the outbox's lock)

    def start(self) -> None:
        self._runner.start()

    def dispatch(self, dev: AttachedDevice, name: str | None, payload: bytes,
                 action: bool = False, read: bool = False) -> None:
        if not self._runner.running:
            return
        with self._outbox.lock:
            self._outbox.counts["commands"] += 1
            busy = self.pending >= _MAX_PENDING_COMMANDS
            if not busy:
                self.pending += 1
        if busy:
            self._reply(dev, request_id_of(payload), False,
                        f"{_MAX_PENDING_COMMANDS} commands already pending; try again later", [])
            return
        if not self._runner.spawn(lambda: self._action(dev, payload) if action
                                  else self._read(dev, payload) if read
                                  else self._command(dev, name, payload)):
            with self._outbox.lock:  # stop() is under way
                self.pending -= 1

    async def _action(self, dev: AttachedDevice, payload: bytes) -> None:
        request_id: Any = None
        try:
            try:
                request_id, action, params = parse_action(payload)
            except ValueError as exc:
                self._reply(dev, request_id_of(payload), False, str(exc), [])
                return
            ok, error = await dev.driver.run_action_async(action, params)
            self._reply(dev, request_id, ok, error, [], action)
        except Exception as exc:  # never let a command kill the loop
            log.exception("%s: MQTT action failed", dev.code)
            self._reply(dev, request_id, False, f"internal error: {exc}", [])
        finally:
            with self._outbox.lock:
                self.pending -= 1

    async def _read(self, dev: AttachedDevice, payload: bytes) -> None:
        """A read on demand (driver.read_now): the values are published as any report
        (item or batch topics); the reply has them too."""
        request_id: Any = None
        names: list[str] = []
        try:
            try:
                request_id, asked = parse_read(payload)
                names = list(asked or [])
                future = dev.driver.read_now(asked)
            except (ValueError, KeyError, ModbusError) as exc:
                text = exc.args[0] if isinstance(exc, KeyError) and exc.args else str(exc)
                self._reply(dev, request_id if request_id is not None
                            else request_id_of(payload), False, str(text), names, read={})
                return
            try:
                values = await asyncio.wrap_future(future)
            except ModbusError as exc:
                self._reply(dev, request_id, False, str(exc), names, read={})
                return
            self._reply(dev, request_id, True, None, list(values), read=values)
        except Exception as exc:  # never let a command kill the loop
            log.exception("%s: MQTT read failed", dev.code)
            self._reply(dev, request_id, False, f"internal error: {exc}", names, read={})
        finally:
            with self._outbox.lock:
                self.pending -= 1

    async def _command(self, dev: AttachedDevice, name: str | None, payload: bytes) -> None:
        request_id: Any = None
        names: list[str] = []
        try:
            try:
                request_id, items = parse_command(name, payload)
            except ValueError as exc:
                self._reply(dev, request_id_of(payload), False, str(exc), [])
                return
            names = [n for n, _ in items]
            ok, error = await dev.driver.write_addresses_async(items, exact=True)
            self._reply(dev, request_id, ok, error, names)
        except Exception as exc:  # never let a command kill the loop
            log.exception("%s: MQTT write failed", dev.code)
            self._reply(dev, request_id, False, f"internal error: {exc}", names)
        finally:
            with self._outbox.lock:
                self.pending -= 1

    def _reply(self, dev: AttachedDevice, request_id: Any, ok: bool, error: str | None,
               names: list[str], action: str | None = None,
               read: dict[str, Any] | None = None) -> None:
        if not ok:
            self._outbox.count("commandErrors")
        body: dict[str, Any] = {"id": request_id, "ok": ok,
                                "error": None if error is None else short_error(error),
                                "items": [n if len(n) <= MAX_ID_CHARS else short_text(n)
                                          for n in names], "ts": now()}
        if action is not None:
            body["action"] = action
        if read is not None:  # a read's reply: each item's value, status, updateTs, error
            body["read"] = read
        self._outbox.push_control(Message(dev.code, dev.reply_topic, dumps(body), 1, False))

    def stop(self) -> None:
        self._runner.stop()
