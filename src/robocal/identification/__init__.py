"""Identification: maximum-likelihood fits of constant and high-order error models.

Public API::

    from robocal.identification import fit, FitOptions, FitResult, accuracy, Accuracy
    res = fit(robot, data, "constant" | "high-order" | "auto", options=..., validation=...)
    res.calibrated.save("MODEL.json")

plus :func:`min_poses` (fewest poses a fit accepts; the planner uses it),
:func:`thermal_shift` (what ``auto``'s thermal term adds at given joint temperatures),
:func:`at_temperatures` (the model with that term folded in, for compensation),
:func:`identifiability`, :func:`extrapolation` (poses a fit leaves nearly free),
:func:`refit_frozen` (re-use joint-dependent terms on a new
session), :func:`cpa_fit` (Circle Point Analysis baseline, classical and polished; the internal
``_cpa.cpa_sweeps`` makes sweep joint sets for the virtual robot in tests) and
:func:`load_ipa_series` (public UR10 data set).
"""

from robocal.identification._cpa import (
    CPA_MAX_NOISE_RATIO,
    CPA_MIN_ARC_DEG,
    CPA_MIN_RADIUS_MM,
    CircleFit,
    CPAPolish,
    CPAResult,
    cpa_fit,
    poe_positions,
)
from robocal.identification._engine import min_poses
from robocal.identification._fit import (
    MODELS,
    FitResult,
    fit,
    refit_frozen,
    sanity_check,
)
from robocal.identification._fitter import FitOptions
from robocal.identification._metrics import (
    BASELINE_DESCRIPTION,
    Accuracy,
    Extrapolation,
    accuracy,
    extrapolation,
)
from robocal.identification._solver import Identifiability, identifiability
from robocal.identification._thermal import at_temperatures, thermal_shift, thermal_term
from robocal.identification._weights import TrackerSigma, whitening
from robocal.identification.datasets import load_ipa_series

__all__ = [
    "BASELINE_DESCRIPTION",
    "CPA_MAX_NOISE_RATIO",
    "CPA_MIN_ARC_DEG",
    "CPA_MIN_RADIUS_MM",
    "MODELS",
    "Accuracy",
    "CPAPolish",
    "CPAResult",
    "CircleFit",
    "Extrapolation",
    "FitOptions",
    "FitResult",
    "Identifiability",
    "TrackerSigma",
    "accuracy",
    "at_temperatures",
    "cpa_fit",
    "extrapolation",
    "fit",
    "identifiability",
    "load_ipa_series",
    "min_poses",
    "poe_positions",
    "refit_frozen",
    "sanity_check",
    "thermal_shift",
    "thermal_term",
    "whitening",
]
