"""``python -m blurcalib``: the command line (see :mod:`blurcalib.cli`)."""

import sys

from blurcalib.cli import main

sys.exit(main())
