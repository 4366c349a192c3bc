"""Ordering poses for short campaigns, and via-points that cap the joint step.

The cost of a move is its duration under a synchronous joint move at constant speed,
``t(a, b) = max_i |q_b,i - q_a,i| / v_i`` (the slowest joint decides), which is what a
joint-interpolated move of an industrial controller takes up to acceleration phases. The tour
is an open path from a start configuration: nearest neighbour, then 2-opt until no reversal
shortens it.

A maximum joint step is enforced by **inserting via-points** on the straight joint-space line
(evenly spaced, never measured), not by reordering: 2-opt already removes long moves where a
shorter order exists, and what is left (for example crossing a wrist's full range) cannot be
shortened by any order.
"""

from __future__ import annotations

import heapq
import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
Index = NDArray[np.intp]


def move_times(qa: Array, qb: Array, speed: Array) -> Array:
    """Duration of joint moves qa -> qb (broadcast (..., dof)) at joint speeds ``speed`` (dof,).

    Returns
    -------
    ndarray, shape (...)
        Seconds (when ``speed`` is in rad/s and ``q`` in rad).
    """
    return np.max(np.abs(np.asarray(qb) - np.asarray(qa)) / speed, axis=-1)


def pairwise_move_times(q: Array, speed: Array) -> Array:
    """Move times (n, n) between every two poses of ``q`` (n, dof): the same figures as
    ``move_times(q[:, None], q[None], speed)`` without its (n, n, dof) temporary."""
    D = np.zeros((len(q), len(q)))
    for j in range(q.shape[1]):
        np.maximum(D, np.abs(q[None, :, j] - q[:, None, j]) / speed[j], out=D)
    return D


def _path_cost(D: Array, start: Array, order: Index) -> float:
    return float(start[order[0]] + D[order[:-1], order[1:]].sum())


def order_poses(q: Array, speed: Array, *, start: Array | None = None,
                cost: Array | None = None, max_passes: int = 50) -> Index:
    """Order poses ``q`` (n, dof) rad to minimise the total move time from ``start``.

    Parameters
    ----------
    q : ndarray, shape (n, dof)
        Poses to visit (each once).
    speed : ndarray, shape (dof,)
        Joint speeds used by the time metric, rad/s.
    start : ndarray, shape (dof,), optional
        Where the robot starts (default: the first pose's configuration).
    cost : ndarray, shape (n, n), optional
        A symmetric move-cost matrix to use instead of the time metric (for penalties).
    max_passes
        Cap on 2-opt improvement passes.

    Returns
    -------
    ndarray of int, shape (n,)
        Visiting order (indices into ``q``).
    """
    q = np.atleast_2d(q)
    n = len(q)
    if n <= 1:
        return np.arange(n, dtype=np.intp)
    D = pairwise_move_times(q, speed) if cost is None else cost
    s = move_times(start[None, :] if start is not None else q[:1], q, speed)
    # nearest neighbour from the start
    order = np.empty(n, dtype=np.intp)
    free = np.ones(n, dtype=bool)
    cur = int(np.argmin(s))
    for k in range(n):
        order[k] = cur
        free[cur] = False
        if k + 1 < n:
            d = np.where(free, D[cur], np.inf)
            cur = int(np.argmin(d))
    return two_opt(order, D, s, max_passes=max_passes)


def two_opt(order: Index, D: Array, start_cost: Array, *, max_passes: int = 50) -> Index:
    """Improve an open path by segment reversals (2-opt), vectorised over the second cut.

    ``D`` (n, n) is the symmetric move cost, ``start_cost`` (n,) the cost from the start
    configuration to each pose. Reversing ``order[i:j+1]`` replaces edges (i-1, i) and
    (j, j+1) by (i-1, j) and (i, j+1); the edge into position 0 comes from the start.
    """
    order = np.array(order, dtype=np.intp)
    n = len(order)
    for _ in range(max_passes):
        improved = False
        for i in range(n - 1):
            j = np.arange(i + 1, n)
            a = order[i]
            prev_in = start_cost[a] if i == 0 else D[order[i - 1], a]
            new_in = start_cost[order[j]] if i == 0 else D[order[i - 1], order[j]]
            nxt = np.minimum(j + 1, n - 1)
            old_out = np.where(j + 1 < n, D[order[j], order[nxt]], 0.0)
            new_out = np.where(j + 1 < n, D[a, order[nxt]], 0.0)
            delta = new_in + new_out - prev_in - old_out
            k = int(np.argmin(delta))
            if delta[k] < -1e-12:
                jj = int(j[k])
                order[i:jj + 1] = order[i:jj + 1][::-1].copy()
                improved = True
        if not improved:
            break
    return order


def insert_via_points(q: Array, max_step: float, *, start: Array | None = None
                      ) -> tuple[Array, NDArray[np.bool_]]:
    """Insert evenly spaced via-points so that no joint moves more than ``max_step`` rad.

    Parameters
    ----------
    q : ndarray, shape (n, dof)
        Ordered poses.
    max_step
        Largest allowed change of any joint between consecutive targets, rad.
    start : ndarray, shape (dof,), optional
        Start configuration; the move into the first pose is capped too.

    Returns
    -------
    q_out : ndarray, shape (m, dof)
        Poses with via-points.
    is_via : ndarray of bool, shape (m,)
        True for inserted via-points.
    """
    q = np.atleast_2d(q)
    rows: list[Array] = []
    via: list[bool] = []
    prev = start
    for qi in q:
        if prev is not None:
            k = math.ceil(float(np.max(np.abs(qi - prev))) / max_step - 1e-9)
            for m in range(1, k):
                rows.append(prev + (qi - prev) * (m / k))
                via.append(True)
        rows.append(qi)
        via.append(False)
        prev = qi
    return np.array(rows).reshape(-1, q.shape[1]), np.array(via, dtype=bool)


def shortest_path(n: int, i: NDArray[np.intp], j: NDArray[np.intp], w: Array, source: int,
                  goal: int) -> list[int] | None:
    """Nodes of the shortest path from ``source`` to ``goal`` (both included) in the
    undirected graph of ``n`` nodes and edges i[k]--j[k] of positive weight w[k], or None
    when no path joins them (Dijkstra; the roadmaps have a few thousand edges)."""
    adj: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    for u, v, c in zip(i.tolist(), j.tolist(), w.tolist(), strict=True):
        adj[u].append((v, c))
        adj[v].append((u, c))
    dist = [math.inf] * n
    pred = [-1] * n
    dist[source] = 0.0
    heap = [(0.0, source)]
    while heap:
        d, u = heapq.heappop(heap)
        if u == goal:
            break
        if d > dist[u]:
            continue
        for v, c in adj[u]:
            if d + c < dist[v]:
                dist[v] = d + c
                pred[v] = u
                heapq.heappush(heap, (d + c, v))
    if not math.isfinite(dist[goal]):
        return None
    path = [goal]
    while path[-1] != source:
        path.append(pred[path[-1]])
    return path[::-1]
