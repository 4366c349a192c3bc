"""The error-model names are one tuple (robocal._core.model_names), used everywhere."""

from __future__ import annotations

import subprocess
import sys
from typing import get_args

from robocal._core import model_names
from robocal.daemon.config import FitConfig, FitModel
from robocal.identification import MODELS
from robocal.planning import MODELS as PLANNING_MODELS
from robocal.report import BASELINE, KNOWN_MODELS


def test_every_user_of_the_model_names_has_the_one_tuple() -> None:
    assert model_names.MODELS == ("constant", "high-order", "auto")
    assert MODELS is model_names.MODELS and PLANNING_MODELS is MODELS
    assert model_names.DEFAULT_MODEL in MODELS
    assert FitModel is model_names.FitModel and get_args(FitModel) == MODELS
    assert FitConfig().models == MODELS
    select = get_args(FitConfig.model_fields["select"].annotation)
    assert select == (*MODELS, "best")
    assert tuple(KNOWN_MODELS) == (model_names.NOMINAL, model_names.CPA,
                                   model_names.CPA_CLASSICAL, *MODELS)
    assert BASELINE == model_names.NOMINAL


def test_the_names_module_imports_nothing_heavy() -> None:
    src = ("import sys, robocal._core.model_names\n"
           "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numpy', 'pydantic')"
           " or m.startswith('robocal._core.m')))\n")
    out = subprocess.run([sys.executable, "-c", src], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "['robocal._core.model_names']", out.stdout + out.stderr
