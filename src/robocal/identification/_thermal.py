"""The linear thermal term: each link's length change per °C of its joint's temperature.

When the measurements carry joint temperatures that vary (some joint's standard deviation at
least ``MIN_VARIATION_C``), ``auto`` considers one more candidate group after its selection:
per link, the length change ``c_j * (T_j - T_ref_j)`` along the link's dominant DH length
(``a_j`` through the ``dx`` error component, else ``d_j`` through ``dz``), ``T_ref`` the
mean temperatures of the poses used. Its columns are the chosen model's columns of those
length components, each pose's row scaled by its temperature difference; the group is
cross-validated like the others (the same folds, on the chosen model linearised at its
solution) and taken only when it lowers the CV score by ``auto_min_improvement``. Without
temperature variation it is not even a candidate. Taken, it is solved jointly with the
model's free parameters (one Gauss-Newton step: the coefficients are micrometres per °C);
the model predicts at ``T_ref`` and :func:`thermal_shift` adds the term at other
temperatures; accuracy figures apply it where the poses' temperatures are known (ADR 0042).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from robocal._core.thermal import thermal_components
from robocal.errors import ConfigError
from robocal.identification._auto import _CV, cv_folds
from robocal.identification._engine import Solution
from robocal.identification._fitter import Fitter
from robocal.kinematics import CalibratedModel, KinematicModel, Term

__all__ = ["MIN_VARIATION_C", "at_temperatures", "thermal_shift", "thermal_step", "thermal_term"]

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: A joint's temperature must vary by at least this standard deviation (°C) for the thermal
#: term to be a candidate.
MIN_VARIATION_C = 0.5


def _with_length_terms(model: KinematicModel, x: Array) -> tuple[KinematicModel, Array,
                                                                  IntArray]:
    """``model`` with a constant length term on every link, ``x`` on it, and the indices
    of those terms."""
    terms = [Term(j, c, "const") for j, c in enumerate(thermal_components(model.robot.joints))]
    m2 = model.with_spec(model.spec.with_terms(terms))
    names = {n: i for i, n in enumerate(m2.names)}
    return m2, model.transfer(x, m2), np.array([names[t.name] for t in terms], dtype=np.intp)


def thermal_term(model: CalibratedModel) -> dict[str, Any] | None:
    """The model's thermal term as MODEL.json's ``fit.thermal`` holds it, or None when the
    model has none (or it was considered and not taken)."""
    term = model.fit.get("thermal") if isinstance(model.fit, dict) else None
    return term if term and term.get("selected") else None


def thermal_shift(model: CalibratedModel, q: Array, temps_c: Array) -> Array:
    """What the model's thermal term adds to its prediction (n, 3) m at joints ``q`` (n, dof)
    rad and joint temperatures ``temps_c`` (n, dof) °C; zeros without a thermal term."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    term = thermal_term(model)
    if term is None:
        return np.zeros((q.shape[0], 3))
    m2, x2, idx = _with_length_terms(model.model, model.params)
    _, J = m2.jacobian(q, x2)
    coef = np.asarray(term["coef_mm_per_c"], dtype=float) * 1e-3
    dT = np.atleast_2d(np.asarray(temps_c, dtype=float)) - np.asarray(term["t_ref_c"])
    return np.einsum("nij,nj->ni", J[:, :, idx], dT * coef)


