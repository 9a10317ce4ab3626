"""``python -m jaxfric``: the command line of :mod:`jaxfric.cli`."""

import sys

from .cli import main

sys.exit(main())
