"""The periodic cubic joint-angle map basis against scipy's B-spline implementation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.interpolate import BSpline

from robocal.kinematics import ErrorModelSpec, Term, load_robot
from robocal.kinematics._basis import evaluate_basis, spline_weights


def _periodic_bspline(c: np.ndarray) -> BSpline:
    """scipy's cubic B-spline over [0, 2 pi) with control value c[r] centred at r h.

    Uniform knots from -5 h to (K + 4) h: basis m starts at knot m - 5, so it is centred at
    (m - 3) h and carries coefficient c[(m - 3) mod K]; [0, 2 pi] lies inside the base interval.
    """
    K = len(c)
    h = 2.0 * math.pi / K
    knots = h * np.arange(-5, K + 5)
    coef = c[(np.arange(len(knots) - 4) - 3) % K]
    return BSpline(knots, coef, 3, extrapolate=False)


@pytest.mark.parametrize("K", [8, 13, 36])
def test_spline_value_and_derivative_match_scipy(K: int) -> None:
    rng = np.random.default_rng(K)
    c = rng.normal(size=K)
    # several revolutions either side, plus the knots themselves (t = 0 exactly)
    q = np.concatenate([rng.uniform(-3 * math.pi, 5 * math.pi, 500),
                        2.0 * math.pi / K * np.arange(-K, 2 * K)])
    idx, w, dw = spline_weights(q, K)
    ref = _periodic_bspline(c)
    qm = np.mod(q, 2.0 * math.pi)
    np.testing.assert_allclose(np.sum(c[idx] * w, axis=1), ref(qm), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.sum(c[idx] * dw, axis=1), ref.derivative()(qm),
                               rtol=0, atol=1e-10 * K)
    # partition of unity: a constant map stays constant
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(dw.sum(axis=1), 0.0, atol=1e-12 * K)


def test_each_map_column_of_evaluate_basis_is_one_scipy_basis_function() -> None:
    robot = load_robot("ur10")
    K = 12
    spec = ErrorModelSpec.constant(robot.dof).with_terms(
        [Term(2, "ez", "map", r) for r in range(K)], map_knots={2: K})
    rng = np.random.default_rng(3)
    q = rng.uniform(-2 * math.pi, 2 * math.pi, (300, robot.dof))
    B, dB = evaluate_basis(spec, robot, q, derivative=True)
    assert dB is not None
    cols = [spec.terms.index(Term(2, "ez", "map", r)) for r in range(K)]
    qm = np.mod(q[:, 2], 2.0 * math.pi)
    for r, col in enumerate(cols):
        unit = np.zeros(K)
        unit[r] = 1.0
        ref = _periodic_bspline(unit)
        np.testing.assert_allclose(B[:, col], ref(qm), atol=1e-12)
        np.testing.assert_allclose(dB[:, col], ref.derivative()(qm), atol=1e-10)
