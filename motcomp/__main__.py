"""``python -m motcomp``."""

import sys

from motcomp.cli import main

sys.exit(main())
