"""``python -m pipeline``: see ``pipeline.runtime.cli``."""

import sys

from pipeline.runtime.cli import main

sys.exit(main())
