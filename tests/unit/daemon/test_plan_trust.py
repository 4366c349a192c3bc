"""The daemon does not sweep a plan again that it has found safe against the same robot,
cell and limits, and only that (ADR 0039)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robocal.daemon import _plan
from robocal.daemon._plan import parse_plan, unsafe_moves
from robocal.daemon.engine import limits_with_margin
from robocal.kinematics import load_robot
from robocal.planning import Cell, load_cell, plan_campaign
from tests.unit.daemon.conftest import ROBOT


@pytest.fixture(scope="module")
def plan_doc() -> _plan.CampaignPlan:
    plan = plan_campaign(ROBOT, "demo", count=12, validation=0, cpa=False, iso=False, seed=1,
                         candidates=64)
    return parse_plan(json.loads(plan.to_json()))


def test_a_verified_plan_is_remembered_for_exactly_what_was_checked(plan_doc) -> None:
    robot = load_robot(ROBOT)
    cell = load_cell("demo")
    limits = limits_with_margin(robot, 1.0)
    key = _plan._check_key(np.radians([p.q_deg for p in plan_doc.poses]),
                           np.radians(plan_doc.home_deg), robot, cell, np.asarray(limits))
    _plan._VERIFIED.pop(key, None)
    assert unsafe_moves(plan_doc, robot, cell, limits) == []
    assert key in _plan._VERIFIED                       # the next submission skips the sweep
    assert unsafe_moves(plan_doc, robot, cell, limits) == []
    # another cell (a floor at shoulder height) or narrower limits: checked afresh, refused
    d = cell.to_dict()
    d.update(floor={"z_mm": 300.0})
    low = unsafe_moves(plan_doc, robot, Cell.from_dict(d), limits)
    assert low and "floor" in low[0].reason
    q = np.array([p.q_deg for p in plan_doc.poses])
    narrow = [(lo, hi) for lo, hi in limits]
    narrow[1] = (narrow[1][0], np.radians(q[:, 1].max() - 1.0))
    assert unsafe_moves(plan_doc, robot, cell, narrow)
