"""Deprecated entry point: ``python -m edgemodbus.service`` is now
``python -m edgemodbus.gateway`` (src/edgemodbus/gateway/); kept so that installed systemd
units that name the old module keep working."""

from __future__ import annotations

import sys
import warnings

from .gateway import main

if __name__ == "__main__":
    warnings.warn(
        "python -m edgemodbus.service is deprecated: use python -m edgemodbus.gateway",
        DeprecationWarning,
        stacklevel=1,
    )
    sys.exit(main())
