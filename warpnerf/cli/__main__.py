"""``python -m warpnerf.cli ...``: the ``warpnerf`` command."""

import sys

from . import main

if __name__ == "__main__":
    sys.exit(main())
