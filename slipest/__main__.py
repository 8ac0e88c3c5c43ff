"""``python -m slipest ...``: the ``slipest`` command (same subcommands and options)."""

import sys

from slipest.cli.main import main

if __name__ == "__main__":  # importing the module (e.g. to list the package) runs nothing
    sys.exit(main())
