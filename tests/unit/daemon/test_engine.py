"""The executor's reading validation: the aligned prediction and the retry rules."""

from __future__ import annotations

import numpy as np

from robocal.daemon.engine import Predictor, limits_with_margin
from robocal.kinematics import ErrorModelSpec, KinematicModel, euler_xyz_to_matrix, load_robot


def _cell(seed: int = 0):
    robot = load_robot("fanuc_lrmate200i")
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = euler_xyz_to_matrix(0.01, -0.02, 2.5)
    T[:3, 3] = [1.8, 0.3, -0.4]
    model = KinematicModel(robot, ErrorModelSpec(robot.dof, ()), T)
    x = model.nominal_params()
    lim = robot.joint_limits
    q = rng.uniform(lim[:, 0] + 0.2, lim[:, 1] - 0.2, (20, robot.dof))
    return robot, q, model.positions(q, x)


def test_predictor_aligns_the_nominal_model_to_the_tracker():
    robot, q, p = _cell()
    pred = Predictor(robot, min_poses=6)
    for i in range(5):
        assert pred.distance(q[i], p[i]) is None
        pred.add(q[i], p[i])
    pred.add(q[5], p[5])
    assert pred.distance(q[6], p[6]) < 1e-9
    assert abs(pred.distance(q[7], p[7] + [0.0, 0.02, 0.0]) - 0.02) < 1e-9


def test_a_primed_predictor_answers_near_planned_poses_without_calling_the_model():
    """Planned poses predicted in one batch; actual joints a little off the plan get the same
    distances (to 0.1 µm) as the model called pose by pose, without a single-pose call."""
    robot, q, p = _cell()
    q_act = q + np.random.default_rng(3).normal(0.0, 1e-4, q.shape)
    plain, primed = Predictor(robot, min_poses=6), Predictor(robot, min_poses=6)
    primed.prime(q)
    calls = []
    model_call = primed._predict
    primed._predict = lambda x: calls.append(np.shape(x)) or model_call(x)
    for i in range(len(q)):
        a, b = plain.distance(q_act[i], p[i]), primed.distance(q_act[i], p[i])
        assert (a is None) == (b is None) and (a is None or abs(a - b) < 1e-7)
        plain.add(q_act[i], p[i])
        primed.add(q_act[i], p[i])
    assert calls == []
    assert len(primed) == len(q)
    far = q[0] + 0.1  # beyond the first-order step: the model answers
    assert abs(primed.distance(far, p[0]) - plain.distance(far, p[0])) < 1e-7
    assert calls == [(robot.dof,)]


def test_a_primed_predictor_out_of_plan_order_finds_the_right_pose():
    """Readings usually come in plan order (the next planned row is tried first); out of
    order, or repeated, they still get the prediction of their own planned pose."""
    robot, q, p = _cell(1)
    q_act = q + np.random.default_rng(4).normal(0.0, 1e-4, q.shape)
    plain, primed = Predictor(robot, min_poses=6), Predictor(robot, min_poses=6)
    primed.prime(q)
    order = [*range(8), 15, 3, 19, 0, 9, 9, 10]
    for i in order:
        plain.add(q_act[i], p[i])
        primed.add(q_act[i], p[i])
        a, b = plain.distance(q_act[i], p[i]), primed.distance(q_act[i], p[i])
        assert (a is None) == (b is None) and (a is None or abs(a - b) < 1e-7)
        assert np.allclose(primed._model_point(q_act[i]), plain._model_point(q_act[i]),
                           atol=1e-7)


def test_limits_with_margin():
    robot = load_robot("fanuc_lrmate200i")
    lim = limits_with_margin(robot, 2.0)
    assert np.allclose(np.asarray(lim) - robot.joint_limits, np.radians([2.0, -2.0]))


