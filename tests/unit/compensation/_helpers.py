"""Shared test helpers: a calibrated model fitted on simulated tracker data.

``fitted_model`` uses :func:`robocal.identification.fit` once it is importable and otherwise a
small truncated-SVD Gauss-Newton fit of the planted structure, so the compensation tests do
not depend on the identification package being finished.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from robocal.kinematics import CalibratedModel, ErrorModelSpec, KinematicModel, rigid_fit
from robocal.simulation import VirtualCell, truth_spec


def _gauss_newton(model: KinematicModel, q: np.ndarray, p: np.ndarray, iters: int = 12
                  ) -> np.ndarray:
    x = model.nominal_params()
    for _ in range(iters):
        pp, J = model.jacobian(q, x)
        r = (p - pp).ravel()
        J = J.reshape(-1, model.size)
        sc = np.linalg.norm(J, axis=0) + 1e-12
        U, S, Vt = np.linalg.svd(J / sc, full_matrices=False)
        keep = S[0] * 1e-3 < S  # drops the unidentifiable combinations
        dx = (Vt[keep].T @ ((U[:, keep].T @ r) / S[keep])) / sc
        c0 = float(np.sum(r**2))
        step = 1.0
        while step > 0.05:
            xn = x + step * dx
            if np.sum((p - model.positions(q, xn)) ** 2) < c0:
                break
            step *= 0.5
        x = xn
        if np.abs(dx).max() < 1e-11:
            break
    return x


def quick_fit(cell: VirtualCell, q: np.ndarray, p: np.ndarray, spec: ErrorModelSpec,
              *, with_fallback: bool = True) -> CalibratedModel:
    """Fit ``spec`` to (q, p); coverage = the data's joint range, optional constant fallback."""
    m0 = KinematicModel(cell.robot, spec)
    T = rigid_fit(m0.positions(q, m0.nominal_params()), p)
    model = KinematicModel(cell.robot, spec, T)
    x = _gauss_newton(model, q, p)
    cover = np.stack([q.min(axis=0), q.max(axis=0)], axis=1)
    fb = None
    if with_fallback:
        const = model.with_spec(ErrorModelSpec.constant(cell.robot.dof))
        fb = CalibratedModel(const, _gauss_newton(const, q, p), kind="constant")
    return CalibratedModel(model, x, coverage=cover, fallback=fb, kind="high-order")


def _identification_fit(cell: VirtualCell, q: np.ndarray, p: np.ndarray,
                        s: np.ndarray) -> CalibratedModel | None:
    try:
        from robocal._core.measurements import MeasurementSet
        from robocal.identification import fit  # type: ignore[attr-defined]
    except ImportError:
        return None
    res = fit(cell.robot, MeasurementSet(q=q, p=p, sigma=s), model="high-order")
    return res.calibrated


@lru_cache(maxsize=4)
def fitted_model(robot: str = "fanuc_lrmate200i", scenario: str = "paper", seed: int = 7,
                 n_poses: int = 250, prefer_identification: bool = True
                 ) -> tuple[VirtualCell, CalibratedModel]:
    """A virtual cell and a model fitted from ``n_poses`` simulated tracker measurements."""
    cell = VirtualCell.create(robot, scenario, seed)
    rng = np.random.default_rng(seed + 1000)
    q = cell.random_joints(n_poses, rng, margin_rad=0.1)
    q_cmd, p, s, _ = cell.simulate(q, rng)
    cal = _identification_fit(cell, q_cmd, p, s) if prefer_identification else None
    if cal is None:
        cal = quick_fit(cell, q_cmd, p, truth_spec(cell.robot, scenario))
    return cell, cal
