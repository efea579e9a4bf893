"""`python -m rigctl` is the `rigctl` command."""

import sys

from rigctl.apps.cli import main

if __name__ == "__main__":  # not when a spawned worker process imports this module as its main
    sys.exit(main())
