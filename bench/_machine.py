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


def machine() -> str:
    """CPU model and count, memory, OS, Python and numpy versions (no date, no load)."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            names = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
        model = names[0] if names else model
    except OSError:
        pass
    try:
        mem = f", {os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB"
    except (ValueError, OSError, AttributeError):
        mem = ""
    return (f"{model}, {os.cpu_count()} CPUs{mem}, {platform.system()} {platform.machine()}, "
            f"{platform.python_implementation()} {platform.python_version()}, "
            f"numpy {np.__version__}")
