"""Small transform helpers (numpy only): Euler angles, FANUC WPR, rotation vectors, rigid
registration."""

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


def rotvec_to_matrix(v: Array) -> Array:
    """Rotation matrix (3, 3) of a rotation vector ``v`` (3,) rad (axis times angle, as UR
    poses ``p[x, y, z, rx, ry, rz]`` give orientations)."""
    v = np.asarray(v, dtype=float)
    ang = float(np.linalg.norm(v))
    if ang < 1e-12:
        return np.eye(3)
    k = v / ang
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(ang) * K + (1.0 - np.cos(ang)) * (K @ K)


def matrix_to_rotvec(R: Array) -> Array:
    """Rotation vectors (..., 3) of rotation matrices R (..., 3, 3), angles in [0, pi]; at pi
    the axis is read from ``R + I`` (the skew part vanishes there)."""
    R = np.asarray(R, dtype=float)
    w = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    s = np.linalg.norm(w, axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    ang = np.arctan2(s, c)
    out = w * np.where(s > 1e-12, ang / np.maximum(s, 1e-300), 1.0)[..., None]
    near_pi = (s < 1e-6) & (c < 0.0)
    if np.any(near_pi):
        B = (R[near_pi] + np.eye(3)) / 2.0           # = k k^T at pi
        col = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        k = B[np.arange(len(B)), :, col]
        k /= np.linalg.norm(k, axis=-1, keepdims=True)
        out[near_pi] = k * ang[near_pi][..., None]
    return out


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
