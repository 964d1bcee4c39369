"""Write docs/configuration.md, the reference of every key of the device file and the
gateway file, from the pydantic models that load them.

Each key's JSON spelling, type, default and allowed values come from the model (its
alias, annotation, default, and its Range / Choice / Literal / enum); its meaning from
the field's ``description`` where the model has one, else from DESCRIPTIONS below, so
that the reference cannot list a key the loader does not know or miss one it does: a key
without a description is an error of this tool, and a description of a key that no
longer exists too.  ``--check`` compares the committed file with what would be written
(tests/unit/test_config_reference.py runs it).

Usage: python tools/gen_config_reference.py [--check]
"""

from __future__ import annotations

import enum
import sys
import types
import typing
from pathlib import Path
from typing import Any, NamedTuple

from pydantic import BaseModel, SecretStr
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from edgemodbus.config import compat
from edgemodbus.config.actions import ActionParameter, DeviceAction
from edgemodbus.config.communication import DriverModbusRtuParameter
from edgemodbus.config.device import DeviceConfig, DeviceOrganizationParameter
from edgemodbus.config.items import DeviceAddressItem
from edgemodbus.console.settings import ConsoleSettings, ConsoleTls, ConsoleUser
from edgemodbus.gateway.config import GatewayConfig
from edgemodbus.gateway.fleet import FleetSettings, LeaseSettings
from edgemodbus.northbound.metrics import MetricsSettings
from edgemodbus.northbound.mqtt.settings import (
    MqttSettings,
    StoreAndForwardSettings,
    TlsSettings,
)
from edgemodbus.northbound.sparkplug.settings import SparkplugSettings
from edgemodbus.serve.settings import ServeSettings, ServeUnit

TOP = Path(__file__).resolve().parents[1]
OUTPUT = TOP / "docs" / "configuration.md"


class Section(NamedTuple):
    """One table: the keys of ``model`` at ``path`` of a file."""

    path: str
    model: Any  # a pydantic model class (BaseModel or the slotted item dataclass)
    intro: str


DEVICE = (
    Section("(top level)", DeviceConfig, "A device file: one JSON object per device."),
    Section("organization", DeviceOrganizationParameter,
            "Who the device is; its timing keys override `communication`'s."),
    Section("communication", DriverModbusRtuParameter,
            "Where the device is and how to talk to it. Times are milliseconds."),
    Section("addressList[]", DeviceAddressItem,
            "One item (tag) each. The byte order keys override the device's, key by key."),
    Section("actions[]", DeviceAction, "Named groups of writes (an action: "
            "[device-files.md](device-files.md#actions))."),
    Section("actions[].parameters[]", ActionParameter, "The parameters of an action."),
)
GATEWAY = (
    Section("(top level)", GatewayConfig,
            "`gateway.json` in the config folder (or `--gateway FILE`)."),
    Section("mqtt", MqttSettings, "The MQTT publisher ([gateway.md](gateway.md)). Times in "
            "milliseconds unless the key says otherwise."),
    Section("mqtt.tls", TlsSettings, "TLS to the broker; relative paths are taken from the "
            "gateway file's folder, and the files are checked at load."),
    Section("mqtt.storeAndForward", StoreAndForwardSettings,
            "The spool on disk ([gateway.md](gateway.md#store-and-forward))."),
    Section("mqtt.sparkplug", SparkplugSettings,
            "Sparkplug B, with `mqtt.mode: \"sparkplug\"` ([gateway.md](gateway.md#sparkplug-b))."),
    Section("metrics", MetricsSettings, "The Prometheus exporter (`/metrics`)."),
    Section("serve", ServeSettings, "The Modbus TCP server for SCADA "
            "([gateway.md](gateway.md#a-modbus-tcp-server-for-scada-serve-and-forward))."),
    Section("serve.units[]", ServeUnit,
            "One unit id each: `device` (serve: cached reads) or `forward` (forward mode)."),
    Section("console", ConsoleSettings, "The web console ([console.md](console.md)); off "
            "unless the section is there."),
    Section("console.users[]", ConsoleUser, "Who may log in; passwords as scrypt hashes "
            "(`python -m edgemodbus.console hash-password`)."),
    Section("console.tls", ConsoleTls, "HTTPS for the console; the files are checked at load "
            "as the MQTT ones are."),
    Section("fleet", FleetSettings, "This instance of a dial-in fleet behind a TCP load "
            "balancer ([deploy.md](deploy.md)); left out: one gateway alone."),
    Section("fleet.lease", LeaseSettings, "A redundant pair: the Redis lease that picks "
            "the instance polling the connect-mode devices "
            "([deploy.md](deploy.md#a-redundant-pair))."),
)

