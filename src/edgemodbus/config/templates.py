"""Device templates: ``"template": "<name>"`` in a device file pulls in a template's
address list and device defaults (docs/device-files.md, "Device templates").

A template is a JSON file ``<name>.json`` found on the search path, first match wins:
the device file's ``templateDirs`` (relative to the device file's folder), then the
folders of ``$EDGEMODBUS_TEMPLATE_PATH`` (separated by ``os.pathsep``), then the
templates shipped in the package (``edgemodbus/templates``).  It holds::

    {"description": "...", "source": {"vendor", "document", "version", "url"},
     "communication": {device defaults: TEMPLATE_COMMUNICATION_KEYS},
     "itemDefaults": {keys every template item gets unless it sets them},
     "addressList": [items]}

Its items' addresses are written with its own ``addressPrefix``/``addressBase`` and are
rewritten to the device's (so a device using entity numbers can use any template).  An
item of the device file whose name is a template item's overrides that item's keys
(``"isEnable": false`` disables it); other items are added after the template's.
:func:`apply_template` does it all, on the raw device data, before validation.
"""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..protocol.address import PREFIXES, format_address, parse_address
from .communication import DriverModbusRtuParameter
from .compat import ng_aliases, norm_key
from .items import DeviceAddressItem
from .jsonfile import read_json_file
from .problems import NO_VALUE, ConfigError, Problem

TEMPLATE_PATH_ENV = "EDGEMODBUS_TEMPLATE_PATH"
SHIPPED_DIR = Path(__file__).resolve().parent.parent / "templates"

TEMPLATE_COMMUNICATION_KEYS: tuple[str, ...] = (
    "dataFormat", "byteSwap16", "dataFormat64", "maxBlockReadRegisterCount", "maxMergeAddressGap",
    "isBlockReadRequireAddressContinuous", "maxBlockReadBitCount", "encoding",
    "writeSingleRegisterFunction", "baudRate", "parity", "dataBits", "stopBits",
    "readTimeout", "byteTimeout", "requestInterval", "addressPrefix", "addressBase",
)
"""What a template's ``communication`` may set: what the device is, not where it is
(ports, hosts and slave ids belong to the device file).  ``addressPrefix`` and
``addressBase`` only say how the template's own addresses are written."""

_TEMPLATE_KEYS = ("name", "description", "source", "communication", "itemDefaults",
                  "addressList")

# The folder of the device file being loaded (its templateDirs are relative to it).
_base_dir: ContextVar[Path | None] = ContextVar("edgemodbus_template_base", default=None)
# Where each item of the merged address list came from (see device_loading).
_origins: ContextVar[dict[int, tuple[str, str]] | None] = ContextVar("edgemodbus_template_origins",
                                                         default=None)


@contextmanager
def device_loading(source: Any) -> Iterator[None]:
    """While loading ``source``: relative ``templateDirs`` are relative to its folder (a
    path), else to the current directory; a ConfigError's ``addressList[i]`` paths are
    told as the device file has them (the merged list counts the template's items
    first): ``addressList[0].unit (over template item 'Voltage')`` (the device file's
    item), ``addressList[3].unit (template eastron-sdm120 item 'Current')`` (the
    template's)."""
    folder = (Path(os.fspath(source)).resolve().parent
              if isinstance(source, os.PathLike)
              or (isinstance(source, str) and not source.lstrip("\ufeff \t\r\n").startswith("{"))
              else None)
    origins: dict[int, tuple[str, str]] = {}
    tokens = (_base_dir.set(folder), _origins.set(origins))
    try:
        yield
    except ConfigError as exc:
        if not origins:
            raise
        raise ConfigError([_told(p, origins) for p in exc.problems]) from None
    finally:
        _origins.reset(tokens[1])
        _base_dir.reset(tokens[0])


def _told(problem: Problem, origins: dict[int, tuple[str, str]]) -> Problem:
    head, sep, rest = problem.path.partition("]")
    if not sep or not head.startswith("addressList["):
        return problem
    try:
        where, note = origins[int(head.removeprefix("addressList["))]
    except (ValueError, KeyError):
        return problem
    message = re.sub(r"addressList\[(\d+)\]",
                     lambda m: origins.get(int(m.group(1)), (m.group(0), ""))[0],
                     problem.message)
    return Problem(f"{where}{rest}{note}", problem.value, message)


@dataclass(frozen=True, slots=True)
class TemplateInfo:
    """One template found on the search path."""

    name: str
    description: str
    source: dict[str, Any]
    file: Path

    def summary(self) -> dict[str, Any]:
        """name, description, source (the descriptor's preset entry; no file path)."""
        return {"name": self.name, "description": self.description, "source": self.source}


def search_path(dirs: Sequence[str | os.PathLike[str]] = ()) -> list[Path]:
    """The folders searched, in order: ``dirs`` (relative to the device file's folder
    while one loads), ``$EDGEMODBUS_TEMPLATE_PATH``, the shipped templates."""
    base = _base_dir.get() or Path.cwd()
    path = [base / Path(d) for d in dirs]
    path += [Path(d) for d in os.environ.get(TEMPLATE_PATH_ENV, "").split(os.pathsep) if d]
    path.append(SHIPPED_DIR)
    return path


