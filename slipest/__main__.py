"""``python -m slipest ...``: the ``slipest`` command (same subcommands and options)."""

import sys

from slipest.cli.main import main

sys.exit(main())
