"""Normal matrices that use the sparsity of joint-angle map columns.

A map knot's Jacobian column is the sensitivity to its joint's ``ez`` component times the
knot's cubic B-spline weight, and a pose has at most four non-zero weights per map. So the
map blocks of ``J^T J`` are sums of a few products per pose (scatter-added with
``np.bincount``) instead of dense products over every map column: for the
``auto`` superset (~1,100 of ~1,600 columns are map knots) that is most of the cost of the
per-fold normal matrices (ADR 0052).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from robocal._core.arrays import Array, IntArray
from robocal.kinematics import ParameterLayout, spline_weights

if TYPE_CHECKING:  # _solver uses this module for models with maps
    from robocal.identification._solver import Problem

_OFF = ParameterLayout.OFFSET


@dataclass(frozen=True)
class _Map:
    """The columns of one joint's map among the requested columns."""

    joint: int
    comp: int            # error component column (joint * 6 + component)
    n_knots: int         # knots of the periodic spline over one revolution
    local: IntArray      # positions among the requested columns (kj,)
    col_of_knot: IntArray  # knot -> position within ``local`` (n_knots,), -1: absent


def split_columns(prob: Problem, cols: IntArray) -> tuple[IntArray, list[_Map]]:
    """Positions (into ``cols``) of the dense columns, and the map blocks."""
    spec = prob.model.spec
    comp = prob.model.term_components
    is_map = _map_columns(prob, cols)
    by_joint: dict[int, list[tuple[int, int]]] = {}
    for i in np.flatnonzero(is_map):
        t = spec.terms[int(cols[i]) - _OFF]
        by_joint.setdefault(t.joint, []).append((int(i), t.index))
    dense = np.flatnonzero(~is_map)
    maps = []
    for j, items in sorted(by_joint.items()):
        K = spec.map_knots[j]
        col_of_knot = np.full(K, -1, dtype=np.intp)
        col_of_knot[[k for _, k in items]] = np.arange(len(items))
        t0 = int(cols[items[0][0]]) - _OFF
        maps.append(_Map(j, int(comp[t0]), K, np.array([i for i, _ in items], dtype=np.intp),
                         col_of_knot))
    return dense.astype(np.intp), maps


def _map_columns(prob: Problem, cols: IntArray) -> NDArray[np.bool_]:
    """Per column of ``cols``: is it a map knot."""
    c = np.asarray(cols, dtype=np.intp)
    out = np.zeros(len(c), dtype=bool)
    term = c >= _OFF
    out[term] = prob.model.term_is_map[c[term] - _OFF]
    return out


def has_maps(prob: Problem, cols: IntArray, minimum: int = 16) -> bool:
    """Whether ``cols`` include at least ``minimum`` map columns (worth the sparse path)."""
    return int(np.count_nonzero(_map_columns(prob, cols))) >= minimum


