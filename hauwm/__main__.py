"""`python -m hauwm ...`: the `hauwm` command (hauwm/cli.py), for an environment whose scripts are not on PATH."""

import sys

from hauwm.cli import main

sys.exit(main())
