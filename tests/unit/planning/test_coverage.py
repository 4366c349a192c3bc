"""Coverage of the joint ranges (ADR 0026): multi-turn joints, program targets, exclusions."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from robocal.kinematics import RobotDescription, load_robot
from robocal.planning import (
    Cell,
    DesignSpace,
    FeasibilityChecker,
    MotionChecker,
    Plan,
    excluded_families,
    joint_coverage,
    load_cell,
    plan_campaign,
    read_program_joints,
    winding_ranges,
    working_ranges,
)
from robocal.planning._coverage import ensure_span, required_span

from .helpers import cell_with


def test_multi_turn_joints_keep_their_whole_range_unless_the_cell_cuts_them(
        robot: RobotDescription, demo: Cell) -> None:
    full = working_ranges(robot, demo)
    np.testing.assert_allclose(np.degrees(full[5]), [-355.0, 355.0])
    np.testing.assert_allclose(np.degrees(full[3]), [-185.0, 185.0])
    cut = working_ranges(robot, cell_with(demo, robot={"one_revolution": True}))
    np.testing.assert_allclose(np.degrees(cut[[3, 5]]), [[-180.0, 180.0]] * 2)
    homed = cell_with(demo, robot={"one_revolution": True},
                      motion={"home_deg": [0, 0, 0, 0, 0, 300]})
    np.testing.assert_allclose(np.degrees(working_ranges(robot, homed)[5]), [-5.0, 355.0])


def test_a_joint_that_cannot_wind_safely_is_cut_and_the_reason_given(demo: Cell) -> None:
    lr = load_robot("fanuc_lrmate200i")
    checker = FeasibilityChecker(lr, demo)
    motion = MotionChecker(lr, demo, limits=checker.ranges)
    home = np.zeros(6)
    kept, notes = winding_ranges(motion, home, checker.ranges)
    assert notes == [] and np.allclose(kept, checker.ranges)       # the wrist winds freely
    ur = load_robot("ur10")
    checker = FeasibilityChecker(ur, demo)
    motion = MotionChecker(ur, demo, limits=checker.ranges)
    home = np.radians([0.0, -90.0, 0.0, -90.0, 0.0, 0.0])
    assert not motion.bad(home[None])[0]
    ranges, notes = winding_ranges(motion, home, checker.ranges)
    cut = [int(n[1]) for n in notes]
    assert 2 in cut and 6 not in cut            # the shoulder would pass through the floor
    for j in cut:
        assert ranges[j - 1, 1] - ranges[j - 1, 0] == pytest.approx(2 * math.pi)
    assert all("cannot turn through its whole range" in n and "planned in" in n for n in notes)
    np.testing.assert_allclose(ranges[5], checker.ranges[5])


def test_ensure_span_reaches_the_ends_and_keeps_the_holders() -> None:
    rng = np.random.default_rng(1)
    q = rng.uniform(-1.0, 1.0, (400, 3))
    inner = np.flatnonzero(np.all(np.abs(q) < 0.6, axis=1))[:20]
    need = np.array([[-0.9, 0.9]] * 3)
    out = ensure_span(q, inner, np.ones(len(q), dtype=bool), need)
    assert len(out) == len(inner) == len(np.unique(out))
    assert np.all(q[out].min(axis=0) <= -0.9) and np.all(q[out].max(axis=0) >= 0.9)
    assert len(np.setdiff1d(out, inner)) <= 6                     # at most two swaps a joint
    # forbidden candidates are never taken; the farthest allowed one then stands in
    allowed = np.abs(q[:, 0]) < 0.8
    allowed[inner] = True
    out = ensure_span(q, inner, allowed, need)
    assert allowed[out].all()
    assert q[out, 0].max() == pytest.approx(q[allowed, 0].max())


def test_required_span_includes_the_targets_with_margin() -> None:
    q = np.array([[-3.0, 0.0], [3.0, 1.0]])
    need = required_span(q, None, 0.1, share=0.9)
    np.testing.assert_allclose(need, [[-2.7, 2.7], [0.05, 0.95]])
    t = np.array([[2.8, 0.0], [2.9, 0.5]])
    need = required_span(q, t, 0.1, share=0.9)
    np.testing.assert_allclose(need[0], [-2.7, 3.0])              # clipped to the span
    np.testing.assert_allclose(need[1], [0.0, 0.95])


def test_joint_coverage_record(robot: RobotDescription) -> None:
    work = robot.joint_limits + np.radians([5.0, -5.0])
    planned = np.radians([[0, 0, 0, 0, 0, -300.0], [10, 20, 30, 40, 50, 300.0]])
    targets = np.radians([[5, 5, 5, 5, 5, 250.0], [6, 6, 6, 6, 6, 250.0]])
    rec = joint_coverage(robot, work, planned, targets, math.radians(5.0))
    assert rec[5]["planned_deg"] == [-300.0, 300.0]
    assert rec[5]["of_limits"] == pytest.approx(600 / 720, abs=1e-4)
    assert rec[5]["targets_deg"] == [250.0, 250.0] and rec[5]["targets_covered"] is True
    assert rec[0]["targets_covered"] is False                     # 6 + 5 deg > 10 deg
    assert rec[1]["targets_covered"] is True                      # [0, 11] within [0, 20]
    assert joint_coverage(robot, work, planned, None, 0.0)[5]["targets_covered"] is None


def test_read_program_joints(tmp_path: Path) -> None:
    j = tmp_path / "JOINTS.csv"
    j.write_text("q1,q2,q3,q4,q5,q6\n0,10,20,30,40,250\n1,2,3,4,5,-250\n")
    np.testing.assert_allclose(np.degrees(read_program_joints(j, dof=6))[:, 5], [250, -250])
    t = tmp_path / "TARGETS.csv"
    t.write_text("x,y,z,q1,q2,q3,q4,q5,q6\n500,0,400,0,10,20,30,40,250\n")
    np.testing.assert_allclose(np.degrees(read_program_joints(t, dof=6))[0, 5], 250.0)


def test_excluded_families_name_the_capsules(checker: FeasibilityChecker) -> None:
    rng = np.random.default_rng(3)
    lim = checker.ranges
    q = rng.uniform(lim[:, 0], lim[:, 1], (3000, 6))
    fam = excluded_families(checker, q, len(q))
    bad = int(np.count_nonzero(~checker.check(q, visibility=False).collision_free))
    assert bad > 0 and sum(int(f["candidates"]) for f in fam) == bad
    assert all(f["reason"].startswith(("self-collision of capsules", "capsule "))
               for f in fam)
    counts = [f["candidates"] for f in fam]
    assert counts == sorted(counts, reverse=True)
    assert all(len(f["joint_ranges_deg"]) == 6 for f in fam)


def test_plan_covers_j6_and_a_program_at_250_deg(tmp_path: Path) -> None:
    prog = tmp_path / "TARGETS.csv"
    prog.write_text("x,y,z,q1,q2,q3,q4,q5,q6\n600,0,400,10,20,10,0,-30,250\n"
                    "550,50,450,-10,30,0,20,30,240\n")
    robot = load_robot("fanuc_lrmate200i")
    d = robot.to_dict()
    d["joints"][5].update(min_deg=-300.0, max_deg=300.0)
    tight = RobotDescription.from_dict(d)
    plan = plan_campaign(tight, "demo", count=30, model="constant", iso=False, seed=2,
                         candidates=1024, targets=prog)
    cov = {c.joint: c for c in plan.coverage}
    assert cov[6].of_limits >= 0.9
    assert all(c.targets_covered for c in plan.coverage)
    assert plan.targets_source == str(prog)
    assert plan.excluded and plan.excluded[0].candidates > 0
    again = Plan.from_json(plan.to_json())
    assert again.coverage == plan.coverage and again.excluded == plan.excluded
    assert plan.capsules is not None and plan.capsules.source.startswith("default")
    # one revolution asked for: the program at J6 = 250 deg widens it again, with a warning
    cell = cell_with(load_cell("demo"), robot={"one_revolution": True})
    cut = plan_campaign(tight, cell, count=30, model="constant", iso=False, seed=2,
                        candidates=1024, targets=prog)
    assert any("J6 working range [-180, 180] deg widened to [-180, 260] deg" in w
               for w in cut.warnings)
    j6 = cut.coverage[5]
    assert j6.targets_covered and j6.planned_deg[0] > -181.0 and j6.planned_deg[1] >= 255.0


def test_plan_cli_prints_coverage_and_exclusions(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from robocal.cli.main import main

    prog = tmp_path / "JOINTS.csv"
    prog.write_text("q1,q2,q3,q4,q5,q6\n10,20,10,0,-30,250\n")
    rc = main(["plan", "--robot", "fanuc_lrmate200i", "--cell", "demo", "--model", "constant",
               "--count", "30", "--no-iso", "--candidates", "512", "--targets", str(prog),
               "--out", str(tmp_path / "PLAN.json")])
    out = capsys.readouterr().out
    assert rc == 0
    assert f"coverage of the calibration poses (deg), program {prog}:" in out
    assert "J6: [" in out and "targets [250, 250] covered" in out
    assert "excluded " in out and "candidates: self-collision of capsules" in out
    assert "link capsules: 48, 48, 48, 30, 30, 30 mm (default" in out


def _demo_cell_design(robot_name: str, candidates: int) -> tuple[
        RobotDescription, Cell, FeasibilityChecker, MotionChecker, np.ndarray, DesignSpace]:
    """A robot in the demo cell, its checkers, feasible candidates and their design space
    for the constant model."""
    from robocal.planning import cell_design_space, draw_candidates, model_spec

    robot = load_robot(robot_name)
    demo = load_cell("demo")
    checker = FeasibilityChecker(robot, demo)
    motion = MotionChecker(robot, demo, limits=checker.ranges)
    q, f, _ = draw_candidates(checker, target=candidates, seed=0)
    return robot, demo, checker, motion, q, cell_design_space(
        checker, model_spec(robot, "constant"), q, f)


def test_candidates_unreachable_from_home_are_counted() -> None:
    # the KR210's folded forearm: feasible poses in pockets no straight move from home reaches;
    # plan_campaign reports them as an excluded family
    from robocal.planning._campaign import _choose_poses

    robot, demo, checker, motion, q, ds = _demo_cell_design("kuka_kr210_r3100", 256)
    unreachable: list[int] = []
    cal, _ = _choose_poses(ds, motion, np.zeros(6), math.radians(90.0), count=15,
                           validation=0, seed=0, design="stratified", exchange_passes=2,
                           warnings=[], unreachable=unreachable)
    assert unreachable and len(set(unreachable)) == len(unreachable) and len(cal) == 15
    fresh = MotionChecker(robot, demo, limits=checker.ranges)     # no cached verdicts
    assert not fresh.moves_safe(np.zeros((len(unreachable), 6)), q[unreachable]).any()


def test_program_file_missing_is_one_data_error_and_semicolons_are_read(tmp_path) -> None:
    from robocal.errors import DataError
    from robocal.planning._coverage import read_program_joints

    with pytest.raises(DataError, match="file not found"):
        read_program_joints(tmp_path / "missing.csv", dof=6)
    prog = tmp_path / "TARGETS.csv"
    prog.write_text("pose_id;x;y;z;q1;q2;q3;q4;q5;q6\nA;1;2;3;0;-90;0;-90;0;250\n")
    q = read_program_joints(prog, dof=6)
    assert q.shape == (1, 6) and np.degrees(q[0, 5]) == pytest.approx(250.0)


def test_unreachable_poses_are_replaced_stratum_by_stratum() -> None:
    # a third of a UR10's candidates in the demo cell lie where no straight move from home
    # reaches: only those strata choose again, so the poses already checked stay chosen
    from robocal.planning._campaign import _choose_poses, _home, _round_deg

    robot, demo, checker, motion, q, ds = _demo_cell_design("ur10", 1024)
    unreachable: list[int] = []
    home = _round_deg(_home(robot, demo, checker.ranges))
    max_step = math.radians(demo.motion.max_joint_step_deg)
    cal, _ = _choose_poses(ds, motion, home, max_step, count=40, validation=0,
                           seed=0, design="stratified", exchange_passes=2, warnings=[],
                           unreachable=unreachable)
    assert len(unreachable) >= 8 and len(set(cal.tolist())) == 40
    assert not set(cal.tolist()) & set(unreachable)
    # each leg was checked once; choosing all strata again after each round checked 734
    # legs here, and still ended with 10 unreachable poses after its 30 rounds
    assert len(motion.leg_verdicts) == 40 + len(unreachable) <= 4 * 40
    fresh = MotionChecker(robot, demo, limits=checker.ranges)
    from robocal.planning._campaign import _legs_safe

    assert _legs_safe(fresh, home, q[cal], max_step)[0].all()


def test_kr210_cpa_sweeps_are_all_routed_in_the_demo_cell() -> None:
    # the widest J4 and J5 sweeps of the KR210 lie in a pocket no move from home reaches (the
    # forearm folded over the shoulder): routing dropped all 24 of their targets. A base whose
    # sweep points are reachable is preferred now.
    from robocal.planning import plan_campaign

    plan = plan_campaign("kuka_kr210_r3100", "demo", count=30, model="constant",
                         validation=10, cpa=True, cpa_points=12, candidates=512, iso=False,
                         seed=0)
    cpa = [p for p in plan.poses if p.purpose.startswith("cpa-")]
    assert not plan.dropped
    assert sorted({p.purpose for p in cpa}) == [f"cpa-j{j}" for j in range(1, 7)]
    assert len(cpa) == 72