async def test_a_reading_far_from_the_prediction_is_retried_then_faults(tmp_path,
                                                                         make_config):
    from robocal.daemon.service import CalibrationService
    from tests.unit.daemon.conftest import random_plan

    svc = CalibrationService(make_config(measurement={"max_distance_mm": 1e-6, "retries": 1}))
    await svc.start()
    try:
        st = await svc.create(random_plan(12), actor="t")
        st = await svc.wait(st["id"], ["faulted"], timeout=30)
        assert st["state"] == "faulted" and "from the prediction" in st["reason"]
        assert st["poses_measured"] == 6  # the first six are needed to align the model
    finally:
        await svc.stop()


async def test_a_noisy_reading_is_rejected(make_config):
    from robocal.daemon.service import CalibrationService
    from tests.unit.daemon.conftest import random_plan

    svc = CalibrationService(make_config(measurement={"max_rms_mm": 1e-9, "retries": 0}))
    await svc.start()
    try:
        st = await svc.create(random_plan(12), actor="t")
        st = await svc.wait(st["id"], ["faulted"], timeout=30)
        assert "sample RMS" in st["reason"] and st["poses_measured"] == 0
    finally:
        await svc.stop()


async def test_retry_backoff_waits_on_the_service_clock(make_config):
    """A 30 s backoff passes when the clock says so, not on the wall clock (ADR 0017)."""
    from robocal.daemon.service import CalibrationService
    from tests._clock import ManualClock
    from tests._waiting import eventually
    from tests.unit.daemon.conftest import random_plan

    clock = ManualClock()
    cfg = make_config(tracker={"options": {"beam_break_rate": 1.0}},
                      measurement={"retries": 2, "backoff_s": 30.0, "max_backoff_s": 30.0})
    svc = CalibrationService(cfg, clock=clock)
    await svc.start()
    try:
        st = await svc.create(random_plan(3, seed=4), actor="t")
        for _ in range(2):                       # two backoffs between three attempts
            await eventually(lambda: clock.sleepers == 1, what="the runner backs off")
            assert svc.status(st["id"])["state"] == "running"
            clock.advance(29.0)
            assert svc.status(st["id"])["state"] == "running"
            clock.advance(1.0)
            await eventually(lambda: clock.sleepers == 0)
        st = await svc.wait(st["id"], ["faulted"], timeout=10)
        assert "no valid reading after 3 attempts" in st["reason"]
    finally:
        await svc.stop()


def test_distances_match_a_rigid_fit_over_the_poses_measured_so_far():
    """The running-moment alignment gives the distances of a full Kabsch fit: to rounding
    while it refits every pose, within a few micrometres once it refits every few poses."""
    from robocal.kinematics import rigid_fit

    robot = load_robot("fanuc_lrmate200i")
    rng = np.random.default_rng(3)
    pred = Predictor(robot, min_poses=6)
    R = np.asarray(euler_xyz_to_matrix(0.3, -0.2, 1.0))
    t = np.array([2.0, -1.0, 0.5])
    src: list[np.ndarray] = []
    dst: list[np.ndarray] = []
    for i, q in enumerate(rng.uniform(-1.0, 1.0, (120, robot.dof))):
        s = pred._model_point(q)
        d = R @ s + t + rng.normal(0.0, 2e-5, 3)
        if i >= 6:
            T = rigid_fit(np.array(src), np.array(dst))
            ref = float(np.linalg.norm(T[:3, :3] @ s + T[:3, 3] - d))
            got = pred.distance(q, d)
            assert got is not None
            assert abs(got - ref) < (1e-12 if i <= Predictor.REFIT_ALL else 5e-6)
        pred.add(q, d)
        src.append(s)
        dst.append(d)


def test_no_distance_while_the_poses_are_collinear():
    robot = load_robot("fanuc_lrmate200i")
    pred = Predictor(robot, min_poses=3)
    q0 = np.zeros(robot.dof)
    for k in range(5):  # one joint of a straight-line point set: the same model point
        pred.add(q0, np.array([k * 0.1, 0.0, 0.0]))
    assert pred.distance(q0, np.zeros(3)) is None
