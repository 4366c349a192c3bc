"""Identification edges of issue 28: the radians rule on small robots, the data digest."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.errors import DataError
from robocal.identification import FitOptions, fit
from robocal.identification._fit import looks_like_radians, sanity_check
from robocal.kinematics import ErrorModelSpec, KinematicModel, RobotDescription, load_robot
from robocal.kinematics._robot import Joint


def _al5d_like() -> RobotDescription:
    """A small 5-joint desktop arm (Lynxmotion AL5D-like proportions), limits +-120 deg."""
    lim = math.radians(120.0)
    dh = [(0.0, 0.07, math.pi / 2), (0.146, 0.0, 0.0), (0.187, 0.0, 0.0),
          (0.0, 0.0, math.pi / 2), (0.0, 0.09, 0.0)]
    joints = tuple(Joint(a=a, d=d, alpha=al, theta_offset=0.0, q_min=-lim, q_max=lim)
                   for a, d, al in dh)
    return RobotDescription(name="al5d_like", joints=joints, tool=(0.0, 0.0, 0.02))


def _measure(robot: RobotDescription, q: np.ndarray, seed: int = 0) -> MeasurementSet:
    rng = np.random.default_rng(seed)
    m = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
    p = m.positions(q, m.nominal_params()) + np.array([1.5, -0.4, 0.3])
    return MeasurementSet(q, p + rng.normal(0.0, 2e-5, p.shape))


def test_small_robot_within_114_deg_is_not_taken_for_radians() -> None:
    robot = _al5d_like()
    rng = np.random.default_rng(3)
    q = rng.uniform(-math.radians(110.0), math.radians(110.0), (60, robot.dof))
    data = _measure(robot, q)
    assert not looks_like_radians(robot, data.q)
    sanity_check(robot, data)                                   # no DataError
    res = fit(robot, data, "constant")
    assert res.train.rms_m < 1e-4
    # the same joints written in radians (read as degrees: within +-1.92 "deg") are refused
    rad = replace(data, q=data.q * (math.pi / 180.0))
    assert looks_like_radians(robot, rad.q)
    with pytest.raises(DataError, match="look like radians"):
        sanity_check(robot, rad)


def test_radians_rule_needs_a_plausible_radian_reading() -> None:
    robot = load_robot("fanuc_lrmate200i")
    rng = np.random.default_rng(4)
    lim = robot.joint_limits
    q = rng.uniform(lim[:, 0] * 0.5, lim[:, 1] * 0.5, (40, robot.dof))
    assert looks_like_radians(robot, q * (math.pi / 180.0))
    assert not looks_like_radians(robot, q)
    # a few degrees about zero, but one joint at 5.73 "deg": as radians 5.73 rad, beyond
    # J1's +-170 deg, so the radian reading is implausible and the data are degrees
    small = q * (math.pi / 180.0)
    small[:, 0] = 0.1
    assert not looks_like_radians(robot, small)
    assert not looks_like_radians(robot, np.zeros((10, robot.dof)))   # no motion: no verdict


def test_digest_covers_sigma_and_orientation_columns() -> None:
    rng = np.random.default_rng(5)
    q, p = rng.normal(size=(8, 6)), rng.normal(size=(8, 3))
    s = np.full((8, 3), 1e-5)
    bare = MeasurementSet(q, p)
    with_s = MeasurementSet(q, p, s)
    with_rot = MeasurementSet(q, p, s, rot=rng.normal(size=(8, 3)) * 0.1)
    digests = {bare.digest(), with_s.digest(), with_rot.digest(),
               MeasurementSet(q, p, 2 * s).digest(),
               replace(with_rot, rot_sigma=np.full((8, 3), 1e-4)).digest()}
    assert len(digests) == 5
    assert with_s.digest(sigma=False) == bare.digest()
    assert with_rot.digest(sigma=False, orientation=False) == bare.digest()


def test_model_digest_differs_with_and_without_sigma_columns(paper_data) -> None:
    d = paper_data
    train = replace(d.train, sigma=np.full(d.train.p.shape, 2e-5))
    with_s = fit(d.cell.robot, train, "constant").calibrated
    without = fit(d.cell.robot, d.train, "constant").calibrated
    assert with_s.data["digest"] == train.digest() != without.data["digest"]
    assert with_s.fit["options"]["use_point_sigma"] is True


def test_sigma_columns_get_the_model_error_they_leave_out(paper_data) -> None:
    """Tracker-like sigmas (a few um) far below what the constant model leaves: the fit adds
    the estimated model-error component; consistent sigmas are left as they are."""
    d = paper_data
    rng = np.random.default_rng(8)
    train = replace(d.train, sigma=rng.uniform(2e-6, 30e-6, d.train.p.shape))
    est = fit(d.cell.robot, train, "constant", validation=d.val)
    raw = fit(d.cell.robot, train, "constant", validation=d.val,
              options=FitOptions(point_sigma_floor_m=0.0))
    assert "model error in quadrature" in est.calibrated.data["sigma_source"]
    assert raw.calibrated.data["sigma_source"] == "per-point sx,sy,sz"
    assert est.variance_factor < 3.0 < 30.0 < raw.variance_factor
    assert est.validation is not None and raw.validation is not None
    assert est.validation.rms_m < raw.validation.rms_m
