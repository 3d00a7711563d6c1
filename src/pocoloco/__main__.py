"""``python -m pocoloco ARGS`` = ``pocoloco ARGS`` (e.g. ``torchrun --nproc_per_node=2 -m pocoloco train ...``)."""

import sys

from pocoloco.cli import main

sys.exit(main())
