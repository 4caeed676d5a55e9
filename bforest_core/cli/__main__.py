"""``python -m bforest_core.cli``: the ``bforest`` command."""

import sys

from .main import main

sys.exit(main())
