"""``python -m phantoms``: see :mod:`phantoms.cli`."""

import sys

from phantoms.cli import main

sys.exit(main())