class _Accumulator:
    """Sums of the grouped normal matrices in the order [dense, map by map]."""

    def __init__(self, prob: Problem, cols: IntArray, n_groups: int) -> None:
        self.prob = prob
        k = len(cols)
        self.dense, self.maps = split_columns(prob, cols)
        self.nd = nd = len(self.dense)
        self.n_groups = n_groups
        self.G = np.zeros((n_groups, k, k))
        self.b = np.zeros((n_groups, k))
        self.c = np.zeros(n_groups)
        self.comp = prob.model.term_components
        is_head = cols[self.dense] < _OFF
        if np.any(np.diff(is_head.astype(np.int8)) > 0):
            raise ValueError("base and tool columns must come before the error terms")
        self.head_cols = cols[self.dense][is_head]
        self.terms = cols[self.dense][~is_head] - _OFF
        self.spans: list[slice] = []
        a = nd
        for mp in self.maps:
            self.spans.append(slice(a, a + len(mp.local)))
            a += len(mp.local)
        self.order = np.concatenate([self.dense] + [mp.local for mp in self.maps]).astype(np.intp)

    def dense_jacobian(self, Hw: Array, Sw: Array, B: Array) -> Array:
        """The dense columns' whitened Jacobian (n, m, nd) of a chunk."""
        n, m = Hw.shape[:2]
        nh = len(self.head_cols)
        Jd = np.empty((n, m, self.nd))
        Jd[:, :, :nh] = np.take(Hw, self.head_cols, axis=2)
        np.multiply(np.take(Sw, self.comp[self.terms], axis=2), B[:, None, :],
                    out=Jd[:, :, nh:])
        return Jd

    def map_bases(self, q: Array) -> list[tuple[Array, IntArray, Array]]:
        """Per map: its basis columns (n, kj), built from each pose's four knot weights,
        and those positions (n, 4) and weights (n, 4) (a knot not among the columns: weight
        0 at position 0)."""
        out = []
        n = q.shape[0]
        for mp in self.maps:
            idx, w, _ = spline_weights(q[:, mp.joint], mp.n_knots)
            pos = mp.col_of_knot[idx]
            ok = pos >= 0
            Bm = np.zeros((n, len(mp.local)))
            Bm[np.nonzero(ok)[0], pos[ok]] = w[ok]   # a pose's four knots are distinct
            out.append((Bm, np.where(ok, pos, 0), np.where(ok, w, 0.0)))
        return out

    def add(self, q: Array, g: IntArray, Jd: Array, Sw: Array, rw: Array) -> None:
        """Add a chunk: joint values (n, dof), groups (n,), dense Jacobian (n, m, nd), the
        component sensitivities (n, m, 6 dof) and the residual (n, m)."""
        nd, G, b = self.nd, self.G, self.b
        V = [Sw[:, :, mp.comp] for mp in self.maps]                   # (n, m) each
        mb = self.map_bases(q)
        Bm = [B_ for B_, _, _ in mb]                                  # (n, kj) each
        Ud = [np.einsum("nmd,nm->nd", Jd, v) for v in V]
        tv = [np.einsum("nm,nm->n", v, rw) for v in V]
        for f in range(self.n_groups):
            # one group: slices, not copies
            sel: slice | IntArray = np.flatnonzero(g == f) if self.n_groups > 1 else slice(None)
            if isinstance(sel, np.ndarray) and len(sel) == 0:
                continue
            Jf = Jd[sel].reshape(-1, nd)
            rf = rw[sel].ravel()
            G[f, :nd, :nd] += Jf.T @ Jf
            b[f, :nd] += Jf.T @ rf
            self.c[f] += float(rf @ rf)
            for a, sa in enumerate(self.spans):
                Ba = Bm[a][sel]
                G[f, sa, :nd] += Ba.T @ Ud[a][sel]
                b[f, sa] += Ba.T @ tv[a][sel]
        # map x map: 16 products per pose and pair of maps, scatter-added per group
        PW = [(p, w) for _, p, w in mb]
        for a, sa in enumerate(self.spans):
            pa, wa = PW[a]
            ka = sa.stop - sa.start
            for a2 in range(a, len(self.maps)):
                pb, wb = PW[a2]
                kb = self.spans[a2].stop - self.spans[a2].start
                cv = np.einsum("nm,nm->n", V[a], V[a2])
                vals = cv[:, None, None] * wa[:, :, None] * wb[:, None, :]
                key = (g[:, None, None] * ka + pa[:, :, None]) * kb + pb[:, None, :]
                G[:, sa, self.spans[a2]] += np.bincount(
                    key.ravel(), weights=vals.ravel(),
                    minlength=self.n_groups * ka * kb).reshape(self.n_groups, ka, kb)

    def result(self) -> tuple[Array, Array, Array]:
        """G, b, c in the order of the columns asked for."""
        G, nd = self.G, self.nd
        for a, sa in enumerate(self.spans):          # the blocks above the diagonal
            G[:, :nd, sa] = G[:, sa, :nd].transpose(0, 2, 1)
            for sb in self.spans[a + 1:]:
                G[:, sb, sa] = G[:, sa, sb].transpose(0, 2, 1)
        k = len(self.order)
        if np.array_equal(self.order, np.arange(k)):
            return G, self.b, self.c
        inv = np.empty(k, dtype=np.intp)
        inv[self.order] = np.arange(k)
        return np.take(np.take(G, inv, axis=1), inv, axis=2), self.b[:, inv], self.c


