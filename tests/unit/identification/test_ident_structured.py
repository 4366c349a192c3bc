"""Normal matrices from the factored Jacobian (map columns sparse) equal the dense ones."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robocal.identification._models import map_terms
from robocal.identification._solver import Problem
from robocal.identification._structured import has_maps, normal_blocks
from robocal.identification._weights import TrackerSigma, whitening
from robocal.kinematics import ErrorModelSpec, KinematicModel, Term, load_robot

K = 48  # knots per revolution (7.5 deg): small blocks keep the tests fast


def _model() -> KinematicModel:
    """Constant, harmonic, pitch and ripple terms, and maps on two joints with knots missing
    (as where a joint's data leave gaps)."""
    robot = load_robot("fanuc_lrmate200i")
    terms = [Term(j, c, "const") for j in range(6) for c in ("dx", "ey", "ez")]
    terms += [Term(1, c, f, 1) for c in ("dx", "ez") for f in ("cos", "sin")]
    terms += [Term(2, "ez", "poly", 1), Term(4, "ez", "cos", 11), Term(4, "ez", "sin", 11)]
    terms += map_terms(1, [k for k in range(K) if k % 7 != 3])
    terms += map_terms(3, range(10, 40))
    knots = [0, K, 0, K, 0, 0]
    return KinematicModel(robot, ErrorModelSpec(6, tuple(terms), tuple(knots)))


def _problem(n: int, seed: int, orientation: bool = False) -> tuple[Problem, np.ndarray]:
    m = _model()
    rng = np.random.default_rng(seed)
    lo, hi = m.robot.joint_limits.T
    q = lo + (hi - lo) * rng.random((n, 6))
    x = m.nominal_params()
    x[:9] += 1e-4 * rng.standard_normal(9)
    x[9:] = 1e-4 * rng.standard_normal(m.size - 9)
    p = m.positions(q, x) + 1e-5 * rng.standard_normal((n, 3))
    W = whitening(p, TrackerSigma())
    if not orientation:
        return Problem(m, q, p, W), x
    _, R, _ = m.pose_jacobian(q, x)
    W_rot = np.broadcast_to(np.eye(3) / 1e-4, (n, 3, 3)).copy()
    return Problem(m, q, p, W, R_probe=R, W_rot=W_rot), x


def _dense(prob: Problem, x: np.ndarray, rows: np.ndarray, cols: np.ndarray,
           group_of: np.ndarray, n_groups: int) -> tuple[np.ndarray, ...]:
    G = np.zeros((n_groups, len(cols), len(cols)))
    b = np.zeros((n_groups, len(cols)))
    c = np.zeros(n_groups)
    Jw, rw = prob.whitened_jacobian(x, rows, cols)
    m = len(rw) // len(rows)
    for f in range(n_groups):
        sel = np.repeat(group_of == f, m)
        G[f] = Jw[sel].T @ Jw[sel]
        b[f] = Jw[sel].T @ rw[sel]
        c[f] = rw[sel] @ rw[sel]
    return G, b, c, Jw


def _close(a: np.ndarray, b: np.ndarray) -> None:
    assert np.max(np.abs(a - b)) <= 1e-12 * max(np.max(np.abs(b)), 1e-300)


@pytest.mark.parametrize("orientation", [False, True])
@pytest.mark.parametrize("order", ["sorted", "maps last", "shuffled"])
def test_grouped_normals_equal_the_dense_products(orientation: bool, order: str) -> None:
    prob, x = _problem(300, seed=1, orientation=orientation)
    P = prob.model.size
    cols = np.arange(P)
    rng = np.random.default_rng(2)
    if order == "maps last":      # the auto superset's order: no permutation at the end
        is_map = np.array([c >= 9 and prob.model.spec.terms[c - 9].family == "map" for c in cols])
        cols = np.concatenate([cols[~is_map], cols[is_map]])
    elif order == "shuffled":     # head first (required), the terms in any order
        cols = np.concatenate([cols[:9], 9 + rng.permutation(P - 9)])
    rows = np.sort(rng.choice(300, 220, replace=False))
    group_of = rng.integers(0, 4, len(rows))
    qr = np.flatnonzero(cols < 20)
    G, b, c, R = normal_blocks(prob, x, rows, cols, group_of, 4, qr_cols=qr)
    Gd, bd, cd, Jw = _dense(prob, x, rows, cols, group_of, 4)
    _close(G, Gd)
    _close(b, bd)
    _close(c, cd)
    assert R is not None
    _close(R.T @ R, Jw[:, qr].T @ Jw[:, qr])


def test_the_solver_uses_the_sparse_path_for_maps_with_the_same_result() -> None:
    prob, x = _problem(200, seed=3)
    rows = np.arange(200)
    cols = np.arange(prob.model.size)
    assert has_maps(prob, cols) and not has_maps(prob, cols[:40])
    A, g, cost = prob.normal_equations(x, rows, cols)
    Gd, bd, cd, _ = _dense(prob, x, rows, cols, np.zeros(200, dtype=int), 1)
    _close(A, Gd[0])
    _close(g, bd[0])
    assert cost == pytest.approx(cd[0], rel=1e-13)


def test_base_and_tool_columns_must_come_first() -> None:
    prob, x = _problem(20, seed=4)
    cols = np.concatenate([[30], np.arange(9), [31]])
    with pytest.raises(ValueError, match="base and tool"):
        normal_blocks(prob, x, np.arange(20), cols)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_any_column_subset_and_grouping(data: st.DataObject) -> None:
    prob, x = _problem(60, seed=5)
    P = prob.model.size
    keep = data.draw(st.lists(st.booleans(), min_size=P - 9, max_size=P - 9))
    head = data.draw(st.lists(st.booleans(), min_size=9, max_size=9))
    cols = np.concatenate([np.flatnonzero(head), 9 + np.flatnonzero(keep)]).astype(np.intp)
    if len(cols) == 0:
        return
    n_groups = data.draw(st.integers(1, 5))
    group_of = np.array(data.draw(st.lists(st.integers(0, n_groups - 1), min_size=60,
                                           max_size=60)))
    rows = np.arange(60)
    G, b, c, _ = normal_blocks(prob, x, rows, cols, group_of, n_groups)
    Gd, bd, cd, _ = _dense(prob, x, rows, cols, group_of, n_groups)
    _close(G, Gd)
    _close(b, bd)
    _close(c, cd)


@pytest.mark.parametrize("orientation", [False, True])
def test_hat_blocks_equal_the_dense_products(orientation: bool) -> None:
    from robocal.identification._engine import hat_statistics
    from robocal.identification._structured import hat_blocks

    prob, x = _problem(150, seed=6, orientation=orientation)
    rng = np.random.default_rng(7)
    cols = np.concatenate([np.arange(9), 9 + rng.permutation(prob.model.size - 9)])
    A = rng.standard_normal((len(cols), len(cols)))
    Ninv = A @ A.T / len(cols)
    rows = np.arange(150)
    H, r = hat_blocks(prob, x, rows, cols, Ninv)
    Jw, rw = prob.whitened_jacobian(x, rows, cols)
    m = 6 if orientation else 3
    Jp = Jw.reshape(150, m, -1)[:, :3]
    _close(H, np.einsum("nik,kl,njl->nij", Jp, Ninv, Jp))
    _close(r, rw.reshape(150, m)[:, :3])
    # the solver's statistic takes the factored path and gives the dense values
    in_fit = rng.random(150) < 0.8
    t = hat_statistics(prob, x, cols, Ninv, in_fit)
    sign = np.where(in_fit, -1.0, 1.0)[:, None, None]
    M = np.eye(3) + sign * np.einsum("nik,kl,njl->nij", Jp, Ninv, Jp) + 1e-9 * np.eye(3)
    rp = rw.reshape(150, m)[:, :3]
    want = np.einsum("ni,ni->n", rp, np.linalg.solve(M, rp[:, :, None])[:, :, 0])
    assert np.allclose(t, want, rtol=1e-9, atol=0)
