"""``python -m emdflow`` runs the ``emdflow`` command (see :mod:`emdflow.cli`)."""

import sys

from emdflow.cli import main

if __name__ == "__main__":
    sys.exit(main())
