"""Small transform helpers (numpy only): Euler angles, FANUC WPR, rigid registration."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def _rx(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def euler_xyz_to_matrix(ex: float, ey: float, ez: float) -> Array:
    """Rotation ``Rx(ex) Ry(ey) Rz(ez)`` (intrinsic x-y-z, as in the error transform)."""
    return _rx(ex) @ _ry(ey) @ _rz(ez)


def matrix_to_euler_xyz(R: Array) -> tuple[float, float, float]:
    """Inverse of :func:`euler_xyz_to_matrix` (ey in [-pi/2, pi/2])."""
    ey = float(np.arcsin(np.clip(R[0, 2], -1.0, 1.0)))
    ex = float(np.arctan2(-R[1, 2], R[2, 2]))
    ez = float(np.arctan2(-R[0, 1], R[0, 0]))
    return ex, ey, ez


def wpr_to_matrix(w: float, p: float, r: float) -> Array:
    """FANUC W, P, R (rad): fixed-axis rotations about x, y, z, ``R = Rz(r) Ry(p) Rx(w)``."""
    return _rz(r) @ _ry(p) @ _rx(w)


def matrix_to_wpr(R: Array) -> tuple[float, float, float]:
    """Inverse of :func:`wpr_to_matrix` (p in [-pi/2, pi/2])."""
    p = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    w = float(np.arctan2(R[2, 1], R[2, 2]))
    r = float(np.arctan2(R[1, 0], R[0, 0]))
    return w, p, r


def rigid_fit(src: Array, dst: Array, weights: Array | None = None) -> Array:
    """Least-squares rigid transform T (4, 4) with ``dst ~ T · src`` (Kabsch), points (n, 3)."""
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    cs = w @ src
    cd = w @ dst
    return kabsch((src - cs).T @ ((dst - cd) * w[:, None]), cs, cd)


def kabsch(H: Array, cs: Array, cd: Array) -> Array:
    """Rigid transform T (4, 4) taking the centroid ``cs`` (3,) to ``cd`` (3,) whose rotation
    best aligns the points of the cross-covariance ``H`` (3, 3) = Σ w (s - cs)(d - cd)ᵀ (any
    positive scale)."""
    U, _, Vt = np.linalg.svd(H)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cd - R @ cs
    return T
