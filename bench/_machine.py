"""The line every bench script prints first: date, machine and load of the run."""

from __future__ import annotations

import os
import platform
import time

import numpy as np


def header() -> str:
    """Date (UTC), CPU count, Python and numpy versions, and the load average."""
    load = os.getloadavg()
    return (f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {platform.machine()} "
            f"{os.cpu_count()} CPUs, {platform.python_implementation()} "
            f"{platform.python_version()}, numpy {np.__version__}; load average "
            f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}")
