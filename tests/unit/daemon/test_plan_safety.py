"""Campaign start refuses plans with unsafe moves; PLAN.json is validated strictly."""

from __future__ import annotations

import copy
import json
from typing import Any

import pytest

from robocal.daemon._plan import parse_plan
from robocal.errors import ConfigError
from robocal.planning import Cell, load_cell, plan_campaign
from tests.unit.daemon.conftest import ROBOT
from tests.unit.planning.helpers import to_toml

# an LR Mate pose reaching ~290 mm below its base plate, inside the limits
THROUGH_TABLE = [0.0, 146.0, -105.0, 0.0, 20.0, 0.0]


@pytest.fixture(scope="module")
def table_plan() -> dict[str, Any]:
    """A planner-made plan for a cell whose floor (a table top) is 150 mm below the base."""
    d = load_cell("demo").to_dict()
    d.update(name="table", floor={"z_mm": -150.0}, keep_out=[d["keep_out"][1]])
    plan = plan_campaign(ROBOT, Cell.from_dict(d), count=12, validation=2, cpa=False,
                         iso=False, seed=0, candidates=64)
    return json.loads(plan.to_json())


def with_pose(doc: dict[str, Any], k: int, q: list[float]) -> dict[str, Any]:
    out = copy.deepcopy(doc)
    out["poses"][k]["joints_deg"] = q
    assert out["poses"][k]["move_clear"] is True  # the file's own flag claims it is fine
    return out


async def test_planned_campaign_is_accepted(service, table_plan) -> None:
    svc = await service()
    st = await svc.create(table_plan, actor="test", start=False)
    measured = sum(p["measure"] for p in table_plan["poses"])
    assert st["state"] == "created" and st["poses_total"] == measured == 14


async def test_pose_through_the_floor_is_refused_and_named(service, table_plan) -> None:
    svc = await service()
    k = next(i for i, p in enumerate(table_plan["poses"]) if p["purpose"] == "calibration"
             and i > 2)
    bad = with_pose(table_plan, k, THROUGH_TABLE)
    with pytest.raises(ConfigError) as err:
        await svc.create(bad, actor="test")
    msg = str(err.value)
    # both moves touching it are named, with the reason and the joints in degrees
    assert f"pose {k} (calibration): capsule" in msg and "floor" in msg
    assert f"pose {k + 1} (" in msg and "2 unsafe move(s) in cell 'table'" in msg
    assert "[0.00, 146.00, -105.00, 0.00, 20.00, 0.00] deg" in msg
    assert svc.list() == []                       # nothing was created, nothing moved


async def test_the_daemons_cell_wins_over_the_plans(service, table_plan, tmp_path) -> None:
    # a plan that moves its own floor away cannot switch the check off
    k = next(i for i, p in enumerate(table_plan["poses"]) if p["purpose"] == "calibration"
             and i > 2)
    bad = with_pose(table_plan, k, THROUGH_TABLE)
    bad["cell"]["floor"]["z_mm"] = -5000.0
    toml = tmp_path / "table.toml"
    toml.write_text(to_toml(Cell.model_validate(table_plan["cell"]).to_dict()))
    svc = await service(cell=str(toml))
    with pytest.raises(ConfigError, match=rf"pose {k} \(calibration\): capsule .* floor"):
        await svc.create(bad, actor="test")
    # without a cell of its own the daemon can only take the plan's (moved) floor
    other = await service(data_dir=str(tmp_path / "other"))
    st = await other.create(bad, actor="test", start=False)
    assert st["state"] == "created"


def test_plans_are_validated_strictly(table_plan) -> None:
    doc = copy.deepcopy(table_plan)
    doc["poses"][0]["q_deg"] = doc["poses"][0].pop("joints_deg")
    with pytest.raises(ConfigError, match=r"poses\[1\]\.joints_deg.*required key is missing"):
        parse_plan(doc)                            # no second spelling of the joint targets
    doc = copy.deepcopy(table_plan)
    del doc["motion"]
    with pytest.raises(ConfigError, match=r"motion.*required key is missing"):
        parse_plan(doc)
    doc = copy.deepcopy(table_plan)
    doc["format"] = "robocal.plan/0"
    with pytest.raises(ConfigError, match="unsupported plan format"):
        parse_plan(doc)
    with pytest.raises(ConfigError, match="not valid JSON"):
        parse_plan("{")
    ok = parse_plan(json.dumps(table_plan))
    assert ok.cell is not None and ok.cell.name == "table"
    assert ok.home_deg == tuple(table_plan["motion"]["home_deg"])
    bare = {"poses": [{"joints_deg": [0.0] * 6}]}
    with pytest.raises(ConfigError, match=r"poses\[1\]\.q_deg'?: required key is missing"):
        parse_plan(bare, strict=False)
