"""Defaults shared by the commands, so that ``fit``, ``plan``, ``simulate`` and ``demo`` agree.

The error-model names and the default model are :mod:`robocal._core.model_names`'.
"""

from __future__ import annotations


def default_validation(count: int) -> int:
    """Held-out poses for ``count`` calibration poses: a fifth, at least 10."""
    return max(10, count // 5)


VALIDATION_HELP = "validation poses, held out from fitting (default: a fifth of the " \
                  "calibration poses, at least 10; 0 for none)"


#: One seed default for plan, simulate and demo (and the simulators, robocal sim): the same
#: seed names the same virtual robot and the same plan everywhere.
DEFAULT_SEED = 1

SCENARIO_HELP = ("planted truth: nominal, constant, paper (constant + joint-dependent harmonics "
                 "and pitch), strain-wave (paper + gear ripple), fine-map (fine joint-angle "
                 "errors, gravity torsion); default paper")
