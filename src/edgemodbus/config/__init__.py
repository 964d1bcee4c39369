"""Configuration models of the seed's files (device file, ``modbusRtu.json``).

Invalid input raises :class:`ConfigError`, one line per problem: path, value given and
what is allowed.  The modules, each one concern:

* problems.py: :class:`Problem`, :class:`ConfigError`;
* compat.py: the key, parity and timestamp spellings accepted besides ours;
* base.py: :class:`Model` (the base of every config model), :class:`Range`,
  :class:`Choice`, :func:`load_model`;
* communication.py: :class:`DriverModbusRtuParameter`, :class:`Parity`;
* items.py: :class:`DeviceAddressItem`, :class:`ParsedItem`, :func:`validate_items`;
* device.py: :class:`DeviceOrganizationParameter`, :class:`DeviceConfig`, the loaders;
* listen.py: the listen-mode (DTU) checks and source allow-lists of the communication
  parameters;
* secret.py: secret values (:data:`Secret`), never shown, masked in ``to_dict()``;
* labels.py: the UI labels of the communication parameters (for descriptor.py).
"""

from __future__ import annotations

from .actions import (
    ACTION_FUNCTIONS,
    PARAMETER_TYPES,
    ActionParameter,
    DeviceAction,
    validate_actions,
)
from .base import (
    MAX_MS,
    MS_RANGE,
    READ_CYCLE_RANGE,
    Choice,
    Model,
    Ms,
    OptionalMs,
    Range,
    load_model,
)
from .communication import (
    AddressPrefixOption,
    DriverModbusRtuParameter,
    Framing,
    Registration,
    ReportMode,
    Rs485Mode,
    Transport,
)
from .compat import Parity
from .device import (
    DeviceConfig,
    DeviceOrganizationParameter,
    device_enabled,
    effective_parameters,
    load_communication,
    load_device_config,
    validate_parameters,
)
from .items import (
    ALLOWED_QUANTITIES,
    MOVING,
    ON_DEMAND,
    STATUSES,
    DeviceAddressItem,
    ItemFields,
    ItemReading,
    ParsedItem,
    validate_items,
)
from .labels import BAUD_RATES
from .problems import NO_VALUE, ConfigError, Problem, WrongType, join_path

__all__ = [
    "ACTION_FUNCTIONS",
    "ALLOWED_QUANTITIES",
    "BAUD_RATES",
    "MAX_MS",
    "MOVING",
    "MS_RANGE",
    "NO_VALUE",
    "ON_DEMAND",
    "PARAMETER_TYPES",
    "READ_CYCLE_RANGE",
    "STATUSES",
    "ActionParameter",
    "AddressPrefixOption",
    "Choice",
    "ConfigError",
    "DeviceAction",
    "DeviceAddressItem",
    "DeviceConfig",
    "DeviceOrganizationParameter",
    "DriverModbusRtuParameter",
    "Framing",
    "ItemFields",
    "ItemReading",
    "Model",
    "Ms",
    "OptionalMs",
    "Parity",
    "ParsedItem",
    "Problem",
    "Range",
    "Registration",
    "ReportMode",
    "Rs485Mode",
    "Transport",
    "WrongType",
    "device_enabled",
    "effective_parameters",
    "join_path",
    "load_communication",
    "load_device_config",
    "load_model",
    "validate_actions",
    "validate_items",
    "validate_parameters",
]
