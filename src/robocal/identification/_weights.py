"""Measurement covariance of a laser tracker and the whitening matrices of the ML fit."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal.errors import ConfigError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class TrackerSigma:
    """1-sigma tracker noise, range dependent (metres; ``*_per_m``: metres per metre of range).

    The covariance of a point at range ``rho`` along unit direction ``u`` (from the tracker,
    which sits at ``position`` in the measurement frame) is
    ``sr**2 u u^T + st**2 (I - u u^T)`` with ``sr = radial_m + radial_per_m * rho`` and
    ``st = transverse_m + transverse_per_m * rho``. The defaults are typical of an
    interferometer/ADM tracker (radial 5 µm + 0.5 µm/m, angular 7.5 µm + 3 µm/m) and equal the
    virtual tracker's.
    """

    radial_m: float = 5e-6
    radial_per_m: float = 0.5e-6
    transverse_m: float = 7.5e-6
    transverse_per_m: float = 3e-6
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.radial_m <= 0 or self.transverse_m <= 0:
            raise ConfigError("tracker sigmas must be positive")
        if self.radial_per_m < 0 or self.transverse_per_m < 0:
            raise ConfigError("range-dependent tracker sigmas must not be negative")

    def sigmas(self, p: Array) -> tuple[Array, Array]:
        """Radial and transverse sigma (n,) m at points ``p`` (n, 3) m."""
        rho = np.linalg.norm(p - np.asarray(self.position), axis=1)
        return (self.radial_m + self.radial_per_m * rho,
                self.transverse_m + self.transverse_per_m * rho)

    def covariances(self, p: Array) -> Array:
        """Per-point covariance (n, 3, 3) m^2."""
        sr, st = self.sigmas(p)
        uu = _outer_dirs(p - np.asarray(self.position))
        return (sr**2)[:, None, None] * uu + (st**2)[:, None, None] * (np.eye(3) - uu)


def _outer_dirs(v: Array) -> Array:
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    # a point at the tracker itself has no direction: uu = 0 makes its covariance isotropic
    # (transverse sigma) instead of NaN
    u = v / np.where(norm > 0, norm, 1.0)
    return u[:, :, None] * u[:, None, :]


def whitening(p: Array, noise: TrackerSigma, point_sigma: Array | None = None) -> Array:
    """Whitening matrices ``W_j = Sigma_j^{-1/2}`` (n, 3, 3), 1/m.

    Parameters
    ----------
    p
        Measured points (n, 3) m, tracker frame.
    noise
        Tracker model, used where ``point_sigma`` is None.
    point_sigma
        Per-axis standard deviations (n, 3) m (CSV columns ``sx, sy, sz``); when given, the
        covariance is taken as diagonal, ``W_j = diag(1 / s_j)``.

    Notes
    -----
    For the tracker model ``Sigma^{-1/2} = u u^T / sr + (I - u u^T) / st`` exactly, so
    ``W^T W = Sigma^{-1}`` and whitened residuals have unit covariance.
    """
    p = np.atleast_2d(np.asarray(p, dtype=float))
    if point_sigma is not None:
        s = np.asarray(point_sigma, dtype=float)
        if s.shape != p.shape or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ConfigError("per-point sigmas must be positive and finite, shape (n, 3)")
        W = np.zeros((p.shape[0], 3, 3))
        W[:, [0, 1, 2], [0, 1, 2]] = 1.0 / s
        return W
    sr, st = noise.sigmas(p)
    uu = _outer_dirs(p - np.asarray(noise.position))
    return uu / sr[:, None, None] + (np.eye(3) - uu) / st[:, None, None]


#: 1-sigma orientation noise of a 6-DoF probe when the data give none (rad): Leica quotes
#: about 0.01 deg for the T-Mac's orientation.
DEFAULT_ORIENTATION_SIGMA_RAD = float(np.radians(0.01))


def euler_xyz_matrices(rot: Array) -> Array:
    """Rotations (n, 3, 3) ``Rx(rx) Ry(ry) Rz(rz)`` of intrinsic x-y-z angles (n, 3) rad."""
    a, b, c = (rot[:, k] for k in range(3))
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    R = np.empty((rot.shape[0], 3, 3))
    R[:, 0] = np.stack([cb * cc, -cb * sc, sb], axis=1)
    R[:, 1] = np.stack([sa * sb * cc + ca * sc, -sa * sb * sc + ca * cc, -sa * cb], axis=1)
    R[:, 2] = np.stack([-ca * sb * cc + sa * sc, ca * sb * sc + sa * cc, ca * cb], axis=1)
    return R


def orientation_whitening(rot: Array, rot_sigma: Array | None,
                          default_sigma: float = DEFAULT_ORIENTATION_SIGMA_RAD) -> Array:
    """Whitening matrices (n, 3, 3) 1/rad of orientation residuals (rotation vectors, tracker
    frame) for probe angles ``rot`` (n, 3) with per-angle sigmas ``rot_sigma`` (n, 3) rad.

    The angle covariance maps to the rotation vector through the Euler rate matrix
    ``E = [x, Rx y, Rx Ry z]``: ``Sigma = E diag(s^2) E^T``. Near gimbal lock E is singular;
    eigenvalues are floored at (a tenth of the smallest angle sigma)^2 so no direction gets
    an unbounded weight. Without sigmas: isotropic ``default_sigma``.
    """
    n = rot.shape[0]
    if rot_sigma is None:
        return np.broadcast_to(np.eye(3) / default_sigma, (n, 3, 3)).copy()
    a, b = rot[:, 0], rot[:, 1]
    E = np.zeros((n, 3, 3))
    E[:, 0, 0] = 1.0
    E[:, 1, 1], E[:, 2, 1] = np.cos(a), np.sin(a)
    E[:, 0, 2], E[:, 1, 2], E[:, 2, 2] = np.sin(b), -np.sin(a) * np.cos(b), np.cos(a) * np.cos(b)
    S = np.einsum("nik,nk,njk->nij", E, rot_sigma**2, E)
    lam, V = np.linalg.eigh(S)
    lam = np.maximum(lam, ((0.1 * rot_sigma.min(axis=1)) ** 2)[:, None])
    return np.einsum("nik,nk,njk->nij", V, 1.0 / np.sqrt(lam), V)