def _path_text(path: Sequence[Path]) -> str:
    return os.pathsep.join(str(p) for p in path)


def find_templates(dirs: Sequence[str | os.PathLike[str]] = ()) -> list[TemplateInfo]:
    """Every template on the search path, by name (a name found twice: the first)."""
    found: dict[str, TemplateInfo] = {}
    for folder in search_path(dirs):
        if not folder.is_dir():
            continue
        for file in sorted(folder.glob("*.json")):
            if file.stem not in found:
                doc = _read(file, file.stem)
                found[file.stem] = TemplateInfo(
                    file.stem, str(doc.get("description", "")),
                    dict(doc.get("source") or {}), file)
    return sorted(found.values(), key=lambda t: t.name)


def template_file(name: str, dirs: Sequence[str | os.PathLike[str]] = ()) -> Path:
    """The file of template ``name``; ConfigError naming the search path if none."""
    path = search_path(dirs)
    if not name or "/" in name or "\\" in name or name.startswith("."):
        raise ConfigError([Problem("template", name, "must be a template name (a file name "
                                   "without .json on the template search path)")])
    for folder in path:
        if (folder / f"{name}.json").is_file():
            return folder / f"{name}.json"
    known = sorted({f.stem for d in path if d.is_dir() for f in d.glob("*.json")})
    close = difflib.get_close_matches(name, known, n=1)
    hint = f"did you mean {close[0]!r}? " if close else ""
    raise ConfigError([Problem(
        "template", name,
        f"no such template on the search path {_path_text(path)} ({hint}known: "
        f"{', '.join(known) or 'none'}; add folders with templateDirs or ${TEMPLATE_PATH_ENV})")])


def _read(file: Path, name: str) -> dict[str, Any]:
    where = f"template {name} ({file})"
    try:
        doc = read_json_file(file)
    except OSError as exc:
        raise ConfigError([Problem(where, NO_VALUE, exc.strerror or str(exc))]) from None
    except ConfigError as exc:
        raise ConfigError([Problem(where, NO_VALUE, p.message) for p in exc.problems]) \
            from None
    if not isinstance(doc, dict):
        raise ConfigError([Problem(where, NO_VALUE, "a template must be a JSON object")])
    problems = [Problem(f"{where}: {key}", NO_VALUE,
                        f"not a template key (use {', '.join(_TEMPLATE_KEYS)})")
                for key in doc if key not in _TEMPLATE_KEYS]
    if doc.get("name", name) != name:
        problems.append(Problem(f"{where}: name", doc["name"],
                                f"must be the file's name {name!r}"))
    for key, kind in (("communication", dict), ("itemDefaults", dict), ("source", dict),
                      ("addressList", list)):
        if key in doc and not isinstance(doc[key], kind):
            problems.append(Problem(f"{where}: {key}", doc[key],
                                    f"must be {'an object' if kind is dict else 'a list'}"))
    if problems:
        raise ConfigError(problems)
    return doc


def load_template(name: str, dirs: Sequence[str | os.PathLike[str]] = ()) -> dict[str, Any]:
    """The JSON object of template ``name`` (checked for its keys' kinds)."""
    return _read(template_file(name, dirs), name)


def template_bytes(device_file: str | os.PathLike[str], data: Any = None) -> bytes:
    """The bytes of the template a device file names (b"" if none, or if it cannot be
    found: loading the file says why), so that a reload notices a changed template.
    ``data``: the file's decoded JSON when the caller has read it (else it is read)."""
    try:
        path = Path(os.fspath(device_file))
        if data is None:
            data = read_json_file(path)
        keys = {norm_key(k): v for k, v in data.items()} if isinstance(data, dict) else {}
        name, dirs = keys.get("template"), keys.get("templatedirs") or []
        if not isinstance(name, str):
            return b""
        with device_loading(path):
            return template_file(name, [dirs] if isinstance(dirs, str) else dirs).read_bytes()
    except (OSError, ValueError, TypeError, ConfigError):
        return b""


# --------------------------------------------------------------------------- merging


# A device's NG spellings replace these template defaults (compat.ng_aliases would see
# both and call them a disagreement).
_NG_REPLACES = {
    "maxGap": ("maxMergeAddressGap",),
    "maxBatch": ("maxBlockReadRegisterCount",),
    "byteOrder": ("dataFormat", "byteSwap16"),
    "wordOrder": ("dataFormat",),
    "connection": ("baudRate", "parity", "dataBits", "stopBits"),
}


