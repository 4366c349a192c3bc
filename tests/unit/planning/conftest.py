"""Shared fixtures for the planning tests: the LR Mate 200i in the demo cell."""

from __future__ import annotations

import numpy as np
import pytest

from robocal.kinematics import RobotDescription, load_robot
from robocal.planning import Cell, Feasibility, FeasibilityChecker, draw_candidates, load_cell


@pytest.fixture(scope="session")
def robot() -> RobotDescription:
    return load_robot("fanuc_lrmate200i")


@pytest.fixture(scope="session")
def demo() -> Cell:
    return load_cell("demo")


@pytest.fixture(scope="session")
def checker(robot: RobotDescription, demo: Cell) -> FeasibilityChecker:
    return FeasibilityChecker(robot, demo)


@pytest.fixture(scope="session")
def pool(checker: FeasibilityChecker) -> tuple[np.ndarray, Feasibility]:
    """About 500 feasible candidates of the LR Mate in the demo cell."""
    q, f, _ = draw_candidates(checker, target=400, seed=7)
    return q, f

