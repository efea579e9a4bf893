"""`python -m rigctl` is the `rigctl` command."""

import sys

from rigctl.cli import main

sys.exit(main())
