"""Damped-least-squares IK, the ISO 9283 cube, and CPA single-axis sweeps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robocal.kinematics import RobotDescription
from robocal.planning import Feasibility, FeasibilityChecker, cpa_sweeps, iso_cube, solve_ik
from robocal.planning._iso import ISO_CORNERS

Pool = tuple[np.ndarray, Feasibility]


def test_ik_reaches_fk_targets_from_nearby_starts(robot: RobotDescription,
                                                  checker: FeasibilityChecker, pool: Pool,
                                                  rng: np.random.Generator) -> None:
    q_true = pool[0][:20]
    _A, _B, R, p = checker.capsules.segments(q_true)
    q0 = q_true + rng.uniform(-0.15, 0.15, q_true.shape)
    q, ok = solve_ik(robot, np.asarray(checker.tool_offset), p, R, q0)
    assert ok.all()
    _, _, R2, p2 = checker.capsules.segments(q)
    np.testing.assert_allclose(p2, p, atol=1e-6)
    np.testing.assert_allclose(R2, R, atol=1e-6)
    far = p[:1] + np.array([[5.0, 0.0, 0.0]])  # out of reach
    _, ok = solve_ik(robot, np.asarray(checker.tool_offset), far, R[:1], q_true[:1])
    assert not ok[0]


def test_iso_cube_poses(checker: FeasibilityChecker, pool: Pool) -> None:
    q, f = pool
    cube = iso_cube(checker, q, f)
    assert cube is not None and cube.side >= 0.1
    assert cube.q.shape == (5, 6) and cube.feasibility.ok.all()
    _, _, R, p = checker.capsules.segments(cube.q)
    np.testing.assert_allclose(p, cube.targets, atol=1e-6)
    np.testing.assert_allclose(p[0], cube.centre, atol=1e-12)  # P1 is the centre
    corners = cube.centre + 0.5 * cube.side * ISO_CORNERS
    diagonal = cube.side * math.sqrt(3.0)
    np.testing.assert_allclose(np.linalg.norm(p[1:] - corners, axis=1), 0.1 * diagonal,
                               atol=1e-6)
    # P2..P5 lie in one plane through two opposite edges, with the centre
    n = np.cross(p[2] - p[1], p[4] - p[1])
    assert abs(np.dot(n / np.linalg.norm(n), p[0] - p[1])) < 1e-6
    for k in range(1, 5):  # one flange orientation for all five poses
        np.testing.assert_allclose(R[k], R[0], atol=1e-6)


def test_cpa_sweeps_move_one_axis(robot: RobotDescription, checker: FeasibilityChecker,
                                  pool: Pool) -> None:
    sweeps = cpa_sweeps(checker, pool[0], points=9, rng=np.random.default_rng(3), bases=12)
    assert [s.joint for s in sweeps] == [1, 2, 3, 4, 5, 6]
    C = robot.coupling_matrix
    for s in sweeps:
        k = s.joint - 1
        theta = s.q @ C.T
        others = np.delete(theta, k, axis=1)
        np.testing.assert_allclose(others - others[0], 0.0, atol=1e-9)
        assert s.feasibility.ok.all() and len(s.q) == 9
        assert np.all(np.diff(s.q[:, k]) > 0)  # sorted along the swept joint
        width = np.ptp(theta[:, k])
        assert width == pytest.approx(s.width, abs=1e-9) and width > math.radians(20)
        steps = np.diff(np.sort(theta[:, k]))
        assert np.ptp(steps) > 1e-3  # jittered, not a regular grid
    # coupled FANUC J2/J3: sweeping axis 2 moves the controller's J3 the other way
    s2 = sweeps[1]
    np.testing.assert_allclose(np.diff(s2.q[:, 2]), -np.diff(s2.q[:, 1]), atol=1e-9)


def test_cpa_sweeps_prefer_bases_whose_points_are_reachable(
        checker: FeasibilityChecker, pool: Pool) -> None:
    rng = np.random.default_rng
    plain = cpa_sweeps(checker, pool[0], points=9, rng=rng(3), bases=12)
    # a predicate that accepts everything changes nothing
    same = cpa_sweeps(checker, pool[0], points=9, rng=rng(3), bases=12,
                      reachable=lambda q: np.ones(len(q), dtype=bool))
    for a, b in zip(plain, same, strict=True):
        np.testing.assert_array_equal(a.q, b.q)
    # the widest sweep of each joint declared unreachable: the widest reachable one at least
    # a quarter as wide is taken instead, from another base
    widest = {s.joint: s for s in plain}

    def not_the_widest(q: np.ndarray) -> np.ndarray:
        return np.array([not any(np.allclose(p, w.q[0]) or np.allclose(p, w.q[-1])
                                 for w in widest.values()) for p in q])

    other = cpa_sweeps(checker, pool[0], points=9, rng=rng(3), bases=12,
                       reachable=not_the_widest)
    assert [s.joint for s in other] == [s.joint for s in plain]
    for s in other:
        w = widest[s.joint]
        assert not np.allclose(s.q[0], w.q[0]) and s.width <= w.width + 1e-12
        assert s.width >= 0.25 * w.width and not_the_widest(s.q).all()
    # nothing reachable at all: the widest, as without the predicate (routing may detour)
    none = cpa_sweeps(checker, pool[0], points=9, rng=rng(3), bases=12,
                      reachable=lambda q: np.zeros(len(q), dtype=bool))
    for a, b in zip(plain, none, strict=True):
        np.testing.assert_array_equal(a.q, b.q)
