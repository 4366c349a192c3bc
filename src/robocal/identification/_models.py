"""Error-model structures used by identification, and the priors of joint-angle maps."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal.kinematics import COMPONENTS, ErrorModelSpec, RobotDescription, Term, spline_weights

Array = NDArray[np.float64]


def constant_spec(robot: RobotDescription) -> ErrorModelSpec:
    """The traditional model: a constant 6-DoF error per joint (the DH-equivalent model)."""
    return ErrorModelSpec.constant(robot.dof)


def high_order_spec(robot: RobotDescription, *, order: int = 2, pitch: bool = True,
                    strain_wave: Sequence[int] = (1, 2)) -> ErrorModelSpec:
    """Constant + joint-dependent terms on every joint (Ma et al. 2018 structure).

    Fourier harmonics ``cos/sin(k q)``, k = 1..``order``, on all six error components (bearing
    runout/wobble, rotating-centre offsets), a linear pitch term (Legendre P1) on the rotation
    about the joint axis, and strain-wave ripple ``cos/sin(m N q)`` on that rotation for joints
    whose gear ratio N the robot file gives.
    """
    terms: list[Term] = []
    for j, jt in enumerate(robot.joints):
        for c in COMPONENTS:
            terms.append(Term(j, c, "const"))
            for k in range(1, order + 1):
                terms += [Term(j, c, "cos", k), Term(j, c, "sin", k)]
        if pitch:
            terms.append(Term(j, "ez", "poly", 1))
        if jt.gear_ratio:
            for m in strain_wave:
                terms += [Term(j, "ez", "swcos", int(m)), Term(j, "ez", "swsin", int(m))]
    return ErrorModelSpec(robot.dof, tuple(terms), label=f"high-order:{order}")


def knots_for_spacing(spacing_deg: float) -> int:
    """Number of periodic map knots per revolution for a knot spacing in degrees."""
    return max(8, round(360.0 / spacing_deg))


def knot_counts(q: Array, n_knots: int) -> NDArray[np.intp]:
    """Number of angles ``q`` (n,) rad in the B-spline support of each knot (n_knots,)."""
    idx, _, _ = spline_weights(np.asarray(q, dtype=float), n_knots)
    return np.bincount(idx.ravel(), minlength=n_knots).astype(np.intp)


def span_knots(q: Array, n_knots: int) -> NDArray[np.intp]:
    """Knot indices (sorted) of the whole arc the angles ``q`` (n,) rad span.

    Unlike the knots with data (:func:`knot_counts` > 0), gaps inside the range are bridged: a map
    that simply stops at a gap drops to zero there, far from its values on both sides (a
    pose in the gap then gets a worse correction than the constant model's). Only the
    largest empty arc of the circle is left out (all knots if the data leave no gap wider
    than a knot support).
    """
    u = np.sort(np.mod(np.asarray(q, dtype=float), 2 * math.pi)) * n_knots / (2 * math.pi)
    if len(u) == 0:
        return np.zeros(0, dtype=np.intp)
    gaps = np.diff(np.concatenate([u, [u[0] + n_knots]]))
    g = int(np.argmax(gaps))
    if gaps[g] <= 4.0:
        return np.arange(n_knots, dtype=np.intp)
    start = math.floor(u[(g + 1) % len(u)]) - 1          # first data point after the gap
    stop = math.floor(u[g]) + 2                          # last data point before it
    if stop < start:
        stop += n_knots
    return np.unique(np.arange(start, stop + 1) % n_knots).astype(np.intp)


def map_terms(joint: int, knots: Sequence[int] | NDArray[np.intp]) -> list[Term]:
    """Map terms of one joint for the given knot indices."""
    return [Term(joint, "ez", "map", int(i)) for i in knots]


def second_difference(knots: Sequence[int] | NDArray[np.intp], n_knots: int) -> Array:
    """Second-difference operator D (rows, len(knots)) over the periodic knot sequence.

    A row ``c[i-1] - 2 c[i] + c[i+1]`` is added for each knot whose two neighbours (modulo
    ``n_knots``) are present, so partial coverage gives open segments and full coverage the
    periodic operator.
    """
    knots = [int(k) for k in knots]
    pos = {k: i for i, k in enumerate(knots)}
    rows = []
    for k in knots:
        a, b = (k - 1) % n_knots, (k + 1) % n_knots
        if a in pos and b in pos and a != b:
            r = np.zeros(len(knots))
            r[pos[a]] += 1.0
            r[pos[k]] -= 2.0
            r[pos[b]] += 1.0
            rows.append(r)
    return np.array(rows).reshape(-1, len(knots))


@dataclass(frozen=True)
class MapPrior:
    """Smoothness prior of one joint's angle map, in whitened cost units.

    ``penalty = lam * D^T D + I / ridge_sigma**2`` over the map coefficients (rad), with D the
    second-difference operator. ``lam`` is absolute (1/rad^2); :func:`map_penalty` builds it
    from a relative weight.
    """

    joint: int
    n_knots: int
    knots: tuple[int, ...]
    lam: float
    ridge_sigma: float
    weak: tuple[int, ...] = ()
    tie_sigma: float = math.inf
    weak_sigma: float = math.inf
    anchored: tuple[int, ...] = ()
    anchor_sigma: float = math.inf

    def matrix(self) -> Array:
        """Penalty matrix (k, k) over this map's coefficients."""
        D = second_difference(self.knots, self.n_knots)
        P = self.lam * (D.T @ D) + np.eye(len(self.knots)) / self.ridge_sigma**2
        if self.weak:
            P = P + weak_penalty(self.knots, self.n_knots, self.weak, self.tie_sigma,
                                 self.weak_sigma)
        if self.anchored and math.isfinite(self.anchor_sigma):
            pos = {int(k): i for i, k in enumerate(self.knots)}
            idx = [pos[int(k)] for k in self.anchored]
            P[idx, idx] += 1.0 / self.anchor_sigma**2
        return P

    def to_dict(self) -> dict[str, object]:
        """JSON-friendly description (spacing in degrees)."""
        return {"joint": self.joint + 1, "n_knots": self.n_knots,
                "spacing_deg": 360.0 / self.n_knots, "n_coefficients": len(self.knots),
                "lambda_per_rad2": self.lam, "ridge_sigma_deg": math.degrees(self.ridge_sigma),
                "weak_knots": len(self.weak),
                "tie_sigma_deg": (math.degrees(self.tie_sigma) if math.isfinite(self.tie_sigma)
                                  else None),
                "weak_sigma_deg": (math.degrees(self.weak_sigma)
                                   if math.isfinite(self.weak_sigma) else None),
                "anchored_knots": len(self.anchored),
                "anchor_sigma_deg": (math.degrees(self.anchor_sigma)
                                     if math.isfinite(self.anchor_sigma) else None)}


def weak_knots(knots: Sequence[int] | NDArray[np.intp], counts: NDArray[np.intp],
               min_points: int) -> tuple[int, ...]:
    """Knots of ``knots`` with fewer than ``min_points`` angles in their support."""
    return tuple(int(k) for k in knots if counts[int(k)] < min_points)


def weak_penalty(knots: Sequence[int] | NDArray[np.intp], n_knots: int, weak: Sequence[int],
                 tie_sigma: float, weak_sigma: float) -> Array:
    """Extra prior (k, k) on sparsely supported knots: tied to neighbours, shrunk to zero.

    Where few poses constrain a map, the maps of neighbouring joints (and the harmonics) can
    trade large opposite values that cancel on those poses only; shrinking the weak knots
    towards zero leaves such regions to the parametric terms and the constant model.
    """
    k = len(knots)
    P = np.zeros((k, k))
    if math.isfinite(tie_sigma):
        T = tie_rows(knots, n_knots, weak)
        P += (T.T @ T) / tie_sigma**2
    if math.isfinite(weak_sigma):
        pos = {int(v): i for i, v in enumerate(knots)}
        for w in weak:
            P[pos[int(w)], pos[int(w)]] += 1.0 / weak_sigma**2
    return P


def tie_rows(knots: Sequence[int] | NDArray[np.intp], n_knots: int,
             weak: Sequence[int]) -> Array:
    """First-difference rows (m, len(knots)) ``c[k+1] - c[k]`` for neighbours one of which is weak.

    Tying sparsely supported knots to their neighbours makes the map interpolate linearly
    across thin data and stay flat beyond the last well supported knot, instead of following
    the one or two poses that happen to lie there.
    """
    pos = {int(k): i for i, k in enumerate(knots)}
    wk = {int(k) for k in weak}
    rows = []
    for k in pos:
        b = (k + 1) % n_knots
        if b in pos and b != k and (k in wk or b in wk):
            r = np.zeros(len(pos))
            r[pos[k]] -= 1.0
            r[pos[b]] += 1.0
            rows.append(r)
    return np.array(rows).reshape(-1, len(pos))


def penalty_for(names: Sequence[str], priors: Sequence[MapPrior]) -> Array | None:
    """Full (P, P) penalty for a parameter list, or None without priors."""
    if not priors:
        return None
    idx = {n: i for i, n in enumerate(names)}
    Pm = np.zeros((len(names), len(names)))
    for pr in priors:
        cols = np.array([idx[t.name] for t in map_terms(pr.joint, pr.knots)], dtype=np.intp)
        Pm[np.ix_(cols, cols)] += pr.matrix()
    return Pm
