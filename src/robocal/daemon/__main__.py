"""``python -m robocal.daemon --config FILE``."""

import sys

from robocal.daemon.main import main

if __name__ == "__main__":  # fit workers are spawned: they import this module as __mp_main__
    sys.exit(main())
