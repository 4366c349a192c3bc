"""plan_campaign end to end, and the PLAN.json model (round trip, errors, fuzzing)."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robocal.errors import ConfigError
from robocal.identification import min_poses
from robocal.kinematics import RobotDescription
from robocal.planning import Cell, FeasibilityChecker, Plan, plan_campaign

from .helpers import cell_with


@pytest.fixture(scope="module")
def plan() -> Plan:
    return plan_campaign("fanuc_lrmate200i", "demo", count=30, validation=10, cpa=True,
                         cpa_points=5, seed=3, candidates=512, iso_cycles=3)


def test_plan_contents(plan: Plan) -> None:
    assert plan.format == "robocal.plan/1" and plan.seed == 3
    assert plan.robot.name == "fanuc_lrmate200i" and plan.cell.name == "demo"
    assert plan.cell_source == "builtin:demo" and plan.model.name == "constant"
    assert plan.count("calibration") == 30 and plan.count("validation") == 10
    assert plan.count("cpa") == 30 and plan.count("iso") == 15
    # ISO 9283: P1..P5 in order, once per cycle
    assert [p.purpose for p in plan.poses if p.purpose.startswith("iso")] == [
        f"iso-P{k}" for k in range(1, 6)] * 3
    assert plan.iso9283 is not None and plan.iso9283.cycles == 3
    assert [c.joint for c in plan.cpa] == [1, 2, 3, 4, 5, 6]
    assert [p.index for p in plan.poses] == list(range(len(plan.poses)))
    assert plan.iso9283 is not None and plan.iso9283.side_mm > 100
    o = plan.observability.calibration
    assert o.poses == 30 and o.identifiable == 27 and o.min_poses == min_poses(27) == 11
    assert plan.observability.random_baseline is not None
    assert o.O1 > plan.observability.random_baseline.O1
    assert plan.candidates.feasible >= 512
    assert plan.motion.blocked_moves == 0 and not plan.dropped
    # J6 turns the reflector about the flange axis: radius = its offset from that axis
    j6 = next(c for c in plan.cpa if c.joint == 6)
    assert j6.radius_mm == pytest.approx(math.hypot(30.0, 20.0), abs=1e-3)
    assert "CPA circle of joint 6 has a radius of only 36 mm (< 100)" in " ".join(plan.warnings)
    for c in plan.cpa:
        short = c.span_deg[1] - c.span_deg[0] < 90.0
        assert (f"CPA sweep of joint {c.joint} spans only" in " ".join(plan.warnings)) == short
    assert all(w.startswith("CPA ") for w in plan.warnings)
    assert plan.model.design == "stratified"
    assert plan.model.design_note.startswith("stratified, D-optimal for the constant model")


def test_designs_differ_and_a_wrong_design_is_refused() -> None:
    kw: dict[str, Any] = dict(count=30, validation=5, seed=3, candidates=512, iso=False)
    d = plan_campaign("fanuc_lrmate200i", "demo", design="d-optimal", **kw)
    s = plan_campaign("fanuc_lrmate200i", "demo", **kw)
    assert d.model.design == "d-optimal" and "plain D-optimal" in d.model.design_note
    assert d.joint_targets("calibration").tolist() != s.joint_targets("calibration").tolist()
    # D-optimal maximises the information; stratification gives a little of it up
    o_d, o_s = d.observability.calibration.O1, s.observability.calibration.O1
    assert o_s <= o_d and o_s > 0.9 * o_d
    with pytest.raises(ConfigError, match="unknown design 'best'"):
        plan_campaign("fanuc_lrmate200i", "demo", design="best", **kw)


def test_plans_written_before_designs_existed_read_as_d_optimal(plan: Plan) -> None:
    doc = json.loads(plan.to_json())
    del doc["model"]["design"], doc["model"]["design_note"]
    old = Plan.from_json(json.dumps(doc))
    assert old.model.design == "d-optimal" and old.model.design_note == ""


def test_validation_is_disjoint_from_calibration(plan: Plan) -> None:
    cal = {tuple(p.joints_deg) for p in plan.poses if p.purpose == "calibration"}
    val = {tuple(p.joints_deg) for p in plan.poses if p.purpose == "validation"}
    assert len(cal) == 30 and len(val) == 10 and not cal & val


def test_every_planned_pose_passes_the_checks(robot: RobotDescription, plan: Plan) -> None:
    checker = FeasibilityChecker(robot, plan.cell)
    q = plan.joint_targets()
    f = checker.check(q)
    measured = np.array([p.measure for p in plan.poses])
    assert f.ok[measured].all()
    assert f.collision_free.all()  # via-points too
    for p, m in zip(plan.poses, measured, strict=True):
        assert p.collision_margin_mm >= 0 and p.move_clear
        if m:
            assert p.angle_margin_deg is not None and p.angle_margin_deg >= 0
            assert p.sight_margin_mm is not None and p.sight_margin_mm >= 0
        else:
            assert p.purpose == "via" and p.angle_margin_deg is None
    np.testing.assert_allclose([p.reflector_mm for p in plan.poses], f.reflector * 1e3,
                               atol=1e-3)
    # every move, including the first from home, respects the maximum joint step
    home = np.radians(plan.motion.home_deg)
    steps = np.abs(np.diff(np.vstack([home[None], q]), axis=0)).max(axis=1)
    assert np.degrees(steps).max() <= plan.motion.max_joint_step_deg + 1e-6
    assert plan.motion.via_points == plan.count("via") > 0
    assert checker.path_clear(np.vstack([home[None], q[:-1]]), q).all()


def test_plans_are_deterministic(plan: Plan, tmp_path: Path) -> None:
    again = plan_campaign("fanuc_lrmate200i", "demo", count=30, validation=10, cpa=True,
                          cpa_points=5, seed=3, candidates=512, iso_cycles=3)
    assert again.to_json() == plan.to_json()
    other = plan_campaign("fanuc_lrmate200i", "demo", count=30, seed=4, candidates=512, iso=False)
    assert other.joint_targets("calibration").tolist() != plan.joint_targets(
        "calibration").tolist()
    assert other.iso9283 is None and other.count("iso") == 0


def test_save_and_load_round_trip(plan: Plan, tmp_path: Path) -> None:
    f = tmp_path / "PLAN.json"
    plan.save(f)
    assert Plan.load(f) == plan
    assert f.read_text() == plan.to_json()
    assert [p.name for p in tmp_path.iterdir()] == ["PLAN.json"]  # no temporary left
    plan.save(f)  # overwrite in place
    assert Plan.load(f) == plan
    with pytest.raises(ConfigError, match="directory does not exist"):
        plan.save(tmp_path / "nope" / "PLAN.json")
    np.testing.assert_allclose(plan.joint_targets("cpa").shape, (30, 6))


@pytest.mark.parametrize(("mutate", "match"), [
    (lambda d: d.update(format="robocal.plan/2"), "unsupported plan format"),
    (lambda d: d.update(colour="red"), "key 'colour': unknown key"),
    (lambda d: d["poses"][1].update(speed=3), r"key 'poses\[2\].speed': unknown key"),
    (lambda d: d["cell"]["tracker"].update(height=3), r"key 'cell.tracker.height'"),
    (lambda d: d["poses"][0]["joints_deg"].pop(), r"poses\[1\] has 5 joints"),
    (lambda d: d["poses"][0].update(purpose="warmup"), r"key 'poses\[1\].purpose'"),
    (lambda d: d["poses"][0].update(index=7), r"poses\[1\].index is 7"),
    (lambda d: d["poses"][0].update(purpose="via", measure=True), "via-points are not measured"),
    (lambda d: d.pop("poses"), "key 'poses': required key is missing"),
    (lambda d: d["poses"][0].update(range_mm=float("nan")), r"poses\[1\].range_mm"),
])
def test_invalid_plans_are_rejected_naming_the_key(plan: Plan, mutate: Any, match: str) -> None:
    d = plan.model_dump(mode="json")
    mutate(d)
    with pytest.raises(ConfigError, match=match):
        Plan.from_json(json.dumps(d), source="PLAN.json")


def test_load_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        Plan.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ConfigError, match=r"bad\.json: not valid JSON"):
        Plan.load(bad)
    bad.write_text("[1, 2]")
    with pytest.raises(ConfigError, match="must be a JSON object"):
        Plan.load(bad)


def test_bad_requests_are_config_errors(demo: Cell) -> None:
    with pytest.raises(ConfigError, match="count 5 is below the 11 poses"):
        plan_campaign("fanuc_lrmate200i", demo, count=5, candidates=256)
    with pytest.raises(ConfigError, match="count must be at least 1"):
        plan_campaign("fanuc_lrmate200i", demo, count=0)
    with pytest.raises(ConfigError, match="validation must not be negative"):
        plan_campaign("fanuc_lrmate200i", demo, count=10, validation=-1)
    with pytest.raises(ConfigError, match="unknown error model"):
        plan_campaign("fanuc_lrmate200i", demo, count=10, model="quadratic")
    with pytest.raises(ConfigError, match="at least 3 points"):
        plan_campaign("fanuc_lrmate200i", demo, count=10, cpa=True, cpa_points=2)
    with pytest.raises(ConfigError, match="home_deg needs 6"):
        plan_campaign("fanuc_lrmate200i", cell_with(demo, motion={"home_deg": [0, 0]}),
                      count=10)
    with pytest.raises(ConfigError, match="must stand above the floor"):
        cell_with(demo, tracker={"position_mm": [1000.0, 0.0, -700.0]})
    wall = {"name": "wall", "min_mm": [1000.0, -5000.0, -600.0],
            "max_mm": [1100.0, 5000.0, 5000.0]}
    hidden = cell_with(demo, keep_out=[wall])
    with pytest.raises(ConfigError, match=r"only 0 of 4096 candidate poses are feasible.*"
                                          r"line_of_sight"):
        plan_campaign("fanuc_lrmate200i", hidden, count=10, candidates=64, max_draws=4096)


# -- fuzzing the plan parser ---------------------------------------------------------------------
leaf = st.none() | st.booleans() | st.integers(-3, 3) | st.floats(allow_nan=False) | st.text(
    max_size=5)


def _paths(d: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix]
    if isinstance(d, dict):
        for k, v in d.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(d, list):
        for i, v in enumerate(d[:3]):
            out += _paths(v, (*prefix, i))
    return out


@settings(max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_mutated_plans_give_a_plan_or_one_config_error(plan: Plan, data: st.DataObject) -> None:
    base = plan.model_dump(mode="json")
    base["poses"] = base["poses"][:4]
    doc = copy.deepcopy(base)
    for _ in range(data.draw(st.integers(1, 3))):
        paths = [p for p in _paths(doc) if p]
        path = data.draw(st.sampled_from(paths))
        parent = doc
        for k in path[:-1]:
            parent = parent[k]
        action = data.draw(st.sampled_from(["replace", "delete", "add"]))
        if action == "replace":
            parent[path[-1]] = data.draw(leaf)
        elif action == "delete" and isinstance(parent, dict):
            del parent[path[-1]]
        elif action == "add" and isinstance(parent, dict):
            parent[data.draw(st.text(min_size=1, max_size=6))] = data.draw(leaf)
    try:
        text = json.dumps(doc)
    except ValueError:  # pragma: no cover - inf is not JSON
        return
    try:
        p = Plan.from_json(text, source="fuzz.json")
    except ConfigError as err:
        assert str(err).startswith("fuzz.json") and "\n" not in str(err)
    else:
        assert isinstance(p, Plan) and all(math.isfinite(v) for q in p.poses
                                           for v in q.joints_deg)
