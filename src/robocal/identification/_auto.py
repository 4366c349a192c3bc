"""``auto`` model: choose joint-dependent terms, orders and joint-angle maps by cross-validation.

Method
------
1. Fit the constant model (robust; gives inliers and the linearisation point ``x_c``).
2. Build a *candidate superset*: per joint, Fourier harmonics of order 1..K on all six error
   components (one group per order; not nested: with position-only data the first harmonic
   of the last joint is nearly invisible while its second is not), a linear pitch term,
   strain-wave ripple per gear-ratio multiple, gravity torsion (robots with masses), and a
   periodic cubic-spline joint-angle map on the rotation about the joint axis (knots only
   where data lies).
3. Linearise at ``x_c`` (the joint-dependent errors are micro-radians, so the problem is linear
   in them to far below the noise) and accumulate per-fold normal matrices of the whitened
   superset Jacobian once. Any candidate model is then a sub-block of these matrices, and its
   K-fold cross-validated sum of squares costs a few small Cholesky solves, no pass over the
   data. Maps are MAP-estimated with a second-difference smoothness prior (weight chosen from
   a grid by CV) and a weak ridge.
4. Greedy forward selection of groups (adding the one that lowers the CV score most, as long
   as it lowers it by at least ``auto_min_improvement``) in three phases: physically modelled
   single terms (gravity, pitch, strain wave), then harmonics, then maps, so that flexible
   maps only take what the parametric terms cannot describe. Then the map smoothness is
   refined (x3 steps) and a backward pass drops groups whose removal does not worsen the
   score. CV folds keep near-repeated configurations together.
5. Solve the chosen model nonlinearly (robust, outliers re-tested) from ``x_c``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.arrays import Array, IntArray
from robocal.errors import IdentificationError
from robocal.identification._engine import Solution
from robocal.identification._fitter import Fitter as _Fitter
from robocal.identification._linalg import block_diag, spd_inverse, spd_solve
from robocal.identification._models import (
    MapPrior,
    knot_counts,
    knots_for_spacing,
    map_terms,
    second_difference,
    span_knots,
    weak_knots,
    weak_penalty,
)
from robocal.identification._solver import Problem, analyse_jacobian
from robocal.identification._structured import normal_blocks
from robocal.kinematics import (
    COMPONENTS,
    ErrorModelSpec,
    KinematicModel,
    ParameterLayout,
    Term,
    gravity_torques,
)


@dataclass
class Group:
    """A block of terms added or removed together."""

    key: str
    terms: list[Term]
    requires: str | None = None
    is_map: bool = False
    joint: int = 0
    n_knots: int = 0
    knots: tuple[int, ...] = ()
    weak: tuple[int, ...] = ()
    cols: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    # map prior pieces in scaled coordinates
    D2: Array | None = None       # scaled D^T D (g, g)
    ridge: Array | None = None    # scaled ridge diagonal (g,)
    tie: Array | None = None      # scaled tie penalty of weak knots (g, g)
    lam_unit: float = 1.0         # absolute lambda per unit relative lambda

    @property
    def is_ripple(self) -> bool:
        """A fine ripple harmonic (left out of the superset's rank analysis)."""
        return ":ripple" in self.key

    @property
    def phase(self) -> int:
        """Selection phase: 1 physical terms, 2 low harmonics, 3 maps and fine ripple."""
        if self.is_map or ":ripple" in self.key:
            return 3
        return 2 if ":fourier" in self.key else 1


def candidate_groups(f: _Fitter, q: Array) -> list[Group]:
    """Candidate term groups for the robot and the joint ranges in ``q`` (n, dof) rad."""
    robot, opts = f.robot, f.opts
    groups: list[Group] = []
    tau = gravity_torques(robot, q) if (opts.auto_gravity and robot.has_masses) else None
    for j, jt in enumerate(robot.joints):
        # A harmonic of order k on a joint whose angle takes fewer than 2k + 2 distinct values
        # (1 deg apart) interpolates those values exactly together with the constant term:
        # cross-validation cannot see it overfit (every fold holds every value), and its
        # coupling with other joints' terms explodes elsewhere (UR10 series D: J6 at -90, 0
        # and 90 deg only, 10 mm off at a configuration unlike the training ones).
        distinct = len(np.unique(np.round(np.degrees(q[:, j]))))
        for k in range(1, opts.auto_max_order + 1):
            if distinct < 2 * k + 2:
                continue
            terms = [Term(j, c, fam, k) for c in COMPONENTS for fam in ("cos", "sin")]
            groups.append(Group(f"j{j + 1}:fourier{k}", terms, joint=j))
        for k in opts.auto_ripple_orders:
            if k > opts.auto_max_order and distinct >= 2 * k + 2:
                # fine periodic joint-angle error (gear and encoder ripple, many cycles per
                # revolution) on the rotation about the axis: two columns, cheap to test
                groups.append(Group(f"j{j + 1}:ripple{k}", [Term(j, "ez", "cos", int(k)),
                                                            Term(j, "ez", "sin", int(k))],
                                    joint=j))
        groups.append(Group(f"j{j + 1}:pitch", [Term(j, "ez", "poly", 1)], joint=j))
        if jt.gear_ratio and opts.auto_strain_wave:
            for m in opts.strain_wave:
                sw = [Term(j, "ez", "swcos", int(m)), Term(j, "ez", "swsin", int(m))]
                groups.append(Group(f"j{j + 1}:strain-wave{m}", sw, joint=j))
        if tau is not None and float(np.std(tau[:, j])) > 1e-3:
            groups.append(Group(f"j{j + 1}:gravity", [Term(j, "ez", "gravity")], joint=j))
        if opts.auto_maps:
            K = knots_for_spacing(opts.map_spacing_deg)
            kn = span_knots(q[:, j], K)
            # map_spacing_deg is the finest spacing: fewer poses widen it until a knot's
            # support (four spacings) holds map_min_points poses on average over the arc
            # the data span; finer knots would be set by the smoothness prior alone
            h_deg = opts.map_min_points * (len(kn) * 360.0 / K) / (4.0 * max(len(q), 1))
            if h_deg > opts.map_spacing_deg and knots_for_spacing(h_deg) < K:
                K = knots_for_spacing(h_deg)
                kn = span_knots(q[:, j], K)
            counts = knot_counts(q[:, j], K)
            weak = weak_knots(kn, counts, opts.map_min_points)
            if len(kn) - len(weak) >= 4:
                groups.append(Group(f"j{j + 1}:map", map_terms(j, kn), is_map=True, joint=j,
                                    n_knots=K, knots=tuple(int(v) for v in kn), weak=weak))
    return groups


# Smallest eigenvalue of a Schur complement, relative to the largest diagonal element of the
# block it was computed from, below which the fold factors are recomputed instead of updated
# (about 8 of the 16 digits left).
SCHUR_RTOL = 1e-8


@dataclass
class _FoldBase:
    """Factorised base model of one CV fold: what adding a candidate group needs.

    ``Ainv`` (k, k) is the inverse training normal matrix (plus prior) of the base columns
    and ``X = Ainv @ Gtr[base, act]`` (k, a) for the *active* superset columns ``act`` (the
    candidates' columns), so a candidate group only indexes columns of X. (The held-out
    matrix ``Gf[base, base]`` is applied to ``X dg`` per option instead of being carried
    as ``Gf[base, base] @ X``: updating that product cost O(k g a) per added group and
    fold, more than the products it saved; see ``_held_out_q``.)
    """

    Ainv: Array
    X: Array


class _CV:
    """K-fold CV of linearised sub-models from per-fold normal matrices (column-scaled)."""

    def __init__(self, G_f: Array, b_f: Array, c_f: Array, G: Array | None = None) -> None:
        self.G_f, self.b_f, self.c_f = G_f, b_f, c_f
        self.G = G_f.sum(axis=0) if G is None else G   # (the sum over the folds)
        self.b = b_f.sum(axis=0)
        self.K = G_f.shape[0]
        self.evaluations = 0
        self.refactorisations = 0
        # base columns, their prior, the active columns and each fold's factorised base
        self._cache: tuple[IntArray, Array, IntArray, list[_FoldBase]] | None = None
        self._inv_cache: tuple[IntArray, Array, list[Array]] | None = None
        # held-out normal matrix of each fold over the columns of the model last varied
        self._held_cache: tuple[IntArray, list[Array]] | None = None

    def fold_bases(self, base_cols: IntArray, base_pen: Array, act: IntArray
                   ) -> list[_FoldBase]:
        """Factorised base model of each fold over the active columns ``act`` (sorted).

        Forward selection extends the base by one group at a time; then the previous
        factorisation is updated with the block (Schur-complement) formulas, O(k g a) for g
        new columns, instead of being recomputed, O(k^2 a). Only the columns of the groups
        still to be tried are carried (``act``): in the early phases the maps (most of the
        superset) are not candidates, and a chosen group's columns are never needed again.
        Columns becoming active (a new phase) make the factors be recomputed: completing
        them from the updated ``Ainv`` loses digits on columns nearly in the span of the
        base (a fine ripple harmonic next to that joint's map), where the Schur complement
        is a small difference of large numbers.
        """
        c = self._cache
        if c is not None:
            old_cols, old_pen, old_act, bases = c
            k0 = len(old_cols)
            g = base_cols[k0:]
            if (len(base_cols) >= k0 and np.array_equal(base_cols[:k0], old_cols)
                    and np.array_equal(base_pen[:k0, :k0], old_pen)
                    and not np.any(base_pen[:k0, k0:]) and np.isin(g, old_act).all()
                    and np.isin(act, old_act).all()):
                if (len(g) == 0 and len(act) == len(old_act)
                        and np.array_equal(act, old_act)):
                    return bases
                # replaced fold by fold, so that only one fold's old and new factors are
                # held at once
                self._cache = None
                for f in range(len(bases)):
                    fb_new: _FoldBase | None = bases[f]
                    if len(g):
                        fb_new = self._extend(f, old_cols, old_act, bases[f], g,
                                              base_pen[k0:, k0:])
                    if fb_new is None:
                        break
                    bases[f] = self._columns(old_act, fb_new, act)
                else:
                    self._cache = (base_cols.copy(), base_pen.copy(), act.copy(), bases)
                    return bases
                del bases                      # (a mix of updated and old factors)
                self.refactorisations += 1
        self._cache = c = None                              # let the old factors go first
        ixb = np.ix_(base_cols, base_cols)
        Gb = self.G[ixb] + base_pen
        bases = []
        for f in range(self.K):
            Ainv = _inv_spd(Gb - self.G_f[f][ixb])
            bases.append(_FoldBase(Ainv, Ainv @ self._train(f, base_cols, act)))
        self._cache = (base_cols.copy(), base_pen.copy(), act.copy(), bases)
        return bases

    def _train(self, f: int, rows: IntArray, cols: IntArray) -> Array:
        """Training normal matrix of fold ``f``, block ``rows`` x ``cols``."""
        ix = np.ix_(rows, cols)
        return np.asarray(self.G[ix] - self.G_f[f][ix])

    @staticmethod
    def _columns(old_act: IntArray, fb: _FoldBase, act: IntArray) -> _FoldBase:
        """``fb`` (columns ``old_act``) restricted to the active columns ``act`` (a subset)."""
        pos = np.searchsorted(old_act, act)
        return _FoldBase(fb.Ainv, fb.X[:, pos])

    def train_gains(self, base_cols: IntArray, base_pen: Array, C: Array, pens: Array,
                    act: IntArray) -> Array:
        """Score-test gains (m,) of groups with columns ``C`` (m, g) and priors ``pens``.

        On the training part of the first fold (most of the data) the base model leaves a
        residual; a group's gain is the drop of the training sum of squares when it is
        added, ``r^T S^-1 r`` with the group's columns projected off the base (``S``, the
        Schur complement) and their correlation ``r`` with the residual. It needs the same
        factors as the cross-validation, and of one fold only: it ranks a large family of
        candidates (fine ripple) so that only the best few are cross-validated.
        """
        fb = self.fold_bases(base_cols, base_pen, act)[0]
        A = np.searchsorted(act, C)
        X = fb.X[:, A].transpose(1, 0, 2)                                 # (m, k, g)
        cc = (C[:, :, None], C[:, None, :])
        Gtr_b = self._train(0, base_cols, np.unique(C))
        Ab = np.searchsorted(np.unique(C), C)
        btr = self.b - self.b_f[0]
        S = (self.G[cc] - self.G_f[0][cc]) + pens - Gtr_b[:, Ab].transpose(1, 2, 0) @ X
        r = btr[C] - X.transpose(0, 2, 1) @ btr[base_cols]
        return np.asarray(np.sum(r * _spd_solve_stack(S, r), axis=1), dtype=np.float64)

    def _extend(self, f: int, b: IntArray, act: IntArray, fb: _FoldBase, g: IntArray,
                gpen: Array) -> _FoldBase | None:
        """``fb`` for base columns ``b`` extended by active columns ``g`` with prior ``gpen``;
        None when the update would lose too many digits (see ``SCHUR_RTOL``)."""
        pg = np.searchsorted(act, g)
        Xg = fb.X[:, pg]                                    # Ainv @ Gtr[b, g]
        Gtr_gb = self._train(f, g, b)
        Ggg = self._train(f, g, g) + gpen
        S = Ggg - Gtr_gb @ Xg
        # S is a difference of nearly equal matrices when the new columns lie almost in the
        # span of the base (a fine map after its joint's harmonics): it then keeps only the
        # digits the ratio below leaves, and every later score inherits the error
        if np.linalg.eigvalsh(S)[0] < SCHUR_RTOL * float(np.max(np.diagonal(Ggg))):
            return None
        Sinv = _inv_spd(S)
        R = Sinv @ (Gtr_gb @ fb.X - self._train(f, g, act))  # (g, a)
        X_top = fb.X + Xg @ R
        XS = Xg @ Sinv
        Ainv = np.block([[fb.Ainv + XS @ Xg.T, -XS], [-XS.T, Sinv]])
        return _FoldBase(Ainv, np.vstack([X_top, -R]))

    def score(self, cols: IntArray, pen: Array) -> float:
        """CV sum of squares (whitened) of the model with columns ``cols`` and prior ``pen``."""
        self.evaluations += 1
        ix = np.ix_(cols, cols)
        Gc = self.G[ix] + pen
        total = 0.0
        for f in range(self.K):
            Gf = self.G_f[f][ix]
            bf = self.b_f[f][cols]
            A = Gc - Gf
            d = _spd_or_lstsq(A, self.b[cols] - bf)
            total += float(self.c_f[f] - 2.0 * d @ bf + d @ Gf @ d)
        return total

    def keep_inverses_only(self) -> None:
        """Let the forward selection's X go: the later passes need the inverses only."""
        c = self._cache
        if c is not None:
            self._inv_cache = (c[0], c[1], [fb.Ainv for fb in c[3]])
        self._cache = None

    def fold_inverses(self, cols: IntArray, pen: Array) -> list[Array]:
        """Inverse training normal matrix (plus prior) of each fold for columns ``cols``."""
        c = self._cache
        if c is not None and np.array_equal(c[0], cols) and np.array_equal(c[1], pen):
            return [fb.Ainv for fb in c[3]]
        ci = self._inv_cache
        if ci is not None and np.array_equal(ci[0], cols) and np.array_equal(ci[1], pen):
            return ci[2]
        ix = np.ix_(cols, cols)
        Gc = self.G[ix] + pen
        invs = [_inv_spd(Gc - self.G_f[f][ix]) for f in range(self.K)]
        self._inv_cache = (cols.copy(), pen.copy(), invs)
        return invs

    def adopt_variant(self, cols: IntArray, pen: Array, new_cols: IntArray, new_pen: Array,
                      drop: IntArray | None = None,
                      repen: tuple[IntArray, Array] | None = None) -> None:
        """Keep the fold inverses of a variant chosen from ``scores_varied`` (low-rank update).

        The forward selection's factors (and their X) are let go first, and the inverses
        replaced fold by fold: with maps each is ~1,700^2 doubles, five folds ~120 MB.
        """
        invs = self.fold_inverses(cols, pen)
        self._cache = self._inv_cache = None
        for f, P in enumerate(invs):
            if drop is not None:
                r = np.setdiff1d(np.arange(len(cols)), drop)
                Ppr = P[np.ix_(drop, r)]
                invs[f] = P[np.ix_(r, r)] - Ppr.T @ _solve_small(P[np.ix_(drop, drop)], Ppr)
            elif repen is not None:
                p, dpen = repen
                invs[f] = P - P[:, p] @ dpen @ _solve_small(
                    np.eye(len(p)) + P[np.ix_(p, p)] @ dpen, P[p, :])
            del P
        self._inv_cache = (new_cols.copy(), new_pen.copy(), invs)

    def held_out_blocks(self, cols: IntArray) -> list[Array]:
        """Held-out normal matrix of each fold over ``cols``, kept while the columns stay:
        the smoothness refinement varies only priors, and gathering K blocks of k^2 from
        the P x P fold matrices cost more than its Woodbury updates."""
        c = self._held_cache
        if c is not None and np.array_equal(c[0], cols):
            return c[1]
        self._held_cache = None
        ix = np.ix_(cols, cols)
        blocks = [np.asarray(self.G_f[f][ix]) for f in range(self.K)]
        self._held_cache = (cols.copy(), blocks)
        return blocks

    def scores_varied(self, cols: IntArray, pen: Array, drops: Sequence[IntArray],
                      repens: Sequence[tuple[IntArray, Array]]) -> tuple[list[float], list[float]]:
        """CV scores of variants of the model (``cols``, ``pen``) without refitting it.

        ``drops``: positions (into ``cols``) of a block removed from the model; ``repens``:
        positions of a block and the change of its prior. Both are low-rank changes of the
        fold inverses (block downdate; Woodbury), O(k^2 g) per fold instead of O(k^3): the
        backward pass and the smoothness refinement try dozens of variants of a model with
        several hundred columns.
        """
        self.evaluations += len(drops) + len(repens)
        s_drop = np.zeros(len(drops))
        s_pen = np.zeros(len(repens))
        held = self.held_out_blocks(cols)
        for f, P in enumerate(self.fold_inverses(cols, pen)):
            btr = self.b[cols] - self.b_f[f][cols]
            bf = self.b_f[f][cols]
            Gf = held[f]
            d = P @ btr
            for i, p in enumerate(drops):
                # the reduced solution embedded in full coordinates (zero on the block):
                # matrix-vector products only, no copy of the (k, k) sub-matrices
                z = btr.copy()
                z[p] = 0.0
                Pz = P @ z
                d_r = Pz - P[:, p] @ _solve_small(P[np.ix_(p, p)], Pz[p])
                d_r[p] = 0.0
                s_drop[i] += float(self.c_f[f] - 2.0 * d_r @ bf + d_r @ Gf @ d_r)
            for i, (p, dpen) in enumerate(repens):
                corr = dpen @ _solve_small(np.eye(len(p)) + P[np.ix_(p, p)] @ dpen, d[p])
                d_v = d - P[:, p] @ corr
                s_pen[i] += float(self.c_f[f] - 2.0 * d_v @ bf + d_v @ Gf @ d_v)
        return list(s_drop), list(s_pen)

    def scores_added(self, base_cols: IntArray, base_pen: Array,
                     options: list[tuple[IntArray, list[Array]]],
                     also_active: IntArray | None = None) -> list[list[float]]:
        """CV scores of ``base + group`` for many groups, each with several priors.

        Schur complements on the factorised base of each fold (``fold_bases``): a group of g
        columns then costs O(k g^2) per fold for k base columns, and each prior O(g^3).
        Groups of equal size are evaluated together as stacked arrays (the ripple family
        alone is a few hundred two-column groups), and the small systems of every fold are
        solved in one stacked call (a forward round of small groups is otherwise dominated
        by the per-call cost of hundreds of tiny solves). ``also_active``: further columns
        the fold factors keep (candidates of later calls).
        """
        self.evaluations += sum(len(p) for _, p in options)
        out = [np.zeros(len(p)) for _, p in options]
        # groups of one size are stacked; the small parametric groups (1-12 columns) are
        # stacked together, padded to the largest (see _pad): one batch instead of one per size
        by_size: dict[int, list[int]] = {}
        for i, (gcols, _) in enumerate(options):
            by_size.setdefault(0 if len(gcols) <= PAD_UP_TO else len(gcols), []).append(i)
        # groups of one size in batches of at most ~32 MB of stacked temporaries over all
        # folds (the map groups have hundreds of columns, each tried with several priors)
        k = len(base_cols)
        batches = []
        for idx_all in by_size.values():
            g = max(len(options[i][0]) for i in idx_all)
            n_opt = max(len(options[i][1]) for i in idx_all)
            step = max(1, int(32e6 // (8 * self.K * (4 * k * g + 4 * n_opt * g * g))))
            batches += [idx_all[a:a + step] for a in range(0, len(idx_all), step)]
        extra = [] if also_active is None else [also_active]
        act = np.unique(np.concatenate([c for c, _ in options] + extra))
        bases = self.fold_bases(base_cols, base_pen, act)
        ixbb = np.ix_(base_cols, base_cols)
        # per fold: training right-hand side and solution of the base model, the held-out
        # residual correlation it leaves, and its held-out sum of squares
        pre = []
        for f, fb in enumerate(bases):
            btr = self.b[base_cols] - self.b_f[f][base_cols]
            dA = fb.Ainv @ btr
            bf_b = self.b_f[f][base_cols]
            Gf_bb = self.G_f[f][ixbb]
            GdA = Gf_bb @ dA
            pre.append((btr, dA, bf_b - GdA, float(self.c_f[f] - 2.0 * dA @ bf_b + dA @ GdA),
                        Gf_bb))
        for idx in batches:
            C, mask = _pad([options[i][0] for i in idx])            # (m, g) superset columns
            m, g = C.shape
            A = np.searchsorted(act, C)                             # (m, g) active positions
            cc = (C[:, :, None], C[:, None, :])
            ixbc = np.ix_(base_cols, C.ravel())
            G_bc = self.G[ixbc]                                     # (k, m g)
            G_cc = self.G[cc]
            opt_of = np.array([a for a, i in enumerate(idx) for _ in options[i][1]])
            pens = np.stack([_pad_square(p, g) for i in idx for p in options[i][1]])
            if mask is not None:
                # padding columns: zero in every gathered block, identity in the system
                mm = mask[:, :, None] & mask[:, None, :]
                G_bc *= mask.ravel()[None, :]
                G_cc = G_cc * mm + (~mask)[:, :, None] * np.eye(g)[None]
            # a group's priors differ by multiples of one positive semidefinite matrix (a
            # map's smoothness grid): its least definite system is the one of smallest trace
            tr_pen = np.trace(pens, axis1=1, axis2=2)
            least = np.zeros(len(opt_of), dtype=bool)
            for a in range(m):
                e_a = np.flatnonzero(opt_of == a)
                least[e_a[int(np.argmin(tr_pen[e_a]))]] = True
            parts = []
            Ms, rhss = [], []
            for f, fb in enumerate(bases):
                Gf = self.G_f[f]
                btr, dA, res_b, _, _ = pre[f]
                X = fb.X[:, A].transpose(1, 0, 2)                   # (m, k, g)
                Gf_bg = Gf[ixbc].reshape(k, m, g).transpose(1, 0, 2)  # (m, k, g)
                Gf_cc = Gf[cc]
                bf_c = self.b_f[f][C]
                btr_c = self.b[C] - bf_c
                if mask is not None:
                    X = X * mask[:, None, :]
                    Gf_bg = Gf_bg * mask[:, None, :]
                    Gf_cc = Gf_cc * mm
                    bf_c = bf_c * mask
                    btr_c = btr_c * mask
                Xt = X.transpose(0, 2, 1)
                Gtr_gb = (G_bc.reshape(k, m, g).transpose(1, 2, 0)
                          - Gf_bg.transpose(0, 2, 1))               # (m, g, k)
                S0 = (G_cc - Gf_cc) - Gtr_gb @ X
                rhs = btr_c - Xt @ btr
                # held-out SSE as a quadratic in dg (db = dA - X dg): dg^T Q dg + 2 lin dg
                lin = Xt @ res_b - bf_c + Gf_bg.transpose(0, 2, 1) @ dA
                Ms.append(S0[opt_of] + pens)
                rhss.append(rhs[opt_of])
                parts.append((X, Gf_bg, Gf_cc, lin))
            dg_all = _spd_solve_stack(np.concatenate(Ms), np.concatenate(rhss),
                                      np.tile(least, self.K))
            del Ms, rhss
            E = len(opt_of)
            vals = np.zeros(E)
            for f, (X, Gf_bg, Gf_cc, lin) in enumerate(parts):
                dg = dg_all[f * E:(f + 1) * E]
                Qdg = _held_out_q(X, pre[f][4], Gf_bg, Gf_cc, dg, opt_of)
                vals += pre[f][3] + np.sum(dg * (2.0 * lin[opt_of] + Qdg), axis=1)
            e = 0
            for i in idx:
                n_p = len(options[i][1])
                out[i] += vals[e:e + n_p]
                e += n_p
        return [list(o) for o in out]


# groups of up to this many columns are stacked together, padded (see _pad)
PAD_UP_TO = 16


def _pad(cols: Sequence[IntArray]) -> tuple[IntArray, NDArray[np.bool_] | None]:
    """Column lists of unequal length (m,) as one (m, g) array, each padded with its own
    first column, and the mask of real entries (None when none is padded). The caller
    zeroes the padding in every gathered block and puts an identity on its diagonal, so
    a padded coefficient solves to zero and changes no score."""
    g = max(len(c) for c in cols)
    if all(len(c) == g for c in cols):
        return np.stack(cols), None
    C = np.stack([np.concatenate([c, np.full(g - len(c), c[0])]) for c in cols])
    mask = np.arange(g)[None, :] < np.array([len(c) for c in cols])[:, None]
    return C.astype(np.intp), mask


def _pad_square(P: Array, g: int) -> Array:
    """``P`` (h, h) in the top-left corner of a (g, g) zero matrix."""
    if P.shape[0] == g:
        return P
    out = np.zeros((g, g))
    out[:P.shape[0], :P.shape[0]] = P
    return out


def _held_out_q(X: Array, Gbb: Array, Gbg: Array, Ggg: Array, dg: Array, opt_of: IntArray
                ) -> Array:
    """``Q dg`` (E, g) for the held-out quadratic ``Q = X^T Gbb X - X^T Gbg - Gbg^T X + Ggg``.

    X, Gbg (m, k, g) and Ggg (m, g, g) per group, Gbb (k, k) the fold's held-out normal
    matrix of the base; dg (E, g) per option, option e of group ``opt_of[e]``.
    Matrix-vector products, O(k g + k^2) per option: forming Q costs O(k g^2) per group,
    which for the maps (g of several hundred) dominated the forward selection.
    """
    if len(opt_of) == X.shape[0]:                               # one option per group
        d = dg[..., None]
        u = X @ d                                               # (m, k, 1)
        return np.asarray((X.transpose(0, 2, 1) @ (Gbb @ u - Gbg @ d)
                           - Gbg.transpose(0, 2, 1) @ u + Ggg @ d)[..., 0], dtype=np.float64)
    out = np.empty_like(dg)
    for a in np.unique(opt_of):
        e = opt_of == a
        D = dg[e].T                                                 # (g, n_options)
        U = X[a] @ D
        Qd = X[a].T @ (Gbb @ U - Gbg[a] @ D) - Gbg[a].T @ U + Ggg[a] @ D
        out[e] = Qd.T
    return out


def cv_folds(q: Array, k: int, seed: int, tol: float) -> IntArray:
    """Fold index (n,) per pose; poses within ``tol`` rad in every joint share a fold.

    Near-repeats of a configuration (common in real campaigns) would otherwise sit on both
    sides of a split and reward models that memorise them.
    """
    n = q.shape[0]
    parent = np.arange(n)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    if tol > 0 and n > 1:
        for i, j in close_pairs(q, tol):
            ri, rj = find(int(i)), find(int(j))
            if ri != rj:
                parent[max(ri, rj)] = min(ri, rj)
    roots = np.array([find(i) for i in range(n)])
    uniq, group = np.unique(roots, return_inverse=True)
    rng = np.random.default_rng(seed)
    fold_of_group = np.empty(len(uniq), dtype=np.intp)
    fold_of_group[rng.permutation(len(uniq))] = np.arange(len(uniq)) % k
    return fold_of_group[group]


def close_pairs(q: Array, tol: float) -> IntArray:
    """Index pairs (m, 2), i < j, of rows of ``q`` (n, d) within ``tol`` in every column.

    Sweep over the rows sorted by the first column: only rows whose first coordinate lies
    within ``tol`` are compared (no k-d tree needed for a few thousand poses).
    """
    order = np.argsort(q[:, 0], kind="stable")
    qs = q[order]
    hi = np.searchsorted(qs[:, 0], qs[:, 0] + tol, side="right")
    out: list[IntArray] = []
    for a in range(len(qs) - 1):
        if hi[a] <= a + 1:
            continue
        cand = np.arange(a + 1, hi[a])
        close = np.all(np.abs(qs[cand] - qs[a]) <= tol, axis=1)
        if close.any():
            b = cand[close]
            i, j = order[a], order[b]
            out.append(np.stack([np.minimum(i, j), np.maximum(i, j)], axis=1))
    return np.concatenate(out).astype(np.intp) if out else np.zeros((0, 2), dtype=np.intp)


def _spd_solve_stack(M: Array, r: Array, proof: NDArray[np.bool_] | None = None) -> Array:
    """Solve stacked SPD systems ``M[e] x[e] = r[e]``, M (E, g, g), r (E, g); singular ones by
    least squares.

    ``proof`` (E,): the matrices whose Cholesky factorisation is taken as the proof that all
    are positive definite (default: every one). A caller may leave a matrix out when it is
    a proven one plus a positive semidefinite matrix (a map's prior at a larger smoothness
    weight): the factorisation only proves definiteness, and costs half the solve.
    """
    try:
        # raises unless every matrix checked is positive definite
        np.linalg.cholesky(M if proof is None or proof.all() else M[proof])
        if not np.all(np.isfinite(M)):
            raise np.linalg.LinAlgError("matrix is not finite")
        return np.asarray(np.linalg.solve(M, r[..., None])[..., 0], dtype=np.float64)
    except np.linalg.LinAlgError:
        return np.stack([_spd_or_lstsq(M[e], r[e]) for e in range(len(M))])


def _spd_or_lstsq(A: Array, b: Array) -> Array:
    """``A^-1 b`` for symmetric positive definite ``A``; least squares when it is not."""
    try:
        return spd_solve(A, b)
    except np.linalg.LinAlgError:
        return np.asarray(np.linalg.lstsq(A, b, rcond=1e-12)[0], dtype=np.float64)


def _solve_small(A: Array, b: Array) -> Array:
    """``A^-1 b`` for a small square ``A``; least squares when it is singular."""
    try:
        return np.asarray(np.linalg.solve(A, b), dtype=np.float64)
    except np.linalg.LinAlgError:
        return np.asarray(np.linalg.lstsq(A, b, rcond=1e-12)[0], dtype=np.float64)


def _inv_spd(A: Array) -> Array:
    try:
        return spd_inverse(A)
    except np.linalg.LinAlgError:
        # numpy stub types pinv() of any float input as floating[Any]; float64 in gives float64
        return np.linalg.pinv(A, rcond=1e-12, hermitian=True)  # type: ignore[return-value]


def auto_select(f: _Fitter, const: Solution) -> tuple[Solution, list[dict[str, Any]]]:
    """Choose and fit the ``auto`` model; return the solution and the selection log.

    Gross errors of a few mm hide in the heavy-tailed residuals of the constant model (a few
    robust sigmas there), but stand out against a joint-dependent model. So the poses the
    selection works on are screened by a robust ``high-order`` fit first, and if the final
    ``auto`` model still rejects poses the selection used, the selection is run once more
    without them: a glitch must never steer which terms are chosen. The second selection is
    kept unless it ends with a higher CV score per coordinate than the first, whose score
    still included the rejected poses: then the second greedy path went astray, and the
    first model (solved without those poses) is the better one.
    """
    inl = const.inliers
    note: dict[str, Any] = {"action": "screen", "by": "constant", "excluded": int((~inl).sum())}
    if f.opts.detect_outliers:
        try:
            ho = f.high_order(const)
        except IdentificationError:
            pass
        else:
            inl = ho.inliers
            note = {"action": "screen", "by": "high-order", "excluded": int((~inl).sum())}
    sol, log = _select(f, const, inl)
    if f.opts.detect_outliers and np.any(inl & ~sol.inliers):
        sol2, log2 = _select(f, const, sol.inliers)
        # without the flagged poses the CV score per coordinate can only drop for the same
        # path; when the second selection ends higher, its greedy path went astray (UR10 B,
        # split 9: 6.43 against 5.78, held-out 0.139 against 0.130 mm) and the first model,
        # already solved without those poses, is kept
        if _final_cv(log2) <= _final_cv(log):
            note = {"action": "screen", "by": "auto (second selection)",
                    "excluded": int((~sol.inliers).sum())}
            sol, log = sol2, log2
        else:
            note = {"action": "screen", "by": "high-order; auto's second selection scored "
                    "worse and was not kept", "excluded": int((~inl).sum()),
                    "second_selection_cv_rms_whitened": _final_cv(log2)}
    from robocal.identification._thermal import thermal_step  # it builds on this module

    sol, thermal = thermal_step(f, sol)  # one more candidate group, when temperatures vary
    # the log ends with the final selection (readers take its groups from the last entry)
    if log and log[-1].get("action") == "final":
        final = {**log[-1], "thermal": bool(thermal.get("selected"))}
        return sol, [note, *log[:-1], thermal, final]
    return sol, [note, *log, thermal]


def _final_cv(log: list[dict[str, Any]]) -> float:
    """The whitened CV RMS per coordinate a selection ended with (its log's last entry)."""
    return float(log[-1]["cv_rms_whitened"])


def _required_gain(groups: Sequence[Group], min_improvement: float, m_obs: int
                   ) -> dict[str, float]:
    """Relative CV gain each group needs to be added.

    ``min_improvement`` for most groups. The ripple harmonics are a large family of small
    groups (one per joint and order), and the best of many useless ones lowers the CV score
    by chance; each needs a gain its chance maximum is unlikely to reach: ``4 g ln N /
    m_obs`` for g columns, N ripple candidates and m_obs coordinates (twice the expected
    maximum of N chi-square gains, in units of the score per coordinate: the score is not
    yet at the noise floor when ripple is tried, and real ripple gains far more).
    """
    n_ripple = sum(1 for g in groups if ":ripple" in g.key)
    out = {}
    for g in groups:
        req = min_improvement
        if ":ripple" in g.key and n_ripple > 1:
            req = max(req, len(g.cols) * 4.0 * math.log(n_ripple) / max(m_obs, 1))
        out[g.key] = req
    return out


@dataclass
class _Superset:
    """The superset model linearised at the constant solution, and its CV machinery."""

    groups: list[Group]
    base_terms: list[Term]
    base_cols: IntArray
    cv: _CV
    scale: Array            # column scale of the per-fold normal matrices (P,)
    model: KinematicModel   # the superset model and the point it is linearised at
    x_c: Array
    ridge_sigma: float
    tie_sigma: float
    weak_sigma: float


def _superset(f: _Fitter, const: Solution, rows: IntArray) -> _Superset:
    """Candidate groups, their identifiable columns and the per-fold normal matrices."""
    opts = f.opts
    q = f.data.q[rows]
    groups = candidate_groups(f, q)
    base_terms = list(const.model.spec.terms)
    terms = list(base_terms)
    knots = [0] * f.robot.dof
    # the maps' columns last, one joint after another: the structured normal matrices
    # (_structured.normal_blocks) accumulate in that order and need no permutation
    for g in sorted(groups, key=lambda g: g.is_map):
        terms += g.terms
        if g.is_map:
            knots[g.joint] = g.n_knots
    spec = ErrorModelSpec(f.robot.dof, tuple(terms), tuple(knots), label="auto:superset")
    msup = KinematicModel(f.robot, spec, const.model.T_ref)
    x_c = const.model.transfer(const.x, msup)
    idx = {n: i for i, n in enumerate(msup.names)}
    for g in groups:
        g.cols = np.array([idx[t.name] for t in g.terms], dtype=np.intp)
    # the superset has ~1,600 columns: Problem.chunks bounds each chunk's Jacobian
    prob = Problem(msup, f.data.q, f.data.p, f.engine.W, chunk=f.opts.chunk)
    # identifiable unpenalised columns (tiers keep low orders first); maps and ripple stay
    # out of the rank analysis: hundreds of ripple columns would make the superset rank
    # deficient on a few hundred poses and push out the physical terms; a weak ridge keeps
    # each of them well posed in the CV instead
    map_cols = set(int(c) for g in groups if g.is_map or g.is_ripple for c in g.cols)
    unpen = np.array([i for i in range(msup.size) if i not in map_cols], dtype=np.intp)
    # one pass over the superset Jacobian: the fold normals and the rank analysis's factor
    # the ridge precision of map and ripple columns is part of their scale: a knot with
    # hardly any data would otherwise be scaled by its tiny data norm, and its (scaled)
    # smoothness prior reach 1e27, leaving the fold factors no correct digit
    prior_prec = np.zeros(msup.size)
    prior_prec[sorted(map_cols)] = 1.0 / math.radians(opts.map_ridge_deg) ** 2
    cv, s, factor = _fold_normals(f, prob, x_c, rows, unpen, prior_prec)
    _, keep, _ = analyse_jacobian(prob, x_c, rows, unpen, tol=opts.rank_tol, factor=factor)
    del factor
    kept = set(int(c) for c in unpen[keep])
    base_cols = np.array([i for i in range(ParameterLayout.OFFSET + len(base_terms)) if i in kept],
                         dtype=np.intp)
    for g in groups:
        if not (g.is_map or g.is_ripple):
            g.cols = np.array([c for c in g.cols if int(c) in kept], dtype=np.intp)
    groups = [g for g in groups if len(g.cols)]
    sup = _Superset(groups, base_terms, base_cols, cv, s, msup, x_c,
                    math.radians(opts.map_ridge_deg),
                    math.radians(opts.map_tie_deg), math.radians(opts.map_weak_deg))
    for g in groups:
        if g.is_map:
            sc = s[g.cols]
            D = second_difference(g.knots, g.n_knots)
            g.D2 = D.T @ D / np.outer(sc, sc)
            g.ridge = 1.0 / (sup.ridge_sigma**2 * sc**2)
            if g.weak:
                g.tie = weak_penalty(g.knots, g.n_knots, g.weak, sup.tie_sigma,
                                     sup.weak_sigma) / np.outer(sc, sc)
            # per unit relative smoothness: the mean data precision of the map's columns
            g.lam_unit = float(np.mean(sc**2 - prior_prec[g.cols]))
    return sup


def _fold_normals(f: _Fitter, prob: Problem, x_c: Array, rows: IntArray, unpen: IntArray,
                  prior_prec: Array) -> tuple[_CV, Array, tuple[Array, Array]]:
    """Per-fold normal matrices of the whitened superset Jacobian at ``x_c``, column-scaled
    (scaled so that the Schur complements compare columns of metres and radians), and from
    the same Jacobian chunks the normal matrix and an R factor of the ``unpen`` columns for
    :func:`analyse_jacobian` (unscaled). ``prior_prec`` (P,): prior precision added to
    each column's data precision in its scale."""
    opts = f.opts
    P = len(prior_prec)
    fold_of = cv_folds(f.data.q[rows], opts.cv_folds, opts.seed,
                       math.radians(opts.cv_group_tol_deg))
    # map columns are sparse (four knots per pose): their blocks are formed per pose
    G_f, b_f, c_f, R_un = normal_blocks(prob, x_c, rows, np.arange(P), fold_of, opts.cv_folds,
                                        qr_cols=unpen)
    G = G_f.sum(axis=0)
    A_un = G[np.ix_(unpen, unpen)]
    s = np.sqrt(np.clip(np.diagonal(G), 0.0, None) + prior_prec)
    s[s <= 1e-300] = 1.0
    S = np.outer(s, s)
    G_f /= S[None]
    G /= S
    del S
    b_f /= s[None]
    assert R_un is not None
    return _CV(G_f, b_f, c_f, G), s, (A_un, R_un)


class _Selection:
    """Greedy forward selection, smoothness refinement and backward pass over the groups.

    ``chosen`` maps a group key to its relative smoothness weight (maps) or None, in the
    order the groups were added (the order of their columns in :meth:`assemble`).
    """

    def __init__(self, sup: _Superset, min_improvement: float, map_lambdas: Sequence[float],
                 m_obs: int, ripple_screen: int = 8) -> None:
        self.sup = sup
        self.ripple_screen = ripple_screen
        self.cv = sup.cv
        self.by_key = {g.key: g for g in sup.groups}
        self.map_lambdas = tuple(map_lambdas)
        self.m_obs = m_obs
        self.required = _required_gain(sup.groups, min_improvement, m_obs)
        self.chosen: dict[str, float | None] = {}
        k0 = len(sup.base_cols)
        self.score = self.cv.score(sup.base_cols, np.zeros((k0, k0)))
        self.step = 0
        self.log: list[dict[str, Any]] = [{"step": 0, "action": "start", "group": "constant",
                                           "cv_rms_whitened": self.rms(self.score)}]

    def rms(self, score: float) -> float:
        """Whitened CV RMS per coordinate of a CV sum of squares."""
        return math.sqrt(score / self.m_obs)

    def map_pen(self, g: Group, lam_rel: float) -> Array:
        """Prior block of a map at relative smoothness ``lam_rel`` (scaled coordinates)."""
        assert g.D2 is not None and g.ridge is not None
        P = lam_rel * g.lam_unit * g.D2 + np.diag(g.ridge)
        return P if g.tie is None else P + g.tie

    def fixed_pen(self, g: Group) -> Array:
        """Prior block of a parametric group: none, or a weak ridge for a ripple harmonic."""
        if not g.is_ripple:
            return np.zeros((len(g.cols), len(g.cols)))
        return np.diag(1.0 / (self.sup.ridge_sigma**2 * self.sup.scale[g.cols] ** 2))

    def assemble(self, sel: dict[str, float | None]) -> tuple[IntArray, Array]:
        """Columns and block-diagonal prior of the model with groups ``sel``."""
        base = self.sup.base_cols
        cols = [base]
        blocks: list[Array] = [np.zeros((len(base), len(base)))]
        for key, lam in sel.items():
            g = self.by_key[key]
            cols.append(g.cols)
            blocks.append(self.map_pen(g, lam) if g.is_map and lam is not None
                          else self.fixed_pen(g))
        return np.concatenate(cols).astype(np.intp), block_diag(*blocks)

    def block_of(self, sel: dict[str, float | None], key: str) -> IntArray:
        """Positions of group ``key``'s columns in ``assemble(sel)``."""
        start = len(self.sup.base_cols)
        for k in sel:
            if k == key:
                return np.arange(start, start + len(self.by_key[k].cols))
            start += len(self.by_key[k].cols)
        raise KeyError(key)

    def round_options(self, phase: int, best_lam: dict[str, float]
                      ) -> tuple[list[tuple[IntArray, list[Array]]],
                                 list[tuple[str, Sequence[float | None]]], IntArray]:
        """Candidates of one forward round: (columns, priors) and (key, smoothness) each, and
        the columns of the ripple groups screened out (the fold factors keep them)."""
        options: list[tuple[IntArray, list[Array]]] = []
        labels: list[tuple[str, Sequence[float | None]]] = []
        ripple: list[str] = []
        for g in self.sup.groups:
            if g.phase > phase or g.key in self.chosen:
                continue
            if g.requires is not None and g.requires not in self.chosen:
                continue
            if g.is_ripple:
                ripple.append(g.key)
            elif g.is_map:
                # after a map's first evaluation only the neighbourhood of its best
                # smoothness so far is re-tried (the optimum moves little)
                lams = list(self.map_lambdas)
                if g.key in best_lam:
                    b = best_lam[g.key]
                    lams = [v for v in lams if b / 11 < v < b * 11]
                options.append((g.cols, [self.map_pen(g, lam) for lam in lams]))
                labels.append((g.key, lams))
            else:
                options.append((g.cols, [self.fixed_pen(g)]))
                labels.append((g.key, [None]))
        tried = ripple
        if len(ripple) > self.ripple_screen:
            # the ripple family (hundreds of groups) is ranked by its score-test gain at the
            # current model; only the best few are cross-validated
            gains = self.cv.train_gains(
                *self.assemble(self.chosen), np.stack([self.by_key[k].cols for k in ripple]),
                np.stack([self.fixed_pen(self.by_key[k]) for k in ripple]),
                np.unique(np.concatenate([c for c, _ in options]
                                         + [self.by_key[k].cols for k in ripple])))
            order = np.argsort(-gains, kind="stable")
            tried = [ripple[i] for i in sorted(order[:self.ripple_screen])]
        for key in tried:
            options.append((self.by_key[key].cols, [self.fixed_pen(self.by_key[key])]))
            labels.append((key, [None]))
        held = [self.by_key[k].cols for k in ripple if k not in tried]
        return options, labels, (np.concatenate(held) if held
                                 else np.zeros(0, dtype=np.intp))

    def forward(self) -> None:
        """Add groups while one lowers the CV score by its required gain, in three phases.

        Phase 1: physically modelled single terms (gravity torsion, pitch, strain-wave
        ripple); phase 2: harmonics; phase 3: maps and fine ripple, which then only describe
        what the parametric terms cannot. Earlier phases stay open in later ones.
        """
        best_lam: dict[str, float] = {}
        for phase in (1, 2, 3):
            while True:
                options, labels, held = self.round_options(phase, best_lam)
                if not options:
                    break
                all_scores = self.cv.scores_added(*self.assemble(self.chosen), options,
                                                  also_active=held)
                for (key_i, lams_i), row in zip(labels, all_scores, strict=True):
                    if lams_i[0] is not None:
                        lam_i = lams_i[int(np.argmin(row))]
                        assert lam_i is not None  # a map's options are all numbers
                        best_lam[key_i] = float(lam_i)
                # a candidate must lower the score by its own threshold (see _required_gain)
                flat = [(sc_, i, j) for i, row in enumerate(all_scores)
                        for j, sc_ in enumerate(row)
                        if sc_ < self.score * (1.0 - self.required[labels[i][0]])]
                if not flat:
                    break
                best_score, bi, bj = min(flat)
                self.step += 1
                key, lam = labels[bi][0], labels[bi][1][bj]
                self.chosen[key] = lam
                self.log.append({"step": self.step, "action": "add", "group": key,
                                 "lambda_rel": lam, "cv_rms_whitened": self.rms(best_score),
                                 "gain_percent": float(100.0 * (1.0 - best_score / self.score))})
                self.score = best_score

    def refine(self) -> None:
        """Try each chosen map's smoothness x1/3 and x3 (one Woodbury update per fold each)."""
        for key in [k for k in self.chosen if self.by_key[k].is_map]:
            lam0 = self.chosen[key]
            assert lam0 is not None
            g = self.by_key[key]
            facs = (1 / 3, 3.0)
            p = self.block_of(self.chosen, key)
            cur = self.map_pen(g, lam0)
            before = self.assemble(self.chosen)
            _, trials = self.cv.scores_varied(
                *before, (), [(p, self.map_pen(g, lam0 * fac) - cur) for fac in facs])
            i_best = int(np.argmin(trials))
            if trials[i_best] < self.score:
                self.chosen[key] = lam0 * facs[i_best]
                self.cv.adopt_variant(*before, *self.assemble(self.chosen),
                                      repen=(p, self.map_pen(g, lam0 * facs[i_best]) - cur))
                self.score = trials[i_best]
                self.log.append({"step": self.step, "action": "refine", "group": key,
                                 "lambda_rel": self.chosen[key],
                                 "cv_rms_whitened": self.rms(self.score)})

    def backward(self) -> None:
        """Drop groups, first in order of addition, whose removal does not worsen the score."""
        changed = True
        while changed and self.chosen:
            changed = False
            droppable = [k for k in self.chosen
                         if not any(self.by_key[o].requires == k for o in self.chosen)]
            before = self.assemble(self.chosen)
            dropped, _ = self.cv.scores_varied(
                *before, [self.block_of(self.chosen, k) for k in droppable], ())
            for key, sc_ in zip(droppable, dropped, strict=True):
                if sc_ <= self.score:
                    p = self.block_of(self.chosen, key)
                    del self.chosen[key]
                    self.cv.adopt_variant(*before, *self.assemble(self.chosen), drop=p)
                    self.score = sc_
                    self.log.append({"step": self.step, "action": "drop", "group": key,
                                     "cv_rms_whitened": self.rms(self.score)})
                    changed = True
                    break


def _select(f: _Fitter, const: Solution, inl: NDArray[np.bool_]
            ) -> tuple[Solution, list[dict[str, Any]]]:
    """Selection and final solve on the poses ``inl`` (outliers re-tested in the final solve)."""
    t0 = time.perf_counter()
    rows = np.flatnonzero(inl)
    sup = _superset(f, const, rows)
    sel = _Selection(sup, f.opts.auto_min_improvement, f.opts.map_lambdas, 3 * len(rows),
                     f.opts.auto_ripple_screen)
    sel.forward()
    sel.cv.keep_inverses_only()
    sel.refine()
    sel.backward()
    # final model, solved nonlinearly from the constant solution
    final_terms = list(sup.base_terms)
    final_knots = [0] * f.robot.dof
    priors: list[MapPrior] = []
    for key, lam in sel.chosen.items():
        g = sel.by_key[key]
        final_terms += g.terms
        if g.is_map:
            assert lam is not None
            final_knots[g.joint] = g.n_knots
            priors.append(MapPrior(g.joint, g.n_knots, g.knots, lam * g.lam_unit,
                                   sup.ridge_sigma, weak=g.weak, tie_sigma=sup.tie_sigma,
                                   weak_sigma=sup.weak_sigma))
    label = "auto:" + ",".join(sel.chosen) if sel.chosen else "auto:constant"
    spec_f = ErrorModelSpec(f.robot.dof, tuple(final_terms), tuple(final_knots), label=label)
    mf = KinematicModel(f.robot, spec_f, const.model.T_ref)
    x0 = _start(f, sup, sel, const, mf, rows)
    log = sel.log
    log.append({"action": "final", "groups": list(sel.chosen),
                "cv_rms_whitened": sel.rms(sel.score),
                "cv_evaluations": sel.cv.evaluations,
                "refactorisations": sel.cv.refactorisations,
                "selection_s": time.perf_counter() - t0})
    # the per-fold normal matrices (folds x P x P over ~1,600 candidate columns) are not
    # needed by the final solve: let them go before it allocates its own
    del sel, sup
    sol = f.engine.solve(mf, x0, priors=priors, inliers=inl, what="auto model")
    return sol, log


def _start(f: _Fitter, sup: _Superset, sel: _Selection, const: Solution, mf: KinematicModel,
           rows: IntArray) -> Array:
    """Start of the final solve: the selection's linearised solution (one Gauss-Newton step
    of the chosen columns from the constant solution, with the CV's priors), unless the
    constant solution fits the poses better."""
    x_const = const.model.transfer(const.x, mf)
    cols, pen = sel.assemble(sel.chosen)
    ix = np.ix_(cols, cols)
    try:
        d = _spd_or_lstsq(sup.cv.G[ix] + pen, sup.cv.b[cols])
    except np.linalg.LinAlgError:
        return x_const
    x_sup = sup.x_c.copy()
    x_sup[cols] += d / sup.scale[cols]
    x_lin = sup.model.transfer(x_sup, mf)
    prob = Problem(mf, f.data.q, f.data.p, f.engine.W, chunk=f.opts.chunk)
    if not np.isfinite(x_lin).all() or prob.cost(x_lin, rows) >= prob.cost(x_const, rows):
        return x_const
    return x_lin
