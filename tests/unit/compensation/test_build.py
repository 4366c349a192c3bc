"""build_table: joint corrections from the ez terms, frames, targets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robocal.compensation import TargetSet, build_table, joint_corrections
from robocal.errors import ConfigError
from robocal.kinematics import (
    CalibratedModel,
    ErrorModelSpec,
    KinematicModel,
    Term,
    euler_xyz_to_matrix,
    load_robot,
    wpr_to_matrix,
)
from robocal.simulation import VirtualCell

Fit = tuple[VirtualCell, CalibratedModel]


def _ez_only_model(rng: np.random.Generator, coverage: np.ndarray | None = None
                   ) -> CalibratedModel:
    """LR Mate 200i (J2/J3 coupled) whose only errors are rotations about the joint axes."""
    robot = load_robot("fanuc_lrmate200i")
    terms = []
    for j in range(6):
        terms.append(Term(j, "ez", "const"))
        terms.append(Term(j, "ez", "poly", 1))
        for k in (1, 2, 3):
            terms += [Term(j, "ez", "cos", k), Term(j, "ez", "sin", k)]
    terms += [Term(2, "ez", "swcos", 1), Term(2, "ez", "swsin", 1)]
    T = np.eye(4)
    T[:3, :3] = euler_xyz_to_matrix(0.01, -0.02, 3.0)
    T[:3, 3] = [1.5, 0.1, -0.3]
    model = KinematicModel(robot, ErrorModelSpec(6, tuple(terms)), T)
    x = model.nominal_params()
    x[9:] = rng.normal(0.0, 3e-4, len(terms))
    x[-2:] = rng.normal(0.0, 2e-5, 2)                       # strain-wave ripple on J3
    return CalibratedModel(model, x, coverage=coverage)


def _exact_command(cal: CalibratedModel, q: np.ndarray) -> np.ndarray:
    """Independent reference: solve C q_c + ez(q_c) = C q by fixed-point iteration."""
    Ci = np.linalg.inv(cal.robot.coupling_matrix)
    qc = q.copy()
    for _ in range(30):
        E, _, _ = cal.model.joint_errors(qc, cal.params)
        qc = q - E[:, :, 5] @ Ci.T
    return qc


def _nominal_positions(cal: CalibratedModel, q: np.ndarray) -> np.ndarray:
    nominal = KinematicModel(cal.robot, ErrorModelSpec(cal.robot.dof, ()), cal.model.T_ref)
    x = nominal.nominal_params()
    x[:9] = cal.params[:9]
    return nominal.positions(q, x)


def test_joint_table_realises_the_exact_correction(rng: np.random.Generator) -> None:
    cal = _ez_only_model(rng)
    table = build_table(cal, "joint", interp_tol_deg=1e-4)
    entries = {(e.joint, e.source) for e in table.joints or []}
    assert entries == {(j, j) for j in range(1, 7)} | {(3, 2)}    # the J2/J3 coupling entry
    assert len({len(e.q_deg) for e in table.joints or []}) == 1      # uniform grids
    q = cal.robot.joint_limits[:, 0] + rng.uniform(0, 1, (3000, 6)) * np.ptp(
        cal.robot.joint_limits, axis=1)
    q_cmd = q + np.radians(table.joint_offsets_deg(np.degrees(q)))
    exact = _exact_command(cal, q)
    bound = {j: sum(e.interpolation_error_bound_deg for e in table.joints or []
                    if e.joint == j) for j in range(1, 7)}
    err_deg = np.degrees(np.abs(q_cmd - exact)).max(axis=0)
    # each joint's stated bound (interpolation; for J3 also the coupling's second order)
    for j in range(6):
        assert err_deg[j] <= bound[j + 1] + 1e-9, (j, err_deg, bound)
    # the robot lands where the nominal robot would: only rotations about axes were wrong
    miss = np.linalg.norm(cal.predict(q_cmd) - _nominal_positions(cal, q), axis=1)
    reach = sum(abs(j.a) + abs(j.d) for j in cal.robot.joints) + 0.1
    assert miss.max() <= reach * math.radians(sum(bound.values()))
    assert np.sqrt(np.mean(miss**2)) < 1e-6
    assert table.predicted_residual_mm < 2e-3
    assert table.stats["frames_only_rms_mm"] > 100 * table.predicted_residual_mm


def test_joint_grid_meets_a_tighter_bound(rng: np.random.Generator) -> None:
    cal = _ez_only_model(rng)
    coarse = joint_corrections(cal, tol_deg=1e-3)
    fine = joint_corrections(cal, tol_deg=1e-5)
    assert len(fine[0].q_deg) > len(coarse[0].q_deg)
    for c, f in zip(coarse, fine, strict=True):
        qd = np.linspace(c.q_deg[0], c.q_deg[-1], 20001)
        gap = np.abs(c.evaluate(qd) - f.evaluate(qd)).max()
        assert gap <= c.interpolation_error_bound_deg + f.interpolation_error_bound_deg
    with pytest.raises(ConfigError, match="positive"):
        joint_corrections(cal, tol_deg=0.0)
    with pytest.raises(ConfigError, match="method"):
        joint_corrections(cal, method="guess")


def test_joint_table_holds_beyond_the_coverage(rng: np.random.Generator) -> None:
    lim = load_robot("fanuc_lrmate200i").joint_limits
    cover = lim.copy()
    cover[0] = [-1.0, 1.2]
    cal = _ez_only_model(rng, coverage=cover)
    table = build_table(cal, "joint")
    assert table.valid_range_deg[0] == pytest.approx((math.degrees(-1.0), math.degrees(1.2)))
    j1 = next(e for e in table.joints or [] if e.joint == 1)
    assert j1.q_deg[0] == pytest.approx(math.degrees(lim[0, 0]))
    assert j1.q_deg[1] == pytest.approx(math.degrees(-1.0))
    outside = j1.evaluate(np.degrees(np.array([-2.5, -2.0, -1.5])))
    assert np.ptp(outside) == 0.0 and outside[0] == pytest.approx(j1.evaluate(-57.29577951))


def test_frames_table_recovers_base_and_tool(rng: np.random.Generator) -> None:
    robot = load_robot("kuka_kr210_r3100")
    T = np.eye(4)
    T[:3, :3] = euler_xyz_to_matrix(0.02, -0.01, 2.5)
    T[:3, 3] = [3.0, -0.4, -0.8]
    model = KinematicModel(robot, ErrorModelSpec(6, ()), T)
    x = model.nominal_params()
    x[:6] = [1e-3, -2e-3, 5e-4, 1e-3, -5e-4, 2e-3]
    x[6:9] = [0.012, -0.004, 0.131]
    cal = CalibratedModel(model, x)
    table = build_table(cal, "frames")
    assert table.predicted_residual_mm < 1e-6
    f = table.frames
    assert f is not None
    T_bt = np.eye(4)
    T_bt[:3, :3] = wpr_to_matrix(*np.radians([f.base.w, f.base.p, f.base.r]))
    T_bt[:3, 3] = np.array([f.base.x, f.base.y, f.base.z]) * 1e-3
    np.testing.assert_allclose(T_bt @ model.base_transform(x), np.eye(4), atol=1e-9)
    assert (f.tool.x, f.tool.y, f.tool.z) == pytest.approx((12.0, -4.0, 131.0), abs=1e-6)


def test_targets_table(paper_fit: Fit) -> None:
    cell, cal = paper_fit
    assert cal.coverage is not None
    rng = np.random.default_rng(9)
    q = rng.uniform(cal.coverage[:, 0] + 0.1, cal.coverage[:, 1] - 0.1, (5, 6))
    p = cell.reflector_position(q)
    p[3] = [4.0, 4.0, 4.0]
    table = build_table(cal, "targets", targets=TargetSet(p=p, q_seed=q), created="t0")
    table.verify()
    rows = table.targets or []
    assert [r.index for r in rows] == list(range(5))
    assert [r.status for r in rows] == ["ok", "ok", "ok", "unreachable", "ok"]
    assert rows[3].q_deg == pytest.approx(np.degrees(q[3]).tolist())   # uncorrected seed
    assert max(r.model_residual_mm for r in rows if r.status == "ok") < 1e-3
    assert table.stats["n_ok"] == 4 and table.created == "t0"
    assert table.model_id == cal.model_id and table.robot == cal.robot.name
    arrays = build_table(cal, "targets", targets_p=p, seeds_q=q, created="t0")
    assert arrays.targets == table.targets                  # the daemon's call style
    with pytest.raises(ConfigError, match="needs program targets"):
        build_table(cal, "targets")
    with pytest.raises(ConfigError, match="seed joints"):
        build_table(cal, "targets", targets=TargetSet(p=p, q_seed=q[:, :5]))


def test_joint_tables_for_the_identified_model(paper_fit: Fit) -> None:
    _, cal = paper_fit
    ez = build_table(cal, "joint", samples=600)
    fit = build_table(cal, "joint", joint_method="fit", samples=600)
    for t in (ez, fit):
        t.verify()
        assert {(e.joint, e.source) for e in t.joints or []} >= {(3, 2), (3, 3)}
        assert t.predicted_residual_mm == pytest.approx(t.stats["with_frames_rms_mm"])
    # the fitted table never does worse than frames alone; here it does clearly better
    assert fit.predicted_residual_mm < 0.9 * fit.stats["frames_only_rms_mm"]
    frames = build_table(cal, "frames", samples=600)
    assert frames.predicted_residual_mm == pytest.approx(ez.stats["frames_only_rms_mm"])
    paired = build_table(cal, "frames", with_joint_table=True, joint_method="fit", samples=600)
    assert paired.predicted_residual_mm == pytest.approx(fit.predicted_residual_mm, rel=1e-6)
