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
