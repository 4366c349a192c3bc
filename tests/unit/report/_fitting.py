"""A small Gauss-Newton fitter for report tests (independent of robocal.identification).

Its fits are given to the report as :class:`ModelEntry` objects, the report's own typed input
for results that do not come from identification.

Unidentifiable columns are found once, by a pivoted Cholesky of the normal matrix of the
column-normalised Jacobian at the start point, and held fixed (zero covariance); the rest is
solved by Gauss-Newton; covariance is (J^T J)^-1 scaled by the residual variance.
"""

from __future__ import annotations

import numpy as np

from robocal._core.measurements import MeasurementSet
from robocal.kinematics import CalibratedModel, ErrorModelSpec, KinematicModel, RobotDescription
from robocal.report import ModelEntry


def _pivoted_columns(M: np.ndarray, tol: float = 1e-10) -> np.ndarray:
    """Columns a pivoted Cholesky of the normal matrix ``M`` (unit diagonal) keeps, sorted."""
    n = M.shape[0]
    d = np.diag(M).astype(float).copy()
    L = np.zeros((n, n))
    piv: list[int] = []
    for k in range(n):
        j = int(np.argmax(d))
        if d[j] <= tol:
            break
        piv.append(j)
        col = (M[:, j] - L[:, :k] @ L[j, :k]) / np.sqrt(d[j])
        L[:, k] = col
        d -= col**2
        d[piv] = -np.inf
    return np.array(sorted(piv), dtype=np.intp)


def gn_fit(robot: RobotDescription, spec: ErrorModelSpec, T_ref: np.ndarray,
           data: MeasurementSet, *, x0: CalibratedModel | None = None, kind: str = "custom",
           iterations: int = 8, exclude: tuple[str, ...] = ()) -> ModelEntry:
    """Fit ``spec`` to ``data`` (poses in ``exclude`` left out)."""
    if exclude:
        keep = np.array([p not in set(exclude) for p in data.pose_id])
        data = data.subset(keep)
    m = KinematicModel(robot, spec, T_ref)
    x = m.nominal_params() if x0 is None else x0.model.transfer(x0.params, m)
    _, J = m.jacobian(data.q, x)
    A = J.reshape(-1, m.size)
    sc = np.linalg.norm(A, axis=0)
    sc[sc == 0] = 1.0
    free = _pivoted_columns((A / sc).T @ (A / sc))
    rk = free.size
    for _ in range(iterations):
        p, J = m.jacobian(data.q, x)
        Af = J.reshape(-1, m.size)[:, free] / sc[free]
        # normal equations: LAPACK least squares is very slow with threaded OpenBLAS on a
        # busy machine, and these problems are well conditioned once redundancy is removed
        N = Af.T @ Af
        dx = np.linalg.solve(N, Af.T @ (data.p - p).ravel())
        x = x.copy()
        x[free] += dx / sc[free]
        if np.max(np.abs(dx / sc[free])) < 1e-13:
            break
    res = np.linalg.norm(data.p - m.positions(data.q, x), axis=1)
    s2 = float(np.sum(res**2)) / max(1, 3 * len(data) - rk)
    cov = np.zeros((m.size, m.size))
    cov[np.ix_(free, free)] = np.linalg.inv(N) / np.outer(sc[free], sc[free]) * s2
    cover = np.stack([data.q.min(axis=0), data.q.max(axis=0)], axis=1)
    cm = CalibratedModel(m, x, cov, coverage=cover, kind=kind,
                         data={"calibration_sha256": data.digest()[:16]})
    removed = tuple(m.names[i] for i in sorted(set(range(m.size)) - set(free)))
    train = {"rms_m": float(np.sqrt(np.mean(res**2))), "mean_m": float(res.mean()),
             "max_m": float(res.max()), "n": len(res)}
    return ModelEntry(kind, cm, outliers=exclude, removed=removed, status="converged",
                      stored={"train": train},
                      summary={"status": "converged", "n_removed": len(removed)})
