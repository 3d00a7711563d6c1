"""``python -m pocoloco.cli ARGS`` = ``pocoloco ARGS``."""

import sys

from pocoloco.cli import main

sys.exit(main())
