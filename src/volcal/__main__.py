"""``python -m volcal``: the ``volcal`` command line (:mod:`volcal.cli.main`)."""

import sys

from volcal.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