_RUNTIME = ("runtime state the driver writes (what it last read); a file may carry it "
            "(the Pascal.Edge UI saves it), it is overwritten once the item is read")

#: Meanings of the keys whose field has no ``description`` (keyed "section.key").
DESCRIPTIONS: dict[str, str] = {
    "(top level).driverType": "The driver the file is for (the Pascal.Edge descriptor's "
                              "name); only DriverModbusRtu",
    "(top level).organization": "The section `organization` below",
    "(top level).communication": "The section `communication` below",
    "(top level).addressList": "The items (section `addressList[]` below); NG's `points` "
                               "is accepted",
    "(top level).actions": "The actions (section `actions[]` below)",
    "organization.deviceId": "The device's id in a management system (kept, not used)",
    "organization.deviceCode": "The device's name: MQTT topics, Sparkplug device, logs, the "
                               "server's `device`; in a gateway folder the file's name "
                               "when left out",
    "organization.deviceName": "A display name (kept, not used)",
    "organization.description": "Free text (kept, not used)",
    "organization.isEnable": "false: the device is configured but not polled (Disabled)",
    "organization.connectTimeout": "Overrides `communication.connectTimeout` (ms)",
    "organization.reconnectInterval": "Overrides `communication.reconnectInterval` (ms)",
    "organization.readCycle": "Overrides `communication.readCycle` (ms; 0 = report-only)",
    "organization.createdAt": "When the record was made, ISO 8601 (kept, not used)",
    "organization.lastModified": "When the record was changed, ISO 8601 (kept, not used)",
    "organization.metadata": "Anything of yours (kept, not used)",
    "addressList[].name": "The item's name: unique in the device; `write_address`, topics "
                          "and metrics use it (NG: `key`)",
    "addressList[].address": "`[type:]offset[.bit]`: type coil|c|1, di|discreteinput|2, "
                             "hr|holding|3, ir|input|4 (none: hr); or a Modicon entity "
                             "number with `addressPrefix: \"entity\"`",
    "addressList[].deviceDataType": "The type of the value in the device's registers "
                                    "(NG: `dataType`)",
    "addressList[].convertedDataType": "The type the value is reported as (e.g. Float for "
                                       "a scaled Int16 written as float32)",
    "addressList[].dataMultiplier": "The value read is multiplied by it (0.1: raw / 10, "
                                    "exactly); writes divide (NG: `scale`)",
    "addressList[].description": "Free text, reported with the item",
    "addressList[].unit": "The engineering unit, reported with the item",
    "addressList[].updateTs": _RUNTIME,
    "addressList[].status": _RUNTIME,
    "addressList[].isEnable": "false: configured but not read",
    "addressList[].addressChanged": "A flag of the Pascal.Edge UI (kept, not used)",
    "addressList[].dataFormat": "The item's own `dataFormat` (values of two or more "
                                "registers)",
    "addressList[].byteSwap16": "The item's own `byteSwap16` (one-register values)",
    "addressList[].dataFormat64": "The item's own `dataFormat64` (64-bit values)",
    "addressList[].quantity": "Registers the item takes (String and Binary: their length; a "
                              "number: Smart Cast); left out: its type's size",
    "addressList[].deadband": "A numeric value is reported only when it moved by more than "
                              "this since the last report",
    "addressList[].encoding": "The text encoding of a String item; left out: the device's "
                              "`encoding`",
    "addressList[].value": _RUNTIME,
    "addressList[].errorReason": _RUNTIME,
    "actions[].name": "The action's name (`run_action(name, ...)`, MQTT `$action`)",
    "actions[].functionCode": "5, 6, 15 or 16 (numbers, hex text such as `0x10`, or NG's "
                              "names)",
    "actions[].parameters": "The parameters (section `actions[].parameters[]`); NG's "
                            "`inputParameters` is accepted",
    "actions[].address": "NG's form: the first coil or register written (protocol, 0-based); "
                         "the value is the parameter `value`",
    "actions[].quantity": "NG's form: coils or registers written (FC16: at most 123 "
                          "registers)",
    "actions[].command": "NG's command text (kept, not used)",
    "actions[].description": "Free text",
    "actions[].parameters[].name": "The parameter's name (NG: `key`)",
    "actions[].parameters[].item": "The coil or register item of the address list it sets",
    "actions[].parameters[].dataType": "Its type (`type`); left out: the item's value type",
    "actions[].parameters[].required": "Must be given when run; left out: true unless it "
                                       "has a default",
    "actions[].parameters[].defaultValue": "The value when not given (`default`)",
    "actions[].parameters[].minValue": "The smallest value accepted",
    "actions[].parameters[].maxValue": "The largest value accepted",
    "actions[].parameters[].description": "Free text",
    "(top level).gatewayId": "This gateway's name: MQTT client id `edgemodbus-{gatewayId}`, "
                             "topics, Sparkplug edge node; left out: the host name",
    "(top level).mqtt": "The section `mqtt` below; left out: no MQTT",
    "(top level).metrics": "The section `metrics` below; left out: no exporter",
    "(top level).serve": "The section `serve` below; left out: no Modbus TCP server",
    "(top level).devicePattern": "Which files of the folder are device files",
    "(top level).statusCheckInterval": "How often the service logs the status changes "
                                       "its devices reported (ms)",
    "mqtt.enabled": "false: the section is kept but nothing connects",
    "mqtt.mode": "per-item: a message per changed item; batch: a message per device cycle; "
                 "sparkplug: a Sparkplug B edge node",
    "mqtt.sparkplug": "The section `mqtt.sparkplug` (required with mode sparkplug)",
    "mqtt.host": "The broker's host name or address",
    "mqtt.port": "The broker's port",
    "mqtt.clientId": "The MQTT client id; left out: `edgemodbus-{gatewayId}`",
    "mqtt.username": "User name at the broker",
    "mqtt.password": "Password at the broker (never shown: masked in a dump)",
    "mqtt.keepalive": "MQTT keepalive (seconds)",
    "mqtt.connectTimeout": "Time for the broker's CONNACK (ms)",
    "mqtt.tls": "The section `mqtt.tls`; left out: plain TCP",
    "mqtt.topicPrefix": "`{prefix}` in the topic templates (no `+`, `#`)",
    "mqtt.itemTopic": "An item's change (mode per-item)",
    "mqtt.batchTopic": "A device's cycle (mode batch)",
    "mqtt.snapshotTopic": "A device's snapshot (every `snapshotInterval`)",
    "mqtt.statusTopic": "A device's status (retained)",
    "mqtt.gatewayTopic": "The gateway's online/offline and last will (retained)",
    "mqtt.commandTopic": "Writes to one item (in)",
    "mqtt.batchCommandTopic": "Writes to several items of a device (in)",
    "mqtt.replyTopic": "Replies to commands",
    "mqtt.actionTopic": "Runs an action (in)",
    "mqtt.readTopic": "Reads items or the whole device now and publishes them (in)",
    "mqtt.qos": "QoS of item updates and batches",
    "mqtt.retain": "Retain item updates and batches",
    "mqtt.snapshotQos": "QoS of snapshots",
    "mqtt.snapshotRetain": "Retain snapshots",
    "mqtt.snapshotInterval": "A snapshot of every device this often (ms; 0: none); a device's "
                             "own `snapshotInterval` wins",
    "mqtt.writes": "false: command topics are not subscribed (read-only gateway)",
    "mqtt.queueSize": "Item updates kept while the broker is away (oldest dropped, counted)",
    "mqtt.maxInflight": "Messages handed to the broker and not yet acknowledged",
    "mqtt.linger": "A busy MQTT thread sends at most about once per this (ms; 0: at once)",
    "mqtt.reconnectMin": "First reconnect delay (ms; doubles, with jitter)",
    "mqtt.reconnectMax": "Longest reconnect delay (ms; at least reconnectMin)",
    "mqtt.failureLogInterval": "A failed connect is logged at once, then once per this (ms)",
    "mqtt.statusCheckInterval": "How often a fleet's held devices are looked at for "
                                "`$status` (ms); other changes are published as they happen",
    "mqtt.storeAndForward": "The section `mqtt.storeAndForward`; left out: no spool",
    "mqtt.tls.enabled": "false: the section is kept but TLS is off",
    "mqtt.tls.caFile": "CA certificates (PEM) to check the broker with; left out: the "
                       "system's",
    "mqtt.tls.certFile": "Client certificate (PEM)",
    "mqtt.tls.keyFile": "Client key (PEM; not encrypted)",
    "mqtt.tls.insecure": "true: the broker's host name is not checked against its "
                         "certificate",
    "mqtt.storeAndForward.path": "The spool file (SQLite); relative: from the gateway file's "
                                 "folder, which must exist and be writable",
    "mqtt.storeAndForward.maxBytes": "The file on disk (database + WAL) at most; the oldest "
                                     "messages make room",
    "mqtt.storeAndForward.maxAgeS": "Older messages are dropped (seconds)",
    "mqtt.storeAndForward.replayRatePerS": "Messages replayed per second at most",
    "mqtt.storeAndForward.replayBytesPerS": "Bytes replayed per second at most; left out: "
                                            "no limit",
    "mqtt.storeAndForward.synchronous": "normal: a commit survives a crash of the process; "
                                        "full: also a power loss (an fsync per commit)",
    "mqtt.storeAndForward.memoryQueueSize": "Messages kept in memory while the disk refuses "
                                            "writes",
    "mqtt.sparkplug.groupId": "The Sparkplug group",
    "mqtt.sparkplug.edgeNodeId": "The edge node's id; left out: `gatewayId`",
    "mqtt.sparkplug.primaryHostId": "Births wait for this host's STATE online; left out: "
                                    "at connection",
    "mqtt.sparkplug.bdSeqFile": "Keeps bdSeq across restarts; left out: "
                                "`$STATE_DIRECTORY/sparkplug.bdseq` (systemd), else the "
                                "gateway file's folder",
    "mqtt.sparkplug.rebirthInterval": "Rebirth requests within this of the last rebirth are "
                                      "folded into one (ms; 0: no limit)",
    "mqtt.sparkplug.sharedByPair": "true: the two instances of a redundant pair (needs "
                                   "`fleet.lease`) are one edge node (`edgeNodeId` as given, "
                                   "no instance suffix), connected only on the leader, "
                                   "bdSeq kept in the lease's Redis (`<keyPrefix>bdseq`, "
                                   "not `bdSeqFile`) ([deploy.md](deploy.md#a-redundant-pair))",
    "metrics.enabled": "false: the section is kept but no exporter runs",
    "metrics.host": "The address `/metrics` is served on",
    "metrics.port": "Its port (0: any free one)",
    "serve.enabled": "false: the section is kept but no server runs",
    "serve.listen": "IPv4 address and port to listen on",
    "serve.maxConnections": "Masters connected at once; one more is closed at once",
    "serve.idleTimeoutS": "A master silent this long is closed (seconds; 0: never)",
    "serve.allowFrom": "IPv4 networks (CIDR) masters may connect from; empty: any",
    "serve.units": "The units (section `serve.units[]`)",
    "serve.units[].unitId": "The unit id masters address",
    "serve.units[].device": "Serve mode: reads answered from this device's latest values "
                            "(its `deviceCode`)",
    "serve.units[].forward": "Forward mode: every request goes to this device's slave",
    "serve.units[].allowFrom": "IPv4 networks (CIDR) whose masters may address this unit; "
    "others get exception 0A; empty: any source",
    "serve.units[].offset": "Added to the device's addresses (serve mode)",
    "serve.units[].maxAgeMs": "Values older than this are answered with exception 0B; left "
                              "out: no age limit",
    "serve.units[].timeoutMs": "Forward mode: the time for the slave's answer; left out: the "
                               "device's `readTimeout`",
}


