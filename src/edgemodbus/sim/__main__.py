"""``python -m edgemodbus.sim``: the same as ``edgemodbus simulate``."""

from __future__ import annotations

import sys

from .cli import main

sys.exit(main())
