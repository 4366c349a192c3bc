"""Nominal inverse kinematics: closed form derived from the DH table, numeric fallback."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from robocal.compensation import has_closed_form, ik_solutions, nominal_fk, nominal_ik
from robocal.errors import ConfigError
from robocal.kinematics import RobotDescription, load_robot

SPHERICAL = ("fanuc_lrmate200i", "fanuc_lrmate200id", "kuka_kr210_r3100")


def _random_q(robot: RobotDescription, n: int, rng: np.random.Generator) -> np.ndarray:
    lim = robot.joint_limits
    return rng.uniform(lim[:, 0] + 0.05, lim[:, 1] - 0.05, (n, robot.dof))


def _pose_error(T1: np.ndarray, T2: np.ndarray) -> np.ndarray:
    return np.abs(T1 - T2).max(axis=(-2, -1))


def test_which_robots_have_a_closed_form() -> None:
    assert all(has_closed_form(load_robot(r)) for r in SPHERICAL)
    assert not has_closed_form(load_robot("ur10"))  # wrist axes do not intersect


@pytest.mark.parametrize("name", SPHERICAL)
def test_every_closed_form_solution_reaches_the_pose(name: str, rng: np.random.Generator
                                                     ) -> None:
    robot = load_robot(name)
    q = _random_q(robot, 300, rng)
    T = nominal_fk(robot, q)
    sols, valid = ik_solutions(robot, T, q)
    assert sols.shape == (300, 8, 6)
    assert valid.any(axis=1).all()  # the generating configuration is always among them
    Ts = nominal_fk(robot, sols.reshape(-1, 6)).reshape(300, 8, 4, 4)
    assert _pose_error(Ts, T[:, None])[valid].max() < 1e-9
    lim = robot.joint_limits
    assert np.all((sols[valid] >= lim[:, 0] - 1e-9) & (sols[valid] <= lim[:, 1] + 1e-9))
    # away from singularities the eight branches are distinct configurations
    d = np.abs(sols[:, :, None, :] - sols[:, None, :, :]).max(axis=3)
    both = valid[:, :, None] & valid[:, None, :] & ~np.eye(8, dtype=bool)
    assert np.median(d[both]) > 0.1


@pytest.mark.parametrize("name", SPHERICAL)
def test_seed_closest_solution_is_returned(name: str, rng: np.random.Generator) -> None:
    robot = load_robot(name)
    q = _random_q(robot, 300, rng)
    T = nominal_fk(robot, q)
    seed = q + rng.normal(0.0, 0.01, q.shape)
    res = nominal_ik(robot, T, seed)
    assert res.method == "closed-form" and res.found.all()
    assert _pose_error(nominal_fk(robot, res.q), T).max() < 1e-9
    # the choice is the valid solution nearest the seed ...
    d = np.where(res.valid, np.sum((res.solutions - seed[:, None]) ** 2, axis=2), np.inf)
    np.testing.assert_allclose(res.q, res.solutions[np.arange(300), d.argmin(axis=1)])
    # ... which, for a seed near the generating configuration, is that configuration
    # (except where two branches nearly meet, at a stretched elbow or a flat wrist)
    close = np.abs(res.q - q).max(axis=1) < 1e-7
    assert close.mean() > 0.95


def test_wrist_singularity_keeps_joint_4_of_the_seed() -> None:
    robot = load_robot("fanuc_lrmate200i")
    q = np.array([0.3, 0.4, 0.2, 0.7, 0.0, -0.5])   # theta5 = 0: J4 and J6 aligned
    T = nominal_fk(robot, q)
    seed = q + np.array([0.0, 0.0, 0.0, 0.25, 0.0, 0.0])
    res = nominal_ik(robot, T, seed)
    assert res.found[0]
    assert res.q[0, 3] == pytest.approx(seed[3], abs=1e-9)
    assert _pose_error(nominal_fk(robot, res.q), T).max() < 1e-9


def test_whole_turns_are_chosen_near_the_seed() -> None:
    robot = load_robot("fanuc_lrmate200i")    # J6 spans +-360 deg
    q = np.array([0.1, 0.3, -0.2, 0.4, 0.6, 5.5])
    T = nominal_fk(robot, q)
    assert nominal_ik(robot, T, q).q[0, 5] == pytest.approx(5.5, abs=1e-9)
    low = nominal_ik(robot, T, q - np.array([0, 0, 0, 0, 0, 2 * math.pi])).q[0, 5]
    assert low == pytest.approx(5.5 - 2 * math.pi, abs=1e-9)


def test_generic_dh_conventions(rng: np.random.Generator) -> None:
    """Flipped axis senses, theta offsets and a coupling: still solved in closed form."""
    base = load_robot("kuka_kr210_r3100")
    joints = []
    for i, j in enumerate(base.joints):
        joints.append(dataclasses.replace(
            j, alpha=-j.alpha if i in (0, 2, 4) else j.alpha,
            theta_offset=j.theta_offset + rng.uniform(-0.5, 0.5),
            sign=-1 if i in (1, 3) else 1,
            coupled_to=1 if i == 2 else None, coupling=0.5 if i == 2 else 0.0))
    robot = RobotDescription(name="odd", joints=tuple(joints))
    assert has_closed_form(robot)
    q = _random_q(robot, 200, rng)
    T = nominal_fk(robot, q)
    res = nominal_ik(robot, T, q + rng.normal(0, 0.01, q.shape))
    assert res.found.all()
    assert _pose_error(nominal_fk(robot, res.q), T).max() < 1e-9


def test_numeric_fallback_for_ur10(rng: np.random.Generator) -> None:
    robot = load_robot("ur10")
    q = _random_q(robot, 200, rng)
    T = nominal_fk(robot, q)
    res = nominal_ik(robot, T, q + rng.normal(0.0, 0.02, q.shape))
    assert res.method == "numeric"
    assert res.found.mean() > 0.98
    assert _pose_error(nominal_fk(robot, res.q[res.found]), T[res.found]).max() < 1e-8


def test_unreachable_pose_is_reported() -> None:
    robot = load_robot("fanuc_lrmate200i")
    T = np.eye(4)
    T[:3, 3] = [3.0, 0.0, 0.5]                      # 3 m away: beyond reach
    res = nominal_ik(robot, T, np.zeros(6))
    assert not res.found[0] and not res.reachable[0] and np.isnan(res.q[0]).all()
    num = nominal_ik(load_robot("ur10"), T, np.zeros(6))
    assert not num.found[0] and np.isnan(num.q[0]).all()


def test_bad_arguments() -> None:
    robot = load_robot("fanuc_lrmate200i")
    with pytest.raises(ConfigError, match="shape"):
        nominal_ik(robot, np.eye(3))
    with pytest.raises(ConfigError, match="seed"):
        nominal_ik(robot, np.eye(4), np.zeros(5))
    with pytest.raises(ConfigError, match="closed-form"):
        ik_solutions(load_robot("ur10"), np.eye(4))
    with pytest.raises(ConfigError, match="method"):
        nominal_ik(robot, np.eye(4), method="magic")
