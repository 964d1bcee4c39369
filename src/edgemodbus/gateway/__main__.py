"""``python -m edgemodbus.gateway --config-dir DIR``: run the gateway service."""

import sys

from .service import main

sys.exit(main())
