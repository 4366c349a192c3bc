"""The swept-path check's shortcuts give the verdicts of checking every sample (ADR 0039)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from robocal.kinematics import load_robot
from robocal.planning import MotionChecker, MoveCheck, load_cell

Array = NDArray[np.float64]


def _every_sample(motion: MotionChecker, q_from: Array, q_to: Array) -> MoveCheck:
    """Reference: every sample checked; a move's reported sample is its first failing
    coarse sample (every 8th and the end) if any, else its first failing sample."""
    q, owner, s = motion.samples(q_from, q_to)
    bad = motion.bad(q)
    n = motion.intervals(q_from, q_to)
    first = np.concatenate([[0], np.cumsum(n + 1)[:-1]])
    offset = np.arange(len(q)) - np.repeat(first, n + 1)
    coarse = (offset % 8 == 0) | (s == 1.0)
    m = len(q_from)
    safe = np.ones(m, dtype=bool)
    at = np.full(m, np.nan)
    q_bad = np.full((m, q.shape[1]), np.nan)
    for k in range(m):
        mine = owner == k
        hits = np.flatnonzero(mine & bad & coarse)
        if not hits.size:
            hits = np.flatnonzero(mine & bad)
        if hits.size:
            safe[k], at[k], q_bad[k] = False, s[hits[0]], q[hits[0]]
    return MoveCheck(safe=safe, samples=n, at=at, q_bad=q_bad, reasons=[])


def _random_moves(motion: MotionChecker, n: int, seed: int) -> tuple[Array, Array]:
    rng = np.random.default_rng(seed)
    lo, hi = motion.limits[:, 0], motion.limits[:, 1]
    a = lo + rng.random((n, len(lo))) * (hi - lo)
    b = a + rng.normal(scale=math.radians(40.0), size=a.shape)
    return a, np.clip(b, lo - 0.05, hi + 0.05)


def test_pruned_samples_give_the_verdicts_of_every_sample() -> None:
    for robot in ("fanuc_lrmate200i", "ur10"):
        motion = MotionChecker(load_robot(robot), load_cell("demo"))
        a, b = _random_moves(motion, 120, seed=7)
        got = motion.check_moves(a, b, explain=False)
        ref = _every_sample(motion, a, b)
        assert 0 < got.safe.sum() < len(a)          # both kinds present
        np.testing.assert_array_equal(got.safe, ref.safe)
        np.testing.assert_array_equal(got.at, ref.at)
        np.testing.assert_array_equal(got.q_bad, ref.q_bad)


def test_check_sequence_trusts_only_moves_checked_under_the_same_limits() -> None:
    motion = MotionChecker(load_robot("fanuc_lrmate200i"), load_cell("demo"))
    a, b = _random_moves(motion, 60, seed=3)
    safe = motion.check_moves(a, b).safe
    q = np.array([a[safe][0], b[safe][0]])             # one safe move as a sequence
    assert motion.check_sequence(q[1:], home=q[0]) == []
    # the planner narrows the limits in place: the remembered verdict no longer holds
    j = int(np.argmax(np.abs(q[1] - q[0])))
    motion.limits[j] = sorted((q[0, j], 0.5 * (q[0, j] + q[1, j])))
    unsafe = motion.check_sequence(q[1:], home=q[0])
    assert len(unsafe) == 1 and "outside" in unsafe[0].reason


def test_check_sequence_reports_unsafe_moves_among_known_safe_ones() -> None:
    motion = MotionChecker(load_robot("fanuc_lrmate200i"), load_cell("demo"))
    a, b = _random_moves(motion, 60, seed=5)
    res = motion.check_moves(a, b)
    i_ok, i_bad = np.flatnonzero(res.safe)[:2], np.flatnonzero(~res.safe)[0]
    # home -> b[i_ok[0]] (unknown) -> a[i_bad] (unknown) -> b[i_bad] (unsafe, known unsafe)
    seq = np.array([a[i_ok[0]], b[i_ok[0]], a[i_bad], b[i_bad]])
    unsafe = MotionChecker(motion.robot, motion.cell).check_sequence(seq[1:], home=seq[0])
    cached = motion.check_sequence(seq[1:], home=seq[0])
    assert [u.index for u in cached] == [u.index for u in unsafe]
    assert 2 in [u.index for u in cached]
    assert [u.reason for u in cached] == [u.reason for u in unsafe]
