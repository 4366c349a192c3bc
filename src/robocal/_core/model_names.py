"""The names of robocal's error models, in one place that imports nothing heavy.

The CLI's parsers and the daemon's configuration read them without loading numpy or
identification; :data:`robocal.identification.MODELS` is this same tuple.
"""

from __future__ import annotations

from typing import Final, Literal, get_args

__all__ = ["CPA", "CPA_CLASSICAL", "DEFAULT_MODEL", "MODELS", "NOMINAL", "FitModel"]

#: An error model :func:`robocal.identification.fit` identifies, as a type.
FitModel = Literal["constant", "high-order", "auto"]
#: Those names, simplest first (``robocal fit --model``, the daemon's ``fit.models``).
MODELS: Final[tuple[FitModel, ...]] = get_args(FitModel)
#: The model fitted when none is named: ``auto`` keeps the joint-dependent terms the data
#: support (cross-validated), which is what a calibration engineer wants unless they say
#: otherwise.
DEFAULT_MODEL: Final[FitModel] = "auto"
#: The further models a campaign reports: the nominal robot with only base and reflector
#: fitted (the baseline of "% described") and Circle Point Analysis.
NOMINAL: Final = "nominal"
CPA: Final = "cpa"
#: Classical Circle Point Analysis (circle fits only), kept beside the polished ``cpa`` (ADR 0021).
CPA_CLASSICAL: Final = "cpa-classical"
