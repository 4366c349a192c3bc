"""Defaults shared by the commands, so that ``fit``, ``plan``, ``simulate`` and ``demo`` agree."""

from __future__ import annotations

#: Error models a user can ask for, and the one used when none is named: ``auto`` chooses the
#: joint-dependent terms the data support (cross-validated), which is what a calibration
#: engineer wants unless they say otherwise. The home of the list is
#: ``robocal.identification.MODELS``; it is spelled out here because ``robocal --help`` must
#: not import numpy (tests/unit/test_model_names.py checks that the two agree).
MODELS = ("constant", "high-order", "auto")
DEFAULT_MODEL = "auto"


def default_validation(count: int) -> int:
    """Held-out poses for ``count`` calibration poses: a fifth, at least 10."""
    return max(10, count // 5)


VALIDATION_HELP = "validation poses, held out from fitting (default: a fifth of the " \
                  "calibration poses, at least 10; 0 for none)"
