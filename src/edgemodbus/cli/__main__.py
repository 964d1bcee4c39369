"""``python -m edgemodbus.cli``: the ``edgemodbus`` command."""

import sys

from . import main

sys.exit(main())
