"""Ordering by move time (nearest neighbour + 2-opt) and via-points for the maximum step."""

from __future__ import annotations

import numpy as np

from robocal.planning import insert_via_points, move_times, order_poses
from robocal.planning._order import two_opt


def _cost(q: np.ndarray, order: np.ndarray, speed: np.ndarray, start: np.ndarray) -> float:
    seq = q[order]
    prev = np.vstack([start[None], seq[:-1]])
    return float(move_times(prev, seq, speed).sum())


def test_move_time_is_the_slowest_joint() -> None:
    speed = np.array([1.0, 2.0, 0.5])
    assert move_times(np.zeros(3), np.array([1.0, 1.0, 1.0]), speed) == 2.0
    assert move_times(np.zeros(3), np.array([-1.5, 0.0, 0.0]), speed) == 1.5
    a = np.zeros((4, 3))
    assert move_times(a, a + 0.1, speed).shape == (4,)


def test_ordering_is_a_permutation_shorter_than_naive_orders(rng: np.random.Generator) -> None:
    q = rng.uniform(-2.0, 2.0, (80, 6))
    speed = np.array([2.0, 2.0, 2.5, 4.0, 4.0, 5.0])
    start = np.zeros(6)
    order = order_poses(q, speed, start=start)
    assert sorted(order.tolist()) == list(range(80))
    mine = _cost(q, order, speed, start)
    assert mine < 0.6 * _cost(q, np.arange(80), speed, start)
    for _ in range(5):
        assert mine < _cost(q, rng.permutation(80), speed, start)


def test_two_opt_leaves_no_improving_reversal(rng: np.random.Generator) -> None:
    q = rng.uniform(-1.0, 1.0, (25, 3))
    speed = np.ones(3)
    start = np.full(3, 1.5)
    order = order_poses(q, speed, start=start)
    D = move_times(q[:, None], q[None], speed)
    s = move_times(start[None], q, speed)
    best = _cost(q, order, speed, start)
    for i in range(25):
        for j in range(i + 1, 25):
            trial = order.copy()
            trial[i:j + 1] = trial[i:j + 1][::-1]
            assert _cost(q, trial, speed, start) >= best - 1e-9
    assert np.array_equal(two_opt(order, D, s), order)


def test_trivial_orders() -> None:
    assert order_poses(np.zeros((0, 3)), np.ones(3)).size == 0
    assert order_poses(np.ones((1, 3)), np.ones(3)).tolist() == [0]


def test_via_points_cap_every_step(rng: np.random.Generator) -> None:
    q = rng.uniform(-6.0, 6.0, (30, 6))
    start = np.zeros(6)
    out, via = insert_via_points(q, 0.5, start=start)
    steps = np.abs(np.diff(np.vstack([start[None], out]), axis=0)).max(axis=1)
    assert steps.max() <= 0.5 + 1e-12
    np.testing.assert_array_equal(out[~via], q)  # originals kept, in order
    assert via.sum() > 0
    # via-points lie on the straight joint-space line between their neighbours
    k = int(np.flatnonzero(via)[0])
    a, b = (start if k == 0 else out[k - 1]), out[np.flatnonzero(~via)[np.searchsorted(
        np.flatnonzero(~via), k)]]
    lam = float(np.dot(out[k] - a, b - a) / np.dot(b - a, b - a))
    assert 0.0 < lam < 1.0
    np.testing.assert_allclose(out[k], a + lam * (b - a), atol=1e-12)
    same, none = insert_via_points(q, 100.0)
    assert not none.any() and np.array_equal(same, q)
