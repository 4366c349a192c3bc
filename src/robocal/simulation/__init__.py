"""robocal's own simulator: a virtual robot with planted errors and a virtual laser tracker.

Used by tests, the demo, benchmarks and the protocol simulators. Not a runtime dependency of
identification, compensation, planning or the daemon.
"""

from robocal.simulation._thermal import WarmUpDrift
from robocal.simulation._virtual import SCENARIOS, TrackerNoise, VirtualCell, truth_spec

__all__ = ["SCENARIOS", "TrackerNoise", "VirtualCell", "WarmUpDrift", "truth_spec"]
