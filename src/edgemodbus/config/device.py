"""The device file: the organisation record (its timing fields override
communication's), :class:`DeviceConfig`, and the loaders of the seed's files."""

from __future__ import annotations

import os
from collections.abc import Mapping
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any, ClassVar

from pydantic import ConfigDict, Field, field_validator, model_validator

from .actions import DeviceAction, validate_actions
from .base import READ_CYCLE_RANGE, Model, OptionalMs, field_checks, load_model, recheck
from .communication import DriverModbusRtuParameter
from .compat import NG_DEVICE_KEYS, iso_timestamp, ng_batch_defaults, ng_device
from .item_cache import cached_items, expect, json_source, keep, list_key
from .items import DeviceAddressItem, ParsedItem, validate_items
from .keys import unknown_count
from .limits import MAX_NAME
from .problems import ConfigError
from .templates import apply_template, device_loading


class DeviceOrganizationParameter(Model):
    """The device's organisation record; its timing fields override communication's."""

    _where: ClassVar[str] = "organization"
    _max_lengths: ClassVar[dict[str, int]] = {
        "deviceId": MAX_NAME, "deviceCode": MAX_NAME, "deviceName": MAX_NAME}

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
        return iso_timestamp(value)


_OVERRIDES = ("read_cycle", "connect_timeout", "reconnect_interval")


def effective_parameters(
    org: DeviceOrganizationParameter | None, comm: DriverModbusRtuParameter
) -> DriverModbusRtuParameter:
    """``comm`` with the organisation's readCycle/connectTimeout/reconnectInterval
    applied where set: a copy when the organisation sets one, else ``comm`` itself (a
    copy of its 60-odd fields is 2.3 kB per device: docs/scale.md "Memory per DTU")."""
    update = (
        {}
        if org is None
        else {name: getattr(org, name) for name in _OVERRIDES if getattr(org, name) is not None}
    )
    return comm.model_copy(update=update) if update else comm


def device_enabled(org: DeviceOrganizationParameter | None, comm: DriverModbusRtuParameter) -> bool:
    """A device is polled when the organisation (if it says) and communication enable it."""
    org_ok = org is None or org.is_enable is None or org.is_enable
    return bool(org_ok and comm.is_enable)


_COMM_CHECKS = field_checks(DriverModbusRtuParameter)
_ORG_CHECKS = field_checks(DeviceOrganizationParameter)


def validate_parameters(
    org: DeviceOrganizationParameter | None, comm: DriverModbusRtuParameter
) -> None:
    """Check the organisation's and communication's field limits on the values they hold
    now; raise one ConfigError (``communication.readCycle ...``) listing every problem."""
    problems = [] if org is None else recheck(org, _ORG_CHECKS, "organization")
    problems += recheck(comm, _COMM_CHECKS, "communication")
    if problems:
        raise ConfigError(problems)


class DeviceConfig(Model):
    """A whole device file: driver type, organisation, communication, address list."""

    # communication.registrationKey is a secret: pydantic's own error text must not show
    # the input (ConfigError's lines mask it)
    model_config = ConfigDict(hide_input_in_errors=True)  # merged with Model's

    _extra_keys: ClassVar[tuple[str, ...]] = NG_DEVICE_KEYS

    driver_type: str = "DriverModbusRtu"
    template: str | None = Field(
        default=None, description="The device template applied (config/templates.py)")
    template_dirs: list[str] = Field(
        default_factory=list,
        description="Folders searched for templates first (relative to the device file)")
    organization: DeviceOrganizationParameter = Field(default_factory=DeviceOrganizationParameter)
    communication: DriverModbusRtuParameter = Field(default_factory=DriverModbusRtuParameter)
    address_list: list[DeviceAddressItem] = Field(default_factory=list)
    actions: list[DeviceAction] = Field(default_factory=list)

    @model_validator(mode="before")
    @classmethod
    def _nested_keys(cls, data: Any) -> Any:
        """Warn about unknown nested keys with their full paths before pydantic sees them."""
        if not isinstance(data, Mapping):
            return data
        data = cls.normalize_keys(data, "")
        ng_points = "points" in data
        data = ng_device(data)
        for key, model in (
            ("organization", DeviceOrganizationParameter),
            ("communication", DriverModbusRtuParameter),
        ):
            if isinstance(data.get(key), Mapping):
                data[key] = model.normalize_keys(data[key], key, key)
        data = apply_template(data)
        if ng_points and isinstance(data.setdefault("communication", {}), dict) and \
                "maxBatch" not in data["communication"]:
            ng_batch_defaults(data["communication"])  # NG's points: NG's read sizes
        items = data.get("addressList")
        text = list_key(items) if isinstance(items, list) else None
        cached = None if text is None else cached_items(text)
        if cached is not None:  # the same list validated before (item_cache.py)
            data["addressList"] = cached
        elif isinstance(items, list):
            before = unknown_count()
            data["addressList"] = [
                DeviceAddressItem.normalize_keys(it, f"addressList[{i}]", f"addressList[{i}]")
                if isinstance(it, Mapping)
                else it
                for i, it in enumerate(items)
            ]
            # a list with unknown keys is not kept: a file loading it again is told them
            expect(text if before is not None and unknown_count() == before else None)
        return data

    @model_validator(mode="after")
    def _items(self) -> DeviceConfig:
        parsed = validate_items(self.address_list, self.communication)
        if self.actions:
            validate_actions(self.actions, parsed)
        keep(self.address_list)  # the file is valid: its list is one to share
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


def load_device_config(source: str | os.PathLike[str] | Mapping[str, Any]) -> DeviceConfig:
    """Load a device file: a path, a str of JSON text, or a dict.  Raises ConfigError.
    A ``template`` is applied (templates.py; ``templateDirs`` are relative to the
    file's folder)."""
    with device_loading(source), json_source(not isinstance(source, Mapping)):
        return load_model(DeviceConfig, source)


def load_device_file(path: str | os.PathLike[str], data: Mapping[str, Any]) -> DeviceConfig:
    """:func:`load_device_config` of the file at ``path`` that the caller has read and
    decoded (``data``, by config/jsonfile.py's rules): the same result and errors
    (gateway/bulk.py reads a file once for its digest and its load)."""
    with device_loading(Path(path)), json_source(True):  # a path, whatever its name
        return load_model(DeviceConfig, data, checked=True)


def load_communication(
    source: str | os.PathLike[str] | Mapping[str, Any],
) -> DriverModbusRtuParameter:
    """Load communication parameters alone (the seed's ``modbusRtu.json``)."""
    return load_model(DriverModbusRtuParameter, source)
