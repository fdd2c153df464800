"""``python -m assets.cli``: the ``atlas-gs`` executable."""

import sys

from assets.cli import command

sys.exit(command())
