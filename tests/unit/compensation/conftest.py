"""Fixtures: a calibrated model of the virtual LR Mate 200i fitted from 250 simulated poses."""

from __future__ import annotations

import pytest

from robocal.kinematics import CalibratedModel
from robocal.simulation import VirtualCell
from tests.unit.compensation._helpers import fitted_model


@pytest.fixture(scope="session")
def paper_fit() -> tuple[VirtualCell, CalibratedModel]:
    """(cell, model): paper scenario, seed 7, 250 poses (cached for the session)."""
    return fitted_model("fanuc_lrmate200i", "paper", 7)