def at_temperatures(model: CalibratedModel, temps_c: Any) -> CalibratedModel:
    """The model as it predicts at joint temperatures ``temps_c`` (dof,) °C: its thermal term
    folded into constant link lengths (``model`` itself when it has no thermal term).

    The term is ``c_j (T_j - T_ref,j)`` along each link's length component, and a position
    is affine in those constants, so the result predicts exactly ``model.predict(q) +
    thermal_shift(model, q, temps_c)`` (to rounding), with plain kinematics: compensation,
    tables and IK need nothing thermal. ``fit.thermal`` becomes ``fit.thermal_applied``
    (the temperatures and the term), so the term is never applied twice.

    Raises
    ------
    ConfigError
        ``temps_c`` is not one finite temperature per joint, or the term is malformed.
    """
    term = thermal_term(model)
    if term is None:
        return model
    dof = model.model.robot.dof
    try:
        t = np.asarray(temps_c, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError(f"joint temperatures must be {dof} numbers (°C)") from None
    if t.shape != (dof,) or not np.all(np.isfinite(t)):
        raise ConfigError(f"joint temperatures must be {dof} finite numbers (°C), got "
                          f"{t.size}")
    try:
        coef = np.asarray(term["coef_mm_per_c"], dtype=float).reshape(-1) * 1e-3
        t_ref = np.asarray(term["t_ref_c"], dtype=float).reshape(-1)
    except (KeyError, TypeError, ValueError):
        coef = t_ref = np.zeros(0)
    if coef.shape != (dof,) or t_ref.shape != (dof,) or not (
            np.all(np.isfinite(coef)) and np.all(np.isfinite(t_ref))):
        raise ConfigError(f"the model's thermal term is malformed: fit.thermal needs "
                          f"{dof} finite coef_mm_per_c and t_ref_c")
    m2, x2, idx = _with_length_terms(model.model, model.params)
    x2[idx] += coef * (t - t_ref)
    cov = None
    if model.covariance is not None:
        # the length terms the model lacked were held at zero: no variance
        pos = {n: i for i, n in enumerate(model.model.names)}
        src = np.array([pos.get(n, -1) for n in m2.names])
        cov = np.zeros((m2.size, m2.size))
        have = np.flatnonzero(src >= 0)
        cov[np.ix_(have, have)] = model.covariance[np.ix_(src[have], src[have])]
    fit_ = {k: v for k, v in model.fit.items() if k != "thermal"}
    fit_["thermal_applied"] = {"temps_c": [float(v) for v in t], "term": term}
    return CalibratedModel(model=m2, params=x2, covariance=cov, coverage=model.coverage,
                           fallback=model.fallback, kind=model.kind,
                           metrics=dict(model.metrics), fit=fit_, data=dict(model.data))


class _Linearised(NamedTuple):
    """The chosen model's free columns followed by the thermal columns, linearised at the
    solution: per-fold CV of them, the column scale, the prior (scaled), the free columns'
    indices in the extended model ``m2`` (parameters ``x2``), and their count ``k``."""

    cv: _CV
    scale: Array
    pen: Array
    free: IntArray
    k: int
    m2: KinematicModel
    x2: Array


def _linearised(f: Fitter, sol: Solution, rows: IntArray, dT: Array) -> _Linearised:
    """Per-fold normal matrices (column-scaled, as ``auto``'s) over ``rows``; each pose's
    row of a length column is scaled by its temperature change ``dT`` (len(rows), dof)."""
    opts = f.opts
    m2, x2, idx = _with_length_terms(sol.model, sol.x)
    names = {n: i for i, n in enumerate(m2.names)}
    free = np.array([names[sol.model.names[i]] for i in sol.free], dtype=np.intp)
    prob = f.engine.problem(m2, sol.priors)
    cols = np.concatenate([free, idx])
    P, k = len(cols), len(free)
    fold_of = cv_folds(f.data.q[rows], opts.cv_folds, opts.seed,
                       math.radians(opts.cv_group_tol_deg))
    G_f = np.zeros((opts.cv_folds, P, P))
    b_f = np.zeros((opts.cv_folds, P))
    c_f = np.zeros(opts.cv_folds)
    for ch in prob.chunks(np.arange(len(rows))):
        Jw, rw = prob.whitened_jacobian(x2, rows[ch], cols)
        m = Jw.shape[0] // len(ch)
        Jw[:, k:] *= np.repeat(dT[ch], m, axis=0)
        fo = np.repeat(fold_of[ch], m)
        for fold in range(opts.cv_folds):
            sel = fo == fold
            if sel.any():
                G_f[fold] += Jw[sel].T @ Jw[sel]
                b_f[fold] += Jw[sel].T @ rw[sel]
                c_f[fold] += float(rw[sel] @ rw[sel])
    s = np.sqrt(np.clip(np.diagonal(G_f.sum(axis=0)), 0.0, None))
    s[s <= 1e-300] = 1.0
    G_f /= np.outer(s, s)[None]
    b_f /= s[None]
    pen = np.zeros((P, P))
    if prob.penalty is not None:
        pen[:k, :k] = prob.penalty[np.ix_(free, free)] / np.outer(s[:k], s[:k])
    return _Linearised(_CV(G_f, b_f, c_f), s, pen, free, k, m2, x2)


def thermal_step(f: Fitter, sol: Solution) -> tuple[Solution, dict[str, Any]]:
    """Consider the thermal group for the ``auto`` solution ``sol``; return the solution (with
    the term solved in when taken) and the selection log entry."""
    temps = f.data.temps
    rows = np.flatnonzero(sol.inliers)
    if temps is None:
        return sol, {"action": "thermal", "considered": False, "reason": "no temperatures"}
    spread = np.std(temps[rows], axis=0)
    if float(spread.max()) < MIN_VARIATION_C:
        return sol, {"action": "thermal", "considered": False,
                     "reason": f"temperatures vary by {float(spread.max()):.3f} degC "
                               f"(std), under {MIN_VARIATION_C} degC"}
    t_ref = temps[rows].mean(axis=0)
    dT = temps[rows] - t_ref
    lin = _linearised(f, sol, rows, dT)
    cv, s, pen, k = lin.cv, lin.scale, lin.pen, lin.k
    all_cols = np.arange(len(s), dtype=np.intp)
    base = cv.score(all_cols[:k], pen[:k, :k])
    with_term = cv.score(all_cols, pen)
    m_obs = 3 * len(rows)
    gain = 1.0 - with_term / base if base > 0 else 0.0
    note: dict[str, Any] = {
        "action": "thermal", "considered": True, "group": "thermal",
        "cv_rms_whitened_without": math.sqrt(base / m_obs),
        "cv_rms_whitened_with": math.sqrt(with_term / m_obs),
        "gain_percent": 100.0 * gain, "selected": bool(gain >= f.opts.auto_min_improvement)}
    if not note["selected"]:
        return sol, note
    A = cv.G + pen
    d = np.linalg.solve(A, cv.b) / s
    x_new = lin.x2.copy()
    x_new[lin.free] += d[:k]
    x_sol = lin.m2.transfer(x_new, sol.model)
    # coefficient sigmas: a-posteriori, the variance factor of the final solve
    var = np.diag(np.linalg.inv(A))[k:] / s[k:] ** 2 * sol.variance_factor
    term = {"selected": True, "components": list(thermal_components(f.robot.joints)),
            "coef_mm_per_c": [float(v) * 1e3 for v in d[k:]],
            "sigma_mm_per_c": [float(v) * 1e3 for v in np.sqrt(np.clip(var, 0.0, None))],
            "t_ref_c": [float(v) for v in t_ref]}
    note.update({k_: term[k_] for k_ in ("coef_mm_per_c", "t_ref_c")})
    return dataclasses.replace(sol, x=x_sol, thermal=term), note
