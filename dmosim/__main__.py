"""``python -m dmosim``: the ``dmosim`` executable, for roles started by a run and for a checkout not installed."""

import sys

from .cli.main import console

sys.exit(console())
