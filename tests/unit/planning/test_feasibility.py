"""Feasibility checks: each kind of infeasible pose is rejected, margins are consistent."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robocal.errors import ConfigError
from robocal.kinematics import RobotDescription
from robocal.planning import Cell, Feasibility, FeasibilityChecker, working_ranges
from robocal.planning._geometry import point_box_distance

from .helpers import cell_with

Pool = tuple[np.ndarray, Feasibility]


def _pose(pool: Pool, k: int = 0) -> np.ndarray:
    q, f = pool
    # a comfortable pose: large margins everywhere
    score = np.minimum(f.angle_margin, 0.2) + np.minimum(f.sight_margin, 0.05) + np.minimum(
        f.collision_margin, 0.05)
    return q[np.argsort(-score, kind="stable")[k]][None, :]


def test_pool_is_feasible_and_screen_is_a_superset(checker: FeasibilityChecker, pool: Pool,
                                                   rng: np.random.Generator) -> None:
    q, f = pool
    assert len(q) >= 400 and f.ok.all()
    again = checker.check(q)
    assert again.ok.all()
    assert np.all(again.angle_margin >= 0) and np.all(again.sight_margin >= 0)
    assert np.all(again.collision_margin >= 0)
    lim = checker.ranges
    qr = rng.uniform(lim[:, 0] - 0.1, lim[:, 1] + 0.1, (3000, 6))
    full = checker.check(qr)
    screen = checker.screen(qr)
    assert np.all(screen == (full.within_limits & full.in_range & full.facing))
    assert not np.any(full.ok & ~screen)
    assert full.rejected()["facing"] > 0 and full.rejected()["within_limits"] > 0


def test_reflector_facing_away_is_rejected(robot: RobotDescription, demo: Cell,
                                          checker: FeasibilityChecker, pool: Pool) -> None:
    q = _pose(pool)
    f = checker.check(q)
    p = f.reflector[0]
    # put the tracker behind the reflector: the nest now faces away from it
    behind = 2 * p - checker.tracker
    away = FeasibilityChecker(robot, cell_with(demo, tracker={
        "position_mm": [float(v) for v in behind * 1e3]}))
    g = away.check(q)
    assert not g.ok[0] and not g.facing[0] and "facing" in g.reasons(0)
    incidence_before = checker.acceptance - f.angle_margin[0] - math.asin(
        checker.tolerance / f.range[0])
    expected = checker.acceptance - (math.pi - incidence_before) - math.asin(
        away.tolerance / g.range[0])
    assert g.angle_margin[0] == pytest.approx(expected, abs=1e-9)
    assert not away.screen(q)[0]


def test_blocked_line_of_sight_is_rejected(robot: RobotDescription, demo: Cell,
                                           checker: FeasibilityChecker, pool: Pool) -> None:
    q = _pose(pool)
    cm = checker.capsules
    A, B, _, p = cm.segments(q)
    k = cm.names.index("j2.a")  # upper arm
    m = 0.5 * (A[0, k] + B[0, k])
    u = (m - p[0]) / np.linalg.norm(m - p[0])
    tracker = m + 1.5 * u  # the beam to the reflector passes through the upper arm's axis
    blocked = FeasibilityChecker(robot, cell_with(
        demo, tracker={"position_mm": [float(v) for v in tracker * 1e3],
                       "position_tolerance_mm": 0.0},
        reflector={"acceptance_deg": 90.0}))
    f = blocked.check(q)
    assert not f.line_of_sight[0] and not f.ok[0] and "line_of_sight" in f.reasons(0)
    assert f.sight_margin[0] == pytest.approx(-(cm.radius[k] + blocked.beam_clearance), abs=1e-9)


def test_keep_out_box_that_blocks_the_beam(robot: RobotDescription, demo: Cell,
                                           checker: FeasibilityChecker, pool: Pool) -> None:
    q = _pose(pool)
    p = checker.check(q).reflector[0]
    mid = 0.5 * (p + checker.tracker)
    box = {"min_mm": [float(v) for v in (mid - 0.05) * 1e3],
           "max_mm": [float(v) for v in (mid + 0.05) * 1e3]}
    solid = FeasibilityChecker(robot, cell_with(demo, keep_out=[{**box, "blocks_beam": True}]))
    f = solid.check(q)
    assert f.outside_keep_out[0] and not f.line_of_sight[0] and not f.ok[0]
    virtual = FeasibilityChecker(robot, cell_with(demo, keep_out=[{**box, "blocks_beam": False}]))
    assert virtual.check(q).ok[0]


def test_link_inside_keep_out_box_is_rejected(robot: RobotDescription, demo: Cell,
                                              checker: FeasibilityChecker, pool: Pool) -> None:
    q = _pose(pool)
    cm = checker.capsules
    A, B, _, _ = cm.segments(q)
    k = cm.names.index("j4.d")  # forearm
    m = 0.5 * (A[0, k] + B[0, k])
    # a small box that does not touch the forearm's axis, only its surface
    axis = (B[0, k] - A[0, k]) / np.linalg.norm(B[0, k] - A[0, k])
    side = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
    off = side / np.linalg.norm(side) * (cm.radius[k] + 0.005)
    c = m + off
    box = {"min_mm": [float(v) for v in (c - 0.01) * 1e3],
           "max_mm": [float(v) for v in (c + 0.01) * 1e3], "blocks_beam": False}
    f = FeasibilityChecker(robot, cell_with(demo, keep_out=[box])).check(q)
    assert not f.outside_keep_out[0] and not f.ok[0] and f.reasons(0) == ["outside_keep_out"]
    t = np.linspace(0, 1, 4001)[:, None]
    lo, hi = np.array(box["min_mm"]) * 1e-3, np.array(box["max_mm"]) * 1e-3
    d = point_box_distance(A[0, k] + t * (B[0, k] - A[0, k]), lo, hi).min()
    assert d < cm.radius[k]
    assert f.keep_out_margin[0] == pytest.approx(d - cm.radius[k] - checker.clearance, abs=1e-5)


def test_link_below_the_floor_is_rejected(robot: RobotDescription, demo: Cell,
                                          checker: FeasibilityChecker, pool: Pool) -> None:
    q = _pose(pool)
    cm = checker.capsules
    A, B, _, _ = cm.segments(q)
    moving = ~cm.static
    lowest = float((np.minimum(A[0, moving, 2], B[0, moving, 2]) - cm.radius[moving]).min())
    high = FeasibilityChecker(robot, cell_with(demo, floor={"z_mm": (lowest + 0.02) * 1e3},
                                               keep_out=[]))
    f = high.check(q)
    assert not f.above_floor[0] and not f.ok[0] and "above_floor" in f.reasons(0)
    assert f.floor_margin[0] == pytest.approx(-0.02 - checker.clearance, abs=1e-9)
    low = FeasibilityChecker(robot, cell_with(demo, floor={"z_mm": (lowest - 0.02) * 1e3},
                                              keep_out=[]))
    assert low.check(q).floor_margin[0] == pytest.approx(0.02 - checker.clearance, abs=1e-9)
    # the static base column reaches below z = 0 but is never checked against the floor
    base = cm.names.index("j1.d")
    assert cm.static[base] and A[0, base, 2] - cm.radius[base] < low.floor_z


def test_self_collision_matches_brute_force(checker: FeasibilityChecker,
                                            rng: np.random.Generator) -> None:
    lim = checker.ranges
    q = rng.uniform(lim[:, 0], lim[:, 1], (150, 6))
    f = checker.check(q, visibility=False)
    assert np.isnan(f.angle_margin).all() and f.line_of_sight.all()
    cm = checker.capsules
    A, B, _, _ = cm.segments(q)
    s = np.linspace(0, 1, 121)
    brute = np.full(len(q), np.inf)
    for a, b in cm.pairs:
        X = A[:, a, None, :] + s[None, :, None] * (B[:, a] - A[:, a])[:, None, :]
        Y = A[:, b, None, :] + s[None, :, None] * (B[:, b] - A[:, b])[:, None, :]
        d = np.linalg.norm(X[:, :, None] - Y[:, None, :], axis=-1).min(axis=(1, 2))
        brute = np.minimum(brute, d - cm.radius[a] - cm.radius[b] - checker.clearance)
    assert np.all(f.self_margin <= brute + 1e-12) and np.all(brute - f.self_margin < 0.01)
    assert (~f.no_self_collision).sum() > 0  # random poses do fold into themselves


def test_tracker_range_and_tolerance(robot: RobotDescription, demo: Cell,
                                     checker: FeasibilityChecker, pool: Pool) -> None:
    q, _ = pool
    q = q[:50]
    base = checker.check(q)
    near = FeasibilityChecker(robot, cell_with(demo, tracker={
        "max_range_mm": float(np.median(base.range)) * 1e3}))
    f = near.check(q)
    assert np.array_equal(f.in_range, base.range <= np.median(base.range))
    loose = FeasibilityChecker(robot, cell_with(demo, tracker={"position_tolerance_mm": 300.0}))
    g = loose.check(q)
    assert np.all(g.angle_margin < base.angle_margin)
    assert np.all(g.sight_margin <= base.sight_margin + 1e-12)


def test_reflector_inside_its_own_link_is_a_config_error(robot: RobotDescription,
                                                         demo: Cell) -> None:
    fat = cell_with(demo, robot={"link_radii_mm": [60, 60, 60, 50, 50, 90]})
    with pytest.raises(ConfigError, match=r"reflector.*j6\.d.*offset_mm"):
        FeasibilityChecker(robot, fat)


def test_working_ranges(robot: RobotDescription, demo: Cell) -> None:
    r = working_ranges(robot, demo)
    # J4 (+-185 deg after the margin) and J6 (+-355) turn more than a revolution: kept whole
    # (ADR 0026; test_coverage.py covers the one_revolution option)
    expect = robot.joint_limits + np.radians([5.0, -5.0])
    np.testing.assert_allclose(r, expect)
    narrow = cell_with(demo, robot={"joint_ranges_deg": [[-30, 30]] * 6, "joint_margin_deg": 0})
    np.testing.assert_allclose(working_ranges(robot, narrow), np.radians([[-30, 30]] * 6))
    with pytest.raises(ConfigError, match="needs 6 entries"):
        working_ranges(robot, cell_with(demo, robot={"joint_ranges_deg": [[-30, 30]]}))
    with pytest.raises(ConfigError, match="joint 2: empty working range"):
        working_ranges(robot, cell_with(demo, robot={"joint_ranges_deg": [
            [-30, 30], [150, 170], [-30, 30], [-30, 30], [-30, 30], [-30, 30]]}))


def test_path_check_finds_a_box_between_two_poses(robot: RobotDescription, demo: Cell,
                                                  checker: FeasibilityChecker,
                                                  pool: Pool) -> None:
    q = _pose(pool)[0]
    qa, qb, qm = q.copy(), q.copy(), q.copy()
    qa[0] -= 0.5
    qb[0] += 0.5
    p_mid = checker.check(qm[None]).reflector[0]
    box = {"min_mm": [float(v) for v in (p_mid - 0.03) * 1e3],
           "max_mm": [float(v) for v in (p_mid + 0.03) * 1e3], "blocks_beam": False}
    boxed = FeasibilityChecker(robot, cell_with(demo, keep_out=[box]))
    ends = boxed.check(np.vstack([qa, qb]), visibility=False)
    assert ends.collision_free.all()
    assert not boxed.path_clear(qa[None], qb[None])[0]
    assert checker.path_clear(qa[None], qb[None])[0]
    assert boxed.path_clear(qa[None], qa[None])[0]  # no move, nothing to check
