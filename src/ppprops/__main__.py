"""``python -m ppprops``: the command line (``ppprops.cli.main``)."""

import sys

from .cli import main

sys.exit(main())