def normal_blocks(prob: Problem, x: Array, rows: IntArray, cols: IntArray,
                  group_of: IntArray | None = None, n_groups: int = 1,
                  qr_cols: IntArray | None = None
                  ) -> tuple[Array, Array, Array, Array | None]:
    """``J^T J`` (g, k, k), ``J^T r`` (g, k) and ``r^T r`` (g,) of the whitened problem at
    ``x`` over the poses ``rows``, summed per group of poses (``group_of`` (len(rows),) in
    ``0..n_groups-1``; default one group), for the columns ``cols`` (k,; base and tool
    columns before the error terms).

    A map column is its joint's ``ez`` sensitivity (m rows per pose) times a basis weight
    per pose, so its products with other columns reduce over a pose's rows first: with
    ``Ud = sum_rows J_dense * v`` (n, nd), the dense x map block is ``B_map^T Ud``, and the
    map x map block sums 16 weight products per pose. The dense Jacobian is formed for the
    dense columns only. Blocks are accumulated in the order [dense, map by map] and put
    into the order of ``cols`` once at the end (free when ``cols`` already has that order,
    as the ``auto`` superset does).

    ``qr_cols``: positions (into ``cols``, dense columns only) whose R factor of the unscaled
    Jacobian is also returned (None: not computed).
    """
    acc = _Accumulator(prob, cols, n_groups)
    grp = np.zeros(len(rows), dtype=np.intp) if group_of is None else np.asarray(group_of)
    R: Array | None = None
    qr_d = None
    if qr_cols is not None:
        where = {int(p): i for i, p in enumerate(acc.dense)}
        qr_d = np.array([where[int(p)] for p in qr_cols], dtype=np.intp)
    for ch in prob.chunks(np.arange(len(rows))):
        if len(ch) == 0:
            continue
        Hw, Sw, B, rw = prob.whitened_factors(x, rows[ch], acc.terms)
        Jd = acc.dense_jacobian(Hw, Sw, B)
        if qr_d is not None:
            Jq = Jd.reshape(-1, acc.nd)[:, qr_d]
            R = np.linalg.qr(Jq if R is None else np.vstack([R, Jq]), mode="r")  # type: ignore[assignment]
        acc.add(prob.q[rows[ch]], grp[ch], Jd, Sw, rw)
    return (*acc.result(), R)


def hat_blocks(prob: Problem, x: Array, rows: IntArray, cols: IntArray, Ninv: Array
               ) -> tuple[Array, Array]:
    """Position blocks ``J_j Ninv J_j^T`` (n, 3, 3) of the hat matrix and the whitened
    position residuals (n, 3) of the poses ``rows``, for the columns ``cols`` (k,) and the
    inverse normal matrix ``Ninv`` (k, k) over them.

    With a pose's map columns ``v_a b_a^T`` (sensitivity times its four knot weights) the
    block is ``Jd Ndd Jd^T + sum_a (w_a v_a^T + v_a w_a^T) + sum_ab s_ab v_a v_b^T`` with
    ``w_a = Jd N_da b_a`` and ``s_ab = b_a^T N_ab b_b`` (16 entries of ``Ninv`` per pose and
    pair of maps): no product over every column per pose.
    """
    acc = _Accumulator(prob, cols, 1)
    d = acc.dense
    N_dd = Ninv[np.ix_(d, d)]
    N_md = [Ninv[np.ix_(mp.local, d)] for mp in acc.maps]
    H = np.empty((len(rows), 3, 3))
    r_out = np.empty((len(rows), 3))
    a0 = 0
    for ch in prob.chunks(np.arange(len(rows))):
        if len(ch) == 0:
            continue
        Hw, Sw, B, rw = prob.whitened_factors(x, rows[ch], acc.terms)
        Jd = acc.dense_jacobian(Hw[:, :3], Sw[:, :3], B)              # position rows only
        V = [Sw[:, :3, mp.comp] for mp in acc.maps]
        h = np.einsum("nid,de,nje->nij", Jd, N_dd, Jd, optimize=True)
        mb = acc.map_bases(prob.q[rows[ch]])
        PW = [(p, w) for _, p, w in mb]
        for a in range(len(acc.maps)):
            Z = mb[a][0] @ N_md[a]                                      # (n, nd)
            wa = np.einsum("nid,nd->ni", Jd, Z)
            h += wa[:, :, None] * V[a][:, None, :] + V[a][:, :, None] * wa[:, None, :]
        for a, mp in enumerate(acc.maps):
            pa, wa_ = PW[a]
            for b_ in range(a, len(acc.maps)):
                pb, wb = PW[b_]
                Nab = Ninv[np.ix_(mp.local, acc.maps[b_].local)]
                s = np.einsum("np,nq,npq->n", wa_, wb, Nab[pa[:, :, None], pb[:, None, :]])
                outer = V[a][:, :, None] * V[b_][:, None, :]
                h += s[:, None, None] * (outer if b_ == a else outer + outer.transpose(0, 2, 1))
        H[a0:a0 + len(ch)] = h
        r_out[a0:a0 + len(ch)] = rw[:, :3]
        a0 += len(ch)
    return H, r_out
