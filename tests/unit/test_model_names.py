"""The error-model names are one list: identification's, which the light modules spell out."""

from __future__ import annotations

from typing import get_args

from robocal.cli import _defaults
from robocal.daemon.config import FitConfig, FitModel
from robocal.identification import MODELS
from robocal.planning import MODELS as PLANNING_MODELS


def test_every_copy_of_the_model_names_equals_identifications() -> None:
    assert MODELS == ("constant", "high-order", "auto")
    assert PLANNING_MODELS is MODELS
    assert _defaults.MODELS == MODELS
    assert _defaults.DEFAULT_MODEL in MODELS
    assert get_args(FitModel) == MODELS
    assert FitConfig().models == MODELS
    select = get_args(FitConfig.model_fields["select"].annotation)
    assert select == (*MODELS, "best")
