"""``python -m firmware_py`` — the same as the ``emdflowd`` console script."""

import sys

from .cli import main

sys.exit(main())
