"""``python -m dmo.cli``: the ``dmosim`` executable, for roles started by a run and for a checkout not installed."""

import sys

from .main import console

sys.exit(console())
