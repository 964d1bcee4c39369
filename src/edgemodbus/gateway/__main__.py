"""``python -m edgemodbus.gateway --config-dir DIR``: run the gateway service."""

import sys

from .run import main

sys.exit(main())
