"""``python -m robocal.drivers.sim ...``: the same as ``robocal sim ...``."""

import sys

from robocal.drivers.sim import main

sys.exit(main())
