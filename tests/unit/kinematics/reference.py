"""An independent, deliberately naive 4x4-matrix implementation used to check the fast code."""

from __future__ import annotations

import numpy as np


def rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def tr(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def chain(robot, q, *, pre=None, post=None, angle=None, base=None, tool=(0, 0, 0)):
    """Reference FK for one pose with optional per-joint perturbations.

    pre[i](q_i) -> 4x4 pre-multiplied before Rz (rotating-centre offset), post[i](q_i) -> 4x4
    after the DH transform (link/assembly), angle[i](theta, q_i) -> perturbed chain angle.
    """
    T = np.eye(4) if base is None else base.copy()
    theta = robot.coupling_matrix @ q + np.array([j.theta_offset for j in robot.joints])
    for i, j in enumerate(robot.joints):
        th = theta[i] if angle is None or angle[i] is None else angle[i](theta[i], q[i])
        A = rz(th) @ tr(z=j.d) @ tr(x=j.a) @ rx(j.alpha)
        if pre is not None and pre[i] is not None:
            A = pre[i](q[i]) @ A
        if post is not None and post[i] is not None:
            A = A @ post[i](q[i])
        T = T @ A
    return (T @ np.array([*tool, 1.0]))[:3], T
