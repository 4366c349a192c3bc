"""Per-model results of a report, shared by the analysis and the CPA comparison.

Apart from :mod:`robocal.report._analysis` so that :mod:`robocal.report._cpa` can name
:class:`ModelResult` without importing the analysis that imports it (ADR 0038).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from robocal.report._input import ModelEntry
from robocal.report._metrics import Described, ErrorStats

__all__ = ["ModelResult", "SetResult"]

Array = NDArray[np.float64]


@dataclass
class SetResult:
    """One model on one pose set. ``norms`` (n,) m for every pose (outliers included),
    ``inlier`` (n,) mask; ``stats``/``described`` over inliers. ``source``: data or stored."""

    stats: ErrorStats | None
    described: Described | None = None
    norms: Array | None = None
    inlier: NDArray[np.bool_] | None = None
    source: str = "data"
    baseline_stats: ErrorStats | None = None


@dataclass
class ModelResult:
    """A model and its results per pose set."""

    entry: ModelEntry
    sets: dict[str, SetResult] = field(default_factory=dict)

    @property
    def name(self) -> str:
        """Model name."""
        return self.entry.name