def _canonical(obj: Mapping[str, Any], table: dict[str, str], where: str,
               allowed: Sequence[str] | None = None) -> tuple[dict[str, Any], list[Problem]]:
    """``obj`` with canonical keys; every unknown (or not allowed) key is a problem."""
    out: dict[str, Any] = {}
    problems: list[Problem] = []
    for key, value in obj.items():
        canon = table.get(norm_key(key)) if isinstance(key, str) else None
        if canon is None or (allowed is not None and canon not in allowed):
            keys = list(allowed if allowed is not None else table.values())
            close = difflib.get_close_matches(str(key), keys, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            more = " ..." if len(keys) > 12 else ""
            problems.append(Problem(f"{where}.{key}", value,
                                    f"not a key here ({hint}use {', '.join(keys[:12])}{more})"))
        else:
            out[canon] = value
    return out, problems


def _options(comm: Mapping[str, Any]) -> tuple[str, int] | None:
    """(addressPrefix, addressBase) of canonical communication keys; None if invalid
    (the device's own validation reports it)."""
    prefix = comm.get("addressPrefix", "function-code")
    base = comm.get("addressBase", 0)
    prefix = prefix.strip().lower() if isinstance(prefix, str) else prefix
    if prefix not in PREFIXES or base not in (0, 1) or isinstance(base, bool):
        return None
    return prefix, base


def apply_template(data: dict[str, Any]) -> dict[str, Any]:
    """Device data (canonical top-level keys) with its ``template`` applied: defaults into
    ``communication``, the template's items (overridden by name) then the file's own
    into ``addressList``.  ConfigError names the template, the key and the value."""
    name = data.get("template")
    if name is None:
        return data
    if not isinstance(name, str):
        raise ConfigError([Problem("template", name, "must be a template name (text)")])
    dirs = data.get("templateDirs") or []
    if isinstance(dirs, str):
        dirs = [dirs]
    if not isinstance(dirs, list) or not all(isinstance(d, str) for d in dirs):
        raise ConfigError([Problem("templateDirs", dirs, "must be a list of folders")])
    file = template_file(name, dirs)
    doc = _read(file, name)
    where = f"template {name} ({file})"
    comm_table = DriverModbusRtuParameter.key_table()
    item_table = DeviceAddressItem.key_table()
    problems: list[Problem] = []

    tcomm, found = _canonical(doc.get("communication", {}), comm_table,
                              f"{where}: communication", TEMPLATE_COMMUNICATION_KEYS)
    problems += found
    try:
        tcomm = ng_aliases(tcomm)
    except ConfigError as exc:
        problems += [Problem(f"{where}: communication.{p.path}", p.value, p.message)
                     for p in exc.problems]
    written = _options(tcomm)
    if written is None:
        problems.append(Problem(f"{where}: communication.addressPrefix", NO_VALUE,
                                "addressPrefix/addressBase of the template are not valid"))
    device_comm = data.get("communication")
    if device_comm is not None and not isinstance(device_comm, Mapping):
        return data  # the device's own validation says what is wrong
    dcomm = dict(device_comm or {})
    replaced = {"addressPrefix", "addressBase"}
    replaced.update(*(_NG_REPLACES.get(key, ()) for key in dcomm))
    comm = {k: v for k, v in tcomm.items() if k not in replaced}
    comm.update(dcomm)
    data["communication"] = comm
    target = _options(comm)

    defaults, found = _canonical(doc.get("itemDefaults", {}), item_table,
                                 f"{where}: itemDefaults")
    problems += found
    items: list[dict[str, Any]] = []
    index: dict[str, int] = {}
    for i, raw in enumerate(doc.get("addressList", [])):
        path = f"{where}: addressList[{i}]"
        if not isinstance(raw, Mapping):
            problems.append(Problem(path, raw, "must be an object"))
            continue
        item, found = _canonical(raw, item_table, path)
        problems += found
        item = {**defaults, **item}
        if not isinstance(item.get("name"), str) or item["name"] in index:
            problems.append(Problem(f"{path}.name", item.get("name", NO_VALUE),
                                    "a template item needs a unique name"))
            continue
        if written is not None and target is not None:
            try:
                addr = parse_address(str(item.get("address")), *written)
                item["address"] = format_address(addr, *target)
            except ValueError as exc:
                problems.append(Problem(f"{path}.address", item.get("address", NO_VALUE),
                                        str(exc)))
        index[item["name"]] = len(items)
        items.append(item)
    origins = {k: (f"addressList[{k}]", f" (template {name} item {item['name']!r})")
               for k, item in enumerate(items)}
    own = data.get("addressList") or []
    if not isinstance(own, list):
        raise ConfigError(problems) if problems else ConfigError(
            [Problem("addressList", own, "must be a list of items")])
    extra: list[Any] = []
    for i, raw in enumerate(own):
        name_of = raw.get("name") if isinstance(raw, Mapping) else None
        if isinstance(name_of, str) and name_of in index:
            override, found = _canonical(raw, item_table, f"addressList[{i}]")
            problems += [Problem(p.path, p.value,
                                 f"{p.message}: an override of template item {name_of!r}")
                         for p in found]
            items[index[name_of]].update(override)
            origins[index[name_of]] = (f"addressList[{i}]",
                                       f" (over template item {name_of!r})")
        else:
            origins[len(items) + len(extra)] = (f"addressList[{i}]", "")
            extra.append(raw)
    if problems:
        raise ConfigError(problems)
    data["addressList"] = [*items, *extra]
    told = _origins.get()
    if told is not None:
        told.clear()
        told.update(origins)
    return data
