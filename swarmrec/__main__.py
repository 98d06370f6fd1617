"""``python -m swarmrec``: the same command line as ``swarmrec``."""

import sys

from swarmrec.cli import main

sys.exit(main())
