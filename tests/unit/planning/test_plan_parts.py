"""Parts of the planner made faster for issue 28 (ADR 0048): own Sobol points, own Dijkstra,
two-thread capsule checks, and the leg-verdict cache's invalidation."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.stats import qmc

from robocal.kinematics import load_robot
from robocal.planning import MotionChecker, load_cell
from robocal.planning._campaign import _legs_safe
from robocal.planning._geometry import PARALLEL_ROWS, map_rows
from robocal.planning._order import shortest_path
from robocal.planning._sobol import MAX_DIM, Sobol


@pytest.mark.parametrize("d", [1, 2, 6, 7, MAX_DIM])
@pytest.mark.parametrize("seed", [0, 5, [3, 4]])
def test_sobol_points_are_scipys(d: int, seed: int | list[int]) -> None:
    ref = qmc.Sobol(d=d, scramble=True, seed=np.random.default_rng(seed))
    own = Sobol(d, np.random.default_rng(seed))
    np.testing.assert_array_equal(own.random_base2(9), ref.random_base2(9))
    for n in (512, 1024, 2048):                   # the planner's doubling draws
        np.testing.assert_array_equal(own.random(n), ref.random(n))


def test_sobol_refuses_dimensions_without_direction_numbers() -> None:
    with pytest.raises(ValueError, match="dimension"):
        Sobol(MAX_DIM + 1, np.random.default_rng(0))


def test_shortest_path_is_a_shortest_path() -> None:
    rng = np.random.default_rng(3)
    for trial in range(20):
        n = 30
        pairs = sorted({(int(min(a, b)), int(max(a, b)))
                        for a, b in rng.integers(0, n, (60, 2)) if a != b})
        i = np.array([p[0] for p in pairs], dtype=np.intp)
        j = np.array([p[1] for p in pairs], dtype=np.intp)
        w = rng.uniform(0.1, 2.0, len(i))
        dist = dijkstra(csr_matrix((w, (i, j)), shape=(n, n)), directed=False, indices=0)
        weight = {(a, b): c for a, b, c in zip(i.tolist(), j.tolist(), w.tolist(), strict=True)}
        for goal in range(1, n):
            path = shortest_path(n, i, j, w, 0, goal)
            if not np.isfinite(dist[goal]):
                assert path is None, trial
                continue
            assert path is not None and path[0] == 0 and path[-1] == goal
            length = sum(weight[(min(a, b), max(a, b))] for a, b in itertools.pairwise(path))
            assert length == pytest.approx(dist[goal], rel=1e-12)


def test_map_rows_covers_every_row_once_in_order() -> None:
    for n, chunk in ((0, 8), (5, 8), (PARALLEL_ROWS, 10**6), (PARALLEL_ROWS + 7, 300)):
        rows = np.arange(n)
        parts = map_rows(rows.__getitem__, n, chunk)
        assert all(len(p) <= chunk for p in parts)
        if n >= PARALLEL_ROWS:
            assert len(parts) >= 2
        np.testing.assert_array_equal(np.concatenate([np.zeros(0, int), *parts]), np.arange(n))


def _safe_leg(motion: MotionChecker) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(11)
    lo, hi = motion.limits[:, 0], motion.limits[:, 1]
    for _ in range(50):
        a = lo + rng.random((40, len(lo))) * (hi - lo)
        b = np.clip(a + rng.normal(scale=math.radians(20.0), size=a.shape), lo, hi)
        ok = motion.check_moves(a, b, explain=False).safe
        if ok.any():
            k = int(np.flatnonzero(ok)[0])
            return a[k], b[k]
    raise AssertionError("no safe move found")


def test_a_new_keep_out_box_invalidates_the_leg_verdicts() -> None:
    motion = MotionChecker(load_robot("fanuc_lrmate200i"), load_cell("demo"))
    a, b = _safe_leg(motion)
    step = math.radians(5.0)
    ok, _ = _legs_safe(motion, a, b, step)
    assert ok.all() and motion.leg_verdicts            # checked and remembered
    # a box around the reflector half-way along the leg
    _, _, _, p = motion.capsules.segments(((a + b) / 2.0)[None, :])
    motion.box_lo = np.vstack([motion.box_lo, p - 0.05])
    motion.box_hi = np.vstack([motion.box_hi, p + 0.05])
    motion.box_names.append("new")
    ok, _ = _legs_safe(motion, a, b, step)
    assert not ok.any()
    assert motion.check_sequence(b[None, :], a)        # the final check sees it too


def test_narrowed_limits_invalidate_the_leg_verdicts() -> None:
    motion = MotionChecker(load_robot("fanuc_lrmate200i"), load_cell("demo"))
    a, b = _safe_leg(motion)
    step = math.radians(5.0)
    assert _legs_safe(motion, a, b, step)[0].all()
    j = int(np.argmax(np.abs(b - a)))
    motion.limits[j] = sorted((a[j], (a[j] + b[j]) / 2.0))    # in place, as the planner does
    assert not _legs_safe(motion, a, b, step)[0].any()
