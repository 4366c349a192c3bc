"""Observability indices, identifiable columns and the D-optimal selection."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from robocal.errors import ConfigError
from robocal.identification import min_poses
from robocal.kinematics import ErrorModelSpec, RobotDescription
from robocal.planning import DesignSpace, Feasibility, model_spec, observability_indices
from robocal.planning._design import _Blocks, _sym_sqrt_factor

Pool = tuple[np.ndarray, Feasibility]


def _logdet(J: np.ndarray, idx, delta: float = 0.0) -> float:
    A = J[np.asarray(idx)].reshape(-1, J.shape[2])
    return float(np.linalg.slogdet(A.T @ A + delta * np.eye(J.shape[2]))[1])


def _space(J: np.ndarray) -> DesignSpace:
    """A DesignSpace over a given (already scaled) Jacobian, bypassing the kinematics."""
    ds = DesignSpace.__new__(DesignSpace)
    ds.J = np.ascontiguousarray(J)
    ds.keep = np.arange(J.shape[2])
    ds.names = tuple(f"p{i}" for i in range(J.shape[2]))
    return ds


def _random_space(rng: np.random.Generator, n: int, L: int) -> DesignSpace:
    """n random candidates with L parameters, of unequal information, over a 2-D joint
    space."""
    ds = _space(rng.normal(size=(n, 3, L)) * rng.uniform(0.2, 2.0, (n, 1, 1)))
    ds.q = rng.uniform(-1.0, 1.0, (n, 2))
    return ds


def test_observability_indices_follow_their_definitions(rng: np.random.Generator) -> None:
    U, _ = np.linalg.qr(rng.normal(size=(12, 4)))
    V, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    s = np.array([8.0, 4.0, 2.0, 0.5])
    J = U @ np.diag(s) @ V.T
    o1, o2, o3, o4, o5, cond = observability_indices(J)
    assert o1 == pytest.approx(np.prod(s) ** 0.25 / math.sqrt(12))
    assert o2 == pytest.approx(0.5 / 8.0) and cond == pytest.approx(16.0)
    assert o3 == pytest.approx(0.5)
    assert o4 == pytest.approx(0.5**2 / 8.0)
    assert o5 == pytest.approx(1.0 / np.sum(1.0 / s))
    J[:, 3] = J[:, 0]  # rank deficient
    assert observability_indices(J)[1:] == (0.0, 0.0, 0.0, 0.0, math.inf)


def test_identifiable_parameters_of_the_lr_mate(robot: RobotDescription, pool: Pool) -> None:
    q, _f = pool
    ds = DesignSpace(robot, model_spec(robot, "constant"), q[:300], np.asarray(robot.tool))
    # 45 parameters, 27 identifiable from positions (docs/adr/0002 decision 2)
    assert len(ds.names) == 45 and ds.identifiable == 27
    assert ds.min_poses == min_poses(27) == 11 and ds.recommended_poses == 27
    assert len(ds.unidentifiable) == 18
    o = ds.observability(np.arange(50))
    assert o.identifiable == 27 and o.poses == 50 and math.isfinite(o.condition_number)
    ho = DesignSpace(robot, model_spec(robot, "high-order"), q[:300], np.asarray(robot.tool))
    assert ho.identifiable > 100 and ho.min_poses == min_poses(ho.identifiable)


def test_model_specs(robot: RobotDescription) -> None:
    assert model_spec(robot, "constant") == ErrorModelSpec.constant(6)
    assert model_spec(robot, "auto") == model_spec(robot, "high-order")
    custom = ErrorModelSpec.build(6, fourier=1)
    assert model_spec(robot, custom) is custom
    with pytest.raises(ConfigError, match="unknown error model 'cubic'"):
        model_spec(robot, "cubic")
    from robocal.identification import _models as ident

    # planning optimises for the structure identification fits
    assert set(model_spec(robot, "high-order").terms) == set(ident.high_order_spec(robot).terms)


def test_rank_three_updates_match_a_fresh_computation(rng: np.random.Generator) -> None:
    n, L = 50, 7
    J = rng.normal(size=(n, 3, L))
    Jt = np.ascontiguousarray(J.transpose(1, 2, 0))
    M = np.eye(L) * 0.1 + J[:5].reshape(-1, L).T @ J[:5].reshape(-1, L)
    b = _Blocks(Jt, np.linalg.inv(M))
    np.testing.assert_allclose(np.moveaxis(b.g, 2, 0),
                               np.einsum("nai,ij,nbj->nab", J, np.linalg.inv(M), J), atol=1e-10)
    # adding pose c: Woodbury factor V with V V^T = M^-1 Jc^T (I + Gc)^-1 Jc M^-1
    c = 17
    V = np.linalg.inv(M) @ J[c].T @ _sym_sqrt_factor(np.eye(3) + b.block(c))
    b.update(V, -1.0)
    M2 = M + J[c].T @ J[c]
    ref = np.einsum("nai,ij,nbj->nab", J, np.linalg.inv(M2), J)
    np.testing.assert_allclose(np.moveaxis(b.g, 2, 0), ref, atol=1e-10)
    G = np.moveaxis(b.g, 2, 0)
    np.testing.assert_allclose(b.logdet_i_plus(), np.linalg.slogdet(np.eye(3) + G)[1],
                               atol=1e-9)


def test_selection_beats_random_and_exchange_is_a_local_optimum(
        rng: np.random.Generator) -> None:
    n, L, k = 40, 6, 4
    J = rng.normal(size=(n, 3, L)) * rng.uniform(0.2, 2.0, (n, 1, 1))
    ds = _space(J)
    greedy = ds.select(k, exchange_passes=0)
    best = ds.select(k, exchange_passes=10)
    assert len(set(best.tolist())) == k
    assert _logdet(J, best) >= _logdet(J, greedy) - 1e-9
    for _ in range(20):
        assert _logdet(J, best) > _logdet(J, rng.choice(n, k, replace=False))
    # no single swap improves the exchanged design
    base = _logdet(J, best, 1e-6)
    for pos, c in itertools.product(range(k), range(n)):
        if c in best:
            continue
        trial = best.copy()
        trial[pos] = c
        assert _logdet(J, trial, 1e-6) <= base + 1e-7


def test_greedy_finds_the_optimum_of_small_problems(rng: np.random.Generator) -> None:
    n, L, k = 10, 4, 3
    J = rng.normal(size=(n, 3, L))
    sel = _space(J).select(k, exchange_passes=5)
    opt = max(_logdet(J, c) for c in itertools.combinations(range(n), k))
    assert _logdet(J, sel) == pytest.approx(opt, abs=1e-6)


def test_selection_respects_allowed_and_counts(rng: np.random.Generator) -> None:
    J = rng.normal(size=(30, 3, 5))
    ds = _space(J)
    allowed = np.zeros(30, dtype=bool)
    allowed[::3] = True
    sel = ds.select(6, allowed=allowed)
    assert np.all(allowed[sel]) and len(set(sel.tolist())) == 6
    assert ds.select(0).size == 0
    with pytest.raises(ConfigError, match="11 poses requested but only 10"):
        ds.select(11, allowed=allowed)


def test_weights_change_the_design_but_not_its_scale(robot: RobotDescription,
                                                     pool: Pool) -> None:
    q, _f = pool
    q = q[:200]
    W = np.broadcast_to(np.diag([1.0, 2.0, 0.5]), (200, 3, 3)).copy()
    a = DesignSpace(robot, model_spec(robot, "constant"), q, np.asarray(robot.tool), weights=W)
    b = DesignSpace(robot, model_spec(robot, "constant"), q, np.asarray(robot.tool),
                    weights=1e5 * W)
    np.testing.assert_allclose(a.J, b.J, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(a.select(20), b.select(20))
    with pytest.raises(ConfigError, match="weights must be finite"):
        DesignSpace(robot, model_spec(robot, "constant"), q, np.asarray(robot.tool),
                    weights=W[:10])


def test_stratified_selection_takes_one_pose_per_stratum_and_is_exchange_optimal(
        rng: np.random.Generator) -> None:
    from robocal.planning._design import _kmeans_strata

    n, L, k = 120, 5, 8
    ds = _random_space(rng, n, L)
    J = ds.J
    sel = ds.select_stratified(k, exchange_passes=10)
    labels, _ = _kmeans_strata(ds.q, k, 12)
    assert len(set(sel.tolist())) == k
    assert sorted(labels[sel].tolist()) == list(range(k))       # one pose per stratum
    # no swap within a stratum improves the design
    base = _logdet(J, sel, 1e-6)
    for pos in range(k):
        for c in np.flatnonzero(labels == labels[sel[pos]]):
            trial = sel.copy()
            trial[pos] = c
            assert _logdet(J, trial, 1e-6) <= base + 1e-7
    # better than the strata's centre poses it starts from, and than random draws per stratum
    _, centres = _kmeans_strata(ds.q, k, 12)
    assert base >= _logdet(J, centres, 1e-6)
    for _ in range(10):
        pick = [rng.choice(np.flatnonzero(labels == s)) for s in range(k)]
        assert base >= _logdet(J, pick, 1e-6)


def test_stratified_selection_covers_the_workspace(rng: np.random.Generator) -> None:
    # information concentrated at one end of q: D-optimal piles up there, strata do not
    n, L, k = 400, 4, 20
    q = rng.uniform(0.0, 1.0, (n, 1))
    J = rng.normal(size=(n, 3, L)) * (0.1 + 3.0 * q[:, :, None] ** 4)
    ds = _space(J)
    ds.q = q
    strat = ds.select_stratified(k)
    dopt = ds.select(k)
    assert np.sum(q[strat, 0] < 0.5) >= k // 2 - 2                # about half in each half
    assert np.sum(q[dopt, 0] < 0.5) <= 2
    allowed = q[:, 0] > 0.2
    sel = ds.select_stratified(k, allowed=allowed)
    assert np.all(allowed[sel]) and len(set(sel.tolist())) == k
    with pytest.raises(ConfigError, match="401 poses requested but only 400"):
        ds.select_stratified(401)


def test_refilling_strata_replaces_only_the_poses_no_longer_allowed(
        rng: np.random.Generator) -> None:
    n, L, k = 300, 5, 12
    ds = _random_space(rng, n, L)
    J = ds.J
    allowed = np.ones(n, dtype=bool)
    chosen, strata = ds.stratify(k, allowed=allowed)
    assert sorted(strata[chosen].tolist()) == list(range(k))
    assert np.array_equal(ds.refill_strata(chosen, strata, allowed), chosen)
    # two chosen poses turn out unreachable: only their slots change, each to an allowed
    # member of its own stratum, D-optimally given the poses that stay
    gone = chosen[[2, 7]]
    allowed[gone] = False
    new = ds.refill_strata(chosen, strata, allowed)
    assert new is not None and len(set(new.tolist())) == k
    assert np.array_equal(np.delete(new, [2, 7]), np.delete(chosen, [2, 7]))
    assert np.all(allowed[new]) and np.array_equal(strata[new], strata[chosen])
    for pos in (2, 7):
        for c in np.flatnonzero(allowed & (strata == strata[chosen[pos]])):
            trial = new.copy()
            trial[pos] = c
            assert _logdet(J, trial, 1e-6) <= _logdet(J, new, 1e-6) + 1e-7
    # a preferred member wins over a better one that is not preferred
    prefer = np.ones(n, dtype=bool)
    prefer[new[2]] = False
    again = ds.refill_strata(chosen, strata, allowed, prefer=prefer)
    assert again is not None and again[2] != new[2] and strata[again[2]] == strata[chosen[2]]
    # a released stratum takes a candidate near its centre from elsewhere
    release = np.zeros(k, dtype=bool)
    release[7] = True
    rel = ds.refill_strata(chosen, strata, allowed, release=release)
    assert rel is not None and strata[rel[7]] != strata[chosen[7]] and allowed[rel[7]]
    assert rel[7] not in np.delete(rel, 7)
    # a stratum with no member left is released too; None when nothing is left at all
    allowed_one = np.zeros(n, dtype=bool)
    allowed_one[chosen] = True
    allowed_one[chosen[0]] = False
    assert ds.refill_strata(chosen, strata, allowed_one) is None
