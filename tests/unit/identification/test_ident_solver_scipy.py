"""The own Levenberg-Marquardt solver reaches the same minimum as scipy's least_squares."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import cholesky
from scipy.optimize import least_squares

from robocal.identification._models import high_order_spec
from robocal.identification._solver import Problem, analyse_jacobian, levenberg_marquardt
from robocal.identification._weights import TrackerSigma, whitening
from robocal.kinematics import ErrorModelSpec, KinematicModel
from robocal.simulation import VirtualCell


def _problem(spec_kind: str, n: int, *, ridge: float = 0.0) -> tuple[Problem, np.ndarray,
                                                                     np.ndarray]:
    cell = VirtualCell.create("fanuc_lrmate200i", "paper", seed=5)
    rng = np.random.default_rng(5)
    q, p, _, _ = cell.simulate(cell.random_joints(n, rng), rng)
    spec = (ErrorModelSpec.constant(6) if spec_kind == "constant"
            else high_order_spec(cell.robot, order=1, strain_wave=()))
    model = KinematicModel(cell.robot, spec, cell.T_tracker_base)
    penalty = ridge * np.eye(model.size) if ridge else None
    prob = Problem(model, q, p, whitening(p, TrackerSigma()), penalty=penalty)
    x0 = model.nominal_params()
    _, keep, _ = analyse_jacobian(prob, x0, np.arange(n), np.arange(model.size), tol=3e-4)
    return prob, x0, np.flatnonzero(keep).astype(np.intp)


def _scipy_minimum(prob: Problem, x0: np.ndarray, free: np.ndarray) -> tuple[float, np.ndarray]:
    """sum r^2 + prior at scipy's minimum, with the prior as extra residual rows."""
    rows = np.arange(prob.n)
    L = None if prob.penalty is None else cholesky(prob.penalty[np.ix_(free, free)])

    def full(z: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[free] = z
        return x

    def fun(z: np.ndarray) -> np.ndarray:
        r = prob.residuals(full(z), rows).ravel()
        return r if L is None else np.concatenate([r, L @ z])

    def jac(z: np.ndarray) -> np.ndarray:
        Jw, _ = prob.whitened_jacobian(full(z), rows, free)
        return -Jw if L is None else np.vstack([-Jw, L])

    res = least_squares(fun, x0[free], jac=jac, method="lm", x_scale="jac",
                        ftol=1e-12, xtol=1e-12, gtol=1e-12)
    assert res.success
    return 2.0 * float(res.cost), full(res.x)


@pytest.mark.parametrize(("spec_kind", "n", "ridge"), [("constant", 40, 0.0),
                                                       ("high-order", 80, 0.0),
                                                       ("constant", 40, 1e6)])
def test_own_lm_and_scipy_reach_the_same_cost(spec_kind: str, n: int, ridge: float) -> None:
    prob, x0, free = _problem(spec_kind, n, ridge=ridge)
    rows = np.arange(n)
    info = levenberg_marquardt(prob, x0, free, rows, max_iter=200, ftol=1e-12)
    assert info.converged, info.message
    cost_scipy, x_scipy = _scipy_minimum(prob, x0, free)
    # the planted errors are far larger than the noise: the start is far from the minimum
    assert prob.cost(x0, rows) > 100 * cost_scipy
    assert info.cost == pytest.approx(cost_scipy, rel=1e-6)
    # same minimum, not just the same value: the fitted positions agree to far below the noise
    p_own = prob.model.positions(prob.q, info.x)
    p_scipy = prob.model.positions(prob.q, x_scipy)
    assert np.max(np.abs(p_own - p_scipy)) < 1e-7
