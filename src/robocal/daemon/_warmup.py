"""When the warm-up routine has done its work: elapsed time and joint-temperature settling.

Pure bookkeeping (no I/O): the runner feeds it one reading per warm-up move and stops the
routine when :meth:`WarmupWatch.add` names a reason (ADR 0042).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

from robocal.daemon.config import WarmupConfig

__all__ = ["WarmupWatch"]


class WarmupWatch:
    """Follow the warm-up's time and temperatures against ``config``'s end conditions.

    Times are seconds on one clock (the controller's temperature timestamps, or the
    daemon's); temperatures °C per joint, empty when the robot does not read them.
    """

    def __init__(self, config: WarmupConfig) -> None:
        self.config = config
        self.t0: float | None = None
        self.elapsed_s = 0.0
        #: largest joint temperature change per minute over the settle window, once known
        self.rate_c_per_min: float | None = None
        self._history: deque[tuple[float, tuple[float, ...]]] = deque()

    def add(self, t: float, temps_c: Sequence[float]) -> str | None:
        """Record one reading; return why the routine is done, or None to go on."""
        cfg = self.config
        if self.t0 is None:
            self.t0 = t
        self.elapsed_s = t - self.t0
        temps = tuple(float(v) for v in temps_c)
        self._history.append((t, temps))
        # keep one reading at least a window old (the oldest the rate is taken against)
        while len(self._history) > 2 and t - self._history[1][0] >= cfg.settle_window_s:
            self._history.popleft()
        t_old, old = self._history[0]
        if temps and old and t - t_old >= cfg.settle_window_s:
            worst = max(abs(a - b) for a, b in zip(temps, old, strict=True))
            self.rate_c_per_min = worst / (t - t_old) * 60.0
        if self.elapsed_s >= cfg.max_s:
            return f"max_s ({cfg.max_s:g} s) reached"
        if cfg.duration_s is not None and self.elapsed_s < cfg.duration_s:
            return None
        if cfg.until_settled_c_per_min is None:
            return f"duration_s ({cfg.duration_s:g} s) reached"
        if self.rate_c_per_min is not None and self.rate_c_per_min <= cfg.until_settled_c_per_min:
            return (f"temperatures settled ({self.rate_c_per_min:.3f} degC/min <= "
                    f"{cfg.until_settled_c_per_min:g})")
        return None