def key_of(name: str, field: FieldInfo) -> str:
    return field.alias or name


def _args(annotation: Any) -> tuple[list[Any], bool]:
    """(the types of a union without None, whether None is allowed)."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(annotation)
        return [a for a in args if a is not type(None)], type(None) in args
    return [annotation], False


def _plain(annotation: Any) -> Any:
    while typing.get_origin(annotation) is typing.Annotated:
        annotation = typing.get_args(annotation)[0]
    return annotation


def type_text(annotation: Any) -> str:
    kinds, optional = _args(_plain(annotation))
    words = []
    for kind in kinds:
        kind = _plain(kind)
        origin = typing.get_origin(kind)
        if origin is typing.Literal or (isinstance(kind, type) and issubclass(kind, enum.Enum)):
            words.append("text")
        elif origin in (list, tuple):
            words.append("list")
        elif origin is dict or (isinstance(kind, type) and issubclass(kind, BaseModel)):
            words.append("object")
        elif kind is SecretStr:
            words.append("text (secret)")
        elif kind is bool:
            words.append("boolean")
        elif kind is int:
            words.append("integer")
        elif kind is float:
            words.append("number")
        elif kind is str:
            words.append("text")
        elif getattr(kind, "__name__", "") == "datetime":
            words.append("ISO 8601 time")
        else:
            words.append("any")
    text = " or ".join(dict.fromkeys(words))
    return f"{text} or null" if optional else text


def allowed_text(field: FieldInfo) -> str:
    for meta in field.metadata:
        describe = getattr(meta, "describe", None)
        if callable(describe):
            return str(describe())
    kinds, _ = _args(_plain(field.annotation))
    for kind in kinds:
        kind = _plain(kind)
        if typing.get_origin(kind) is typing.Literal:
            return " \\| ".join(str(a) for a in typing.get_args(kind))
        if isinstance(kind, type) and issubclass(kind, enum.Enum):
            return " \\| ".join(str(m.value) for m in kind)
    return ""


def default_text(field: FieldInfo) -> str:
    if field.default_factory is not None:
        value: Any = field.default_factory()  # type: ignore[call-arg]
    elif field.default is PydanticUndefined:
        return "required"
    else:
        value = field.default
    if isinstance(value, BaseModel):
        return "(its defaults)"
    if isinstance(value, SecretStr):
        value = value.get_secret_value()
    if isinstance(value, enum.Enum):
        value = value.value
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[]" if not value else f"`{list(value)}`"
    if isinstance(value, dict):
        return "{}"
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    return f'`"{value}"`' if isinstance(value, str) else f"`{value}`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ") if "\\|" not in text else text


def rows(section: Section) -> tuple[list[str], list[str]]:
    """(table lines, keys without a description) of one section."""
    lines = ["| key | type | default | allowed | meaning |", "|---|---|---|---|---|"]
    missing: list[str] = []
    for name, field in section.model.model_fields.items():
        key = key_of(name, field)
        meaning = field.description or DESCRIPTIONS.get(f"{section.path}.{key}")
        if not meaning:
            missing.append(f"{section.path}.{key}")
            meaning = ""
        lines.append(f"| `{key}` | {type_text(field.annotation)} | {default_text(field)} | "
                     f"{_cell(allowed_text(field))} | {_cell(meaning)} |")
    return lines, missing


def render() -> tuple[str, list[str]]:
    """(the page, problems: keys without a description, descriptions of no key)."""
    out = [
        "# Configuration reference",
        "",
        "Every key of the device file and of the gateway file, with its type, default and",
        "allowed values. Generated from the models that load the files by",
        "`tools/gen_config_reference.py` (do not edit by hand: `make test` fails when this",
        "page and the models differ). Keys are camelCase as written here; PascalCase and",
        "snake_case spellings load too, a misspelt key is an error naming the key it",
        "resembles, and an unknown one a warning. How the keys work together:",
        "[device-files.md](device-files.md), [gateway.md](gateway.md).",
        "",
    ]
    problems: list[str] = []
    known: set[str] = set()
    for title, sections in (("The device file", DEVICE), ("The gateway file", GATEWAY)):
        out += [f"## {title}", ""]
        for section in sections:
            heading = section.path if section.path != "(top level)" else f"{title}: top level"
            out += [f"### {heading}", "", section.intro, ""]
            lines, missing = rows(section)
            out += [*lines, ""]
            problems += [f"{key}: no description (add one to the field or to DESCRIPTIONS)"
                         for key in missing]
            prefix = "(top level)" if section.model in (DeviceConfig, GatewayConfig) \
                else section.path
            known |= {f"{prefix}.{key_of(n, f)}"
                      for n, f in section.model.model_fields.items()}
    problems += [f"DESCRIPTIONS[{key!r}]: no such key in the models"
                 for key in DESCRIPTIONS if key not in known]
    out += [
        "## Keys of other formats",
        "",
        "Accepted besides the keys above and translated by the compatibility layer",
        "([migration.md](migration.md)):",
        "",
        f"- in `communication` (NG Gateway): {', '.join(f'`{k}`' for k in compat.NG_KEYS)};",
        f"- in an item (NG Gateway): {', '.join(f'`{k}`' for k in compat.NG_POINT_KEYS)};",
        f"- at the top level (NG Gateway): {', '.join(f'`{k}`' for k in compat.NG_DEVICE_KEYS)}"
        " (the item list).",
        "",
    ]
    return "\n".join(out), problems


def main(argv: list[str]) -> int:
    text, problems = render()
    for line in problems:
        print(f"gen_config_reference: {line}", file=sys.stderr)
    if problems:
        return 1
    if argv[1:] == ["--check"]:
        if not OUTPUT.exists() or OUTPUT.read_text(encoding="utf-8") != text:
            print(f"{OUTPUT.relative_to(TOP)} is out of date: run "
                  "python tools/gen_config_reference.py", file=sys.stderr)
            return 1
        return 0
    OUTPUT.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
