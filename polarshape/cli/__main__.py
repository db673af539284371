"""``python -m polarshape.cli``: the same command line as ``polarshape``."""

import sys

from polarshape.cli import main

sys.exit(main())
