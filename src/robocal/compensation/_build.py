"""Building compensation tables from a calibrated model (pure functions, no I/O).

``targets``  corrected joint commands for program targets (:func:`compensate`);
``joint``    per-joint corrections derived from the model's rotation errors about the joint
             axes (``ez`` terms), on grids fine enough for a stated linear-interpolation bound;
``frames``   user (base) and tool frames that make the controller's *nominal* kinematics match
             the model as closely as frames can (least squares over poses in the coverage).

Every table states its predicted residual: the RMS distance, predicted by the model, between
where the robot goes and where it should go with the table applied (sampled poses inside the
coverage for ``joint``/``frames``; the solver's model residual for ``targets``).
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from robocal.compensation._solve import CompensationResult, compensate, model_evaluator
from robocal.compensation._table import (
    CompensationTable,
    Frame,
    FramesPayload,
    JointCorrection,
    TargetRow,
)
from robocal.compensation._targets import TargetSet
from robocal.errors import CompensationError, ConfigError
from robocal.kinematics import (
    CalibratedModel,
    ErrorModelSpec,
    KinematicModel,
    ParameterLayout,
    Term,
    evaluate_basis,
    matrix_to_wpr,
)

Array = NDArray[np.float64]
Kind = Literal["targets", "joint", "frames"]
_TWO_PI = 2.0 * math.pi


# --- sampling and frames --------------------------------------------------------------------
def valid_range(cal: CalibratedModel) -> Array:
    """Joint range (dof, 2) rad where the model is valid: its coverage within the limits."""
    lim = cal.robot.joint_limits
    if cal.coverage is None:
        return lim.copy()
    cov = np.asarray(cal.coverage, dtype=float)
    return np.stack([np.maximum(cov[:, 0], lim[:, 0]), np.minimum(cov[:, 1], lim[:, 1])], 1)


def ideal_positions(cal: CalibratedModel, q: Array) -> Array:
    """Reflector positions (n, 3) m of the *error-free* robot with the calibrated base and tool.

    These are the Cartesian targets a program taught with joint values ``q`` (n, dof) rad
    means; compensation finds the joints that reach them on the real (modelled) robot.
    """
    nominal = cal.model.with_spec(ErrorModelSpec(cal.robot.dof, ()))
    x = cal.model.transfer(cal.params, nominal)
    return nominal.positions(np.atleast_2d(np.asarray(q, dtype=float)), x)


def nominal_residual_mm(cal: CalibratedModel, q: Array, p_target: Array | None = None) -> float:
    """RMS distance (mm), predicted by the model, between where the *uncompensated* robot
    goes at joints ``q`` (n, dof) rad and where it should go (``p_target`` (n, 3) m, default
    :func:`ideal_positions`): the figure a table's predicted residual is compared with.
    """
    q2 = np.atleast_2d(np.asarray(q, dtype=float))
    target = ideal_positions(cal, q2) if p_target is None else np.atleast_2d(p_target)
    d = np.linalg.norm(cal.predict(q2) - target, axis=1)
    return float(np.sqrt(np.mean(d**2)) * 1e3) if d.size else 0.0


def sample_poses(cal: CalibratedModel, n: int, seed: int = 0) -> Array:
    """``n`` uniform random joint vectors (n, dof) rad inside :func:`valid_range` (seeded)."""
    rng = np.random.default_rng(seed)
    r = valid_range(cal)
    return rng.uniform(r[:, 0], r[:, 1], (n, r.shape[0]))


@dataclass(frozen=True)
class FrameFit:
    """Frames for the nominal kinematics fitted to the model.

    ``T_tracker_base`` (4, 4) m; ``tool`` (3,) m, TCP in the flange frame; ``residual_m``
    (n,) per sampled pose.
    """

    T_tracker_base: Array
    tool: Array
    residual_m: Array

    @property
    def rms_m(self) -> float:
        """RMS residual, m."""
        return float(np.sqrt(np.mean(self.residual_m**2)))


def fit_frames(cal: CalibratedModel, q_nominal: Array, p_actual: Array, iters: int = 8
               ) -> FrameFit:
    """Base and tool frames so that the nominal robot at ``q_nominal`` reaches ``p_actual``.

    Gauss-Newton over the 9 frame parameters (base 6, tool 3), started from the model's own
    base and tool. ``q_nominal`` (n, dof) rad, ``p_actual`` (n, 3) m tracker frame.
    """
    robot = cal.robot
    nm = KinematicModel(robot, ErrorModelSpec(robot.dof, ()),
                        cal.model.base_transform(cal.params))
    x = nm.nominal_params()
    x[ParameterLayout.TOOL] = cal.params[ParameterLayout.TOOL]
    for _ in range(iters):
        p, J = nm.jacobian(q_nominal, x)
        r = (p_actual - p).ravel()
        dx = np.linalg.lstsq(J.reshape(-1, nm.size), r, rcond=None)[0]
        x = x + dx
        if np.abs(dx).max() < 1e-12:
            break
    res = np.linalg.norm(p_actual - nm.positions(q_nominal, x), axis=1)
    return FrameFit(T_tracker_base=nm.base_transform(x), tool=x[ParameterLayout.TOOL].copy(),
                    residual_m=res)


def _frame(T: Array) -> Frame:
    w, p, r = (math.degrees(a) for a in matrix_to_wpr(T[:3, :3]))
    x, y, z = (float(v) * 1e3 for v in T[:3, 3])
    return Frame(x=x, y=y, z=z, w=w, p=p, r=r)


def frames_payload(fit: FrameFit) -> FramesPayload:
    """Frames in table form: user frame ``T_base_tracker`` and tool (mm, deg)."""
    # numpy stub types inv() of any float input as floating[Any]; float64 in gives float64
    T_bt: Array = np.linalg.inv(fit.T_tracker_base)  # type: ignore[assignment]
    tool = np.eye(4)
    tool[:3, 3] = fit.tool
    return FramesPayload(base=_frame(T_bt), tool=_frame(tool))


# --- joint corrections ----------------------------------------------------------------------
def _ez_basis(cal: CalibratedModel, j: int, *, with_const: bool = False
              ) -> tuple[Any, Array, float] | None:
    """Basis of the model's rotation error about joint j's axis.

    Returns ``(phi, coef, freq)``: ``phi(q (m,)) -> (m, k)`` the ``ez`` basis functions of
    joint j (gravity terms left out: they depend on the whole configuration), their
    coefficients in the model, and the highest frequency (rad^-1) among them. None when the
    model has no such terms (unless ``with_const``: then at least a constant).
    """
    spec = cal.model.spec
    robot = cal.robot
    idx = [k for k, t in enumerate(spec.terms)
           if t.joint == j and t.component == "ez" and t.family != "gravity"]
    terms = [spec.terms[k] for k in idx]
    coef = cal.params[ParameterLayout.TERMS][idx] if idx else np.zeros(0)
    if with_const and not any(t.family == "const" for t in terms):
        terms.append(Term(j, "ez", "const"))
        coef = np.append(coef, 0.0)
    if not terms:
        return None
    sub = ErrorModelSpec(spec.dof, tuple(terms), spec.map_knots)
    freq = 1.0
    for t in terms:
        if t.family in ("cos", "sin"):
            freq = max(freq, float(t.index))
        elif t.family in ("swcos", "swsin"):
            freq = max(freq, t.index * float(robot.joints[j].gear_ratio or 0.0))
        elif t.family == "map":
            freq = max(freq, float(spec.map_knots[j]))
        elif t.family == "poly":
            span = robot.joints[j].q_max - robot.joints[j].q_min
            freq = max(freq, t.index * _TWO_PI / max(span, 1e-9))

    def phi(q: Array) -> Array:
        Q = np.zeros((np.size(q), spec.dof))
        Q[:, j] = np.ravel(q)
        B, _ = evaluate_basis(sub, robot, Q)
        return B

    return phi, coef, freq


def _grid(lo: float, hi: float, c_lo: float, c_hi: float, n: int) -> Array:
    """n strictly increasing points over [lo, hi], uniform over the coverage [c_lo, c_hi]."""
    ends = [lo] if c_lo > lo + 1e-12 else []
    tail = [hi] if c_hi < hi - 1e-12 else []
    inner = np.linspace(c_lo, c_hi, n - len(ends) - len(tail))
    return np.concatenate([ends, inner, tail])


@dataclass(frozen=True)
class _Entry:
    joint: int          # 0-based target joint
    source: int         # 0-based source joint
    f: Any              # correction (rad) as a function of the source joint's value
    freq: float


def _ez_entries(cal: CalibratedModel) -> list[_Entry]:
    robot = cal.robot
    Ci = np.linalg.inv(robot.coupling_matrix)
    cover = valid_range(cal)
    out: list[_Entry] = []
    for j in range(robot.dof):
        fb = _ez_basis(cal, j)
        if fb is None:
            continue
        phi, coef, freq = fb
        cjj = Ci[j, j]
        lo, hi = cover[j]

        def cmd(q: Array, phi: Any = phi, coef: Array = coef, cjj: float = cjj,
                lo: float = lo, hi: float = hi) -> Array:
            # diagonal fixed point s = -Cinv[j, j] u_j(q + s), held beyond the coverage
            qc = np.clip(q, lo, hi)
            s = np.zeros_like(qc)
            for _ in range(4):
                s = -cjj * (phi(qc + s) @ coef)
            return qc + s

        for i in range(robot.dof):
            cij = Ci[i, j]
            if abs(cij) < 1e-15:
                continue

            def f(q: Array, phi: Any = phi, coef: Array = coef, cij: float = cij,
                  cmd: Any = cmd) -> Array:
                return -cij * (phi(cmd(q)) @ coef)

            out.append(_Entry(joint=i, source=j, f=f, freq=freq))
    return out


def _low_order_basis(robot: Any, j: int) -> Any:
    """[1, P1(q), cos q, sin q, cos 2q, sin 2q] of joint j's value (P1 over its limits)."""
    lo, hi = robot.joints[j].q_min, robot.joints[j].q_max

    def phi(q: Array) -> Array:
        q = np.ravel(q)
        return np.stack([np.ones_like(q), (2.0 * q - (lo + hi)) / (hi - lo), np.cos(q),
                         np.sin(q), np.cos(2.0 * q), np.sin(2.0 * q)], axis=1)

    return phi


def _fitted_entries(cal: CalibratedModel, samples: int, seed: int, iters: int = 3
                    ) -> list[_Entry]:
    """The ``ez`` entries plus low-order corrections fitted (with the frames) so that the
    nominal kinematics with the table reproduce the model best.

    Rotations about a joint axis at high frequency (strain-wave ripple, fine maps, higher
    harmonics) cannot be mimicked by other error components, so the ``ez`` derivation is
    kept for them; the constant, linear and first/second harmonic parts, which position-only
    data may split arbitrarily between ``ez`` and other components, are re-fitted.
    """
    robot = cal.robot
    Ci = np.linalg.inv(robot.coupling_matrix)
    cover = valid_range(cal)
    base = {(e.joint, e.source): e for e in _ez_entries(cal)}
    pairs = [(i, j) for j in range(robot.dof) for i in range(robot.dof)
             if abs(Ci[i, j]) > 1e-15]
    Q = sample_poses(cal, samples, seed + 1)
    dq0 = np.zeros_like(Q)
    for (i, j), e in base.items():
        dq0[:, i] += e.f(Q[:, j])
    phis = {j: _low_order_basis(robot, j) for j in range(robot.dof)}
    Phi = [phis[j](Q[:, j]) for _, j in pairs]
    coefs = [np.zeros(P.shape[1]) for P in Phi]
    nm = KinematicModel(robot, ErrorModelSpec(robot.dof, ()),
                        cal.model.base_transform(cal.params))
    x = nm.nominal_params()
    x[ParameterLayout.TOOL] = cal.params[ParameterLayout.TOOL]
    ev = model_evaluator(cal)
    for _ in range(iters):
        dq = dq0.copy()
        for (i, _), P, c in zip(pairs, Phi, coefs, strict=True):
            dq[:, i] += P @ c
        p_m, _, J = ev(Q + dq, True)
        assert J is not None
        p_n, Jn = nm.jacobian(Q, x)
        cols = [-Jn.reshape(-1, nm.size)]
        for (i, _), P in zip(pairs, Phi, strict=True):
            cols.append((J[:, :3, i, None] * P[:, None, :]).reshape(-1, P.shape[1]))
        A = np.concatenate(cols, axis=1)
        scale = np.linalg.norm(A, axis=0)
        scale[scale == 0] = 1.0
        sol = np.linalg.lstsq(A / scale, (p_n - p_m).ravel(), rcond=1e-9)[0] / scale
        x = x + sol[:nm.size]
        k = nm.size
        for c in coefs:
            c += sol[k:k + c.size]
            k += c.size
    out: list[_Entry] = []
    for (i, j), c in zip(pairs, coefs, strict=True):
        lo, hi = cover[j]
        e0 = base.get((i, j))

        def f(q: Array, phi: Any = phis[j], c: Array = c, lo: float = lo, hi: float = hi,
              e0: _Entry | None = e0) -> Array:
            v = phi(np.clip(q, lo, hi)) @ c
            return v if e0 is None else v + e0.f(q)

        out.append(_Entry(joint=i, source=j, f=f, freq=max(2.0, e0.freq if e0 else 2.0)))
    return out


def _max_interp_error(f_dense: Array, q_dense: Array, grid: Array, f_grid: Array) -> float:
    return float(np.max(np.abs(np.interp(q_dense, grid, f_grid) - f_dense)))


def joint_corrections(cal: CalibratedModel, *, tol_deg: float = 1e-4, max_points: int = 20001,
                      uniform_length: bool = True, method: str = "ez", samples: int = 2000,
                      sample_seed: int = 0) -> list[JointCorrection]:
    """Per-joint correction tables derived from the model's ``ez`` terms.

    For chain angles ``theta = C q + offset`` and rotation errors ``u_j(q_j)`` about the
    joint axes, the command ``q_c`` that realises program joints ``q`` satisfies
    ``C (q_c - q) = -u(q_c)``, i.e. ``dq = -C^-1 u(q_c)``. Entry (i, j) tabulates
    ``-Cinv[i, j] u_j(q_j + s_j(q_j))`` over joint j's value, where ``s_j`` is joint j's own
    (diagonal) correction, solved as a fixed point; a coupled robot therefore gets an extra
    entry (FANUC: joint 3 from joint 2). A separable table cannot follow the small shift
    the cross entry makes in joint i's own correction (``u_i'`` times the cross value); that
    second-order term is added to the cross entry's stated bound. Beyond the model's
    coverage the correction is held at its edge value: the table never extrapolates.

    Grids are uniform over the coverage plus the two range ends; the spacing is refined until
    linear interpolation, checked on a dense sampling that resolves the highest harmonic,
    stays below ``tol_deg`` split evenly over the entries of each joint. With
    ``uniform_length`` every entry gets the same number of points (register-block drivers
    need it).

    ``method="fit"`` keeps the ``ez`` derivation and adds per-entry low-order corrections
    (constant, linear, first and second harmonic of the source joint), fitted together with
    the frames so that the nominal kinematics with the table reproduce the model best over
    ``samples`` poses in the coverage. Use it when position-only data leave the split between
    rotations about the joint axes and the other error components unidentifiable (then the
    plain ``ez`` table can even increase the residual; the table's stats show it).
    """
    if method not in ("ez", "fit"):
        raise ConfigError(f"unknown joint-table method {method!r} (ez, fit)")
    if tol_deg <= 0:
        raise ConfigError(f"interpolation tolerance must be positive, got {tol_deg}")
    robot = cal.robot
    lim = robot.joint_limits
    cover = valid_range(cal)
    entries = _ez_entries(cal) if method == "ez" else _fitted_entries(cal, samples, sample_seed)
    per_joint = {i: sum(1 for e in entries if e.joint == i) for i in range(robot.dof)}
    tol = math.radians(tol_deg)
    dense: dict[int, tuple[Array, Array]] = {}
    need: list[int] = []
    bounds: list[float] = []
    for e in entries:
        lo, hi = cover[e.source]
        step = min(math.radians(0.25), _TWO_PI / e.freq / 48.0)
        qd = np.linspace(lo, hi, max(3, math.ceil((hi - lo) / step) + 1))
        fd = e.f(qd)
        dense[id(e)] = (qd, fd)
        bound = tol / per_joint[e.joint]
        bounds.append(bound)
        h = qd[1] - qd[0]
        m2 = float(np.max(np.abs(np.diff(fd, 2)))) / h**2 if qd.size > 2 else 0.0
        spacing = math.sqrt(8.0 * 0.8 * bound / m2) if m2 > 0 else hi - lo
        n = int(min(max_points, max(2, math.ceil((hi - lo) / max(spacing, 1e-12)) + 1)))
        while True:
            g = np.linspace(lo, hi, n)
            if _max_interp_error(fd, qd, g, e.f(g)) <= 0.8 * bound or n >= max_points:
                break
            n = min(max_points, int(n * 1.25) + 1)
        ends = int(lo > lim[e.source, 0] + 1e-12) + int(hi < lim[e.source, 1] - 1e-12)
        need.append(n + ends)
    n_common = max(need, default=2)
    # A cross entry (i from j) shifts joint i's command, and so the argument of joint i's own
    # correction, by up to max|f_ij|: a non-separable error of about max|f_ii'| max|f_ij|.
    slope = {e.joint: float(np.max(np.abs(np.diff(dense[id(e)][1]) / np.diff(dense[id(e)][0]))))
             for e in entries if e.joint == e.source and dense[id(e)][0].size > 1}
    out: list[JointCorrection] = []
    for k, e in enumerate(entries):
        lo, hi = cover[e.source]
        g = _grid(lim[e.source, 0], lim[e.source, 1], lo, hi,
                  n_common if uniform_length else need[k])
        fg = e.f(g)
        qd, fd = dense[id(e)]
        err = max(bounds[k], _max_interp_error(fd, qd, g, fg))
        if e.joint != e.source:
            err += 1.2 * slope.get(e.joint, 0.0) * float(np.max(np.abs(fd)))
        out.append(JointCorrection(
            joint=e.joint + 1, q_deg=np.degrees(g).tolist(), dq_deg=np.degrees(fg).tolist(),
            interpolation_error_bound_deg=math.degrees(err),
            source_joint=None if e.source == e.joint else e.source + 1))
    return out


# --- tables -----------------------------------------------------------------------------------
def _validation_rms_mm(cal: CalibratedModel) -> float | None:
    m = cal.metrics or {}
    for path in (("validation_rms_mm",), ("validation", "rms_mm"), ("validation", "rms_m")):
        v: Any = m
        for key in path:
            v = v.get(key) if isinstance(v, dict) else None
        if isinstance(v, int | float) and math.isfinite(v):
            return float(v) * (1e3 if path[-1] == "rms_m" else 1.0)
    return None


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")



def _check_targets(cal: CalibratedModel, targets: TargetSet) -> None:
    if targets.dof != cal.robot.dof:
        raise ConfigError(f"targets have {targets.dof} seed joints, robot {cal.robot.name!r} "
                          f"has {cal.robot.dof}")


def targets_table(cal: CalibratedModel, targets: TargetSet, result: CompensationResult, *,
                  created: str | None = None) -> CompensationTable:
    """A sealed ``targets`` table from an already computed :func:`compensate` result.

    Rows follow the targets' order (``index`` = row number). A row whose status is not
    ``ok`` carries the uncorrected seed joints, so the table stays rectangular; drivers push
    only ``ok`` rows.
    """
    _check_targets(cal, targets)
    if len(result) != len(targets):
        raise ConfigError(f"result has {len(result)} rows, targets {len(targets)}")
    rows = []
    for i in range(len(result)):
        ok = bool(result.ok[i])
        q = result.q[i] if ok else targets.q_seed[i]
        rows.append(TargetRow(index=i, q_deg=np.degrees(q).tolist(), status=result.status[i],
                              model_residual_mm=float(result.residual_m[i] * 1e3)))
    okr = result.residual_m[result.ok]
    stats: dict[str, float] = {
        "n_targets": float(len(result)), "n_ok": float(okr.size),
        "max_model_residual_mm": float(okr.max() * 1e3) if okr.size else 0.0,
        "n_outside_coverage": float(np.sum(result.ok & ~result.in_coverage)),
        "n_orientation_relaxed": float(np.sum(result.ok & result.orientation_relaxed)),
        # the seeds are the program's joints when the targets come from a taught program
        "nominal_residual_mm": nominal_residual_mm(cal, targets.q_seed, targets.p),
    }
    vr = _validation_rms_mm(cal)
    if vr is not None:
        stats["model_validation_rms_mm"] = vr
    return CompensationTable(
        kind="targets", targets=rows, stats=stats, model_id=cal.model_id, robot=cal.robot.name,
        valid_range_deg=[(float(a), float(b)) for a, b in np.degrees(valid_range(cal))],
        created=created if created is not None else _now(),
        predicted_residual_mm=float(np.sqrt(np.mean(okr**2)) * 1e3) if okr.size else 0.0,
    ).sealed()


def build_table(cal: CalibratedModel, kind: Kind, *, targets: TargetSet | None = None,
                targets_p: Array | None = None, seeds_q: Array | None = None,
                R_targets: Array | None = None,
                interp_tol_deg: float = 1e-4, with_joint_table: bool = False,
                joint_method: str = "ez", samples: int = 2000, sample_seed: int = 0,
                created: str | None = None,
                **compensate_options: Any) -> CompensationTable:
    """Build a sealed compensation table of ``kind`` from a calibrated model.

    Parameters
    ----------
    cal
        The identified model.
    kind
        ``"targets"``, ``"joint"`` or ``"frames"``.
    targets
        Program targets (required for ``targets``) ...
    targets_p, seeds_q, R_targets
        ... or the same as arrays: positions (n, 3) m tracker frame, seed joints (n, dof)
        rad, optional flange orientations (n, 3, 3).
    interp_tol_deg
        ``joint``: bound on the linear-interpolation error of each joint's total correction.
    with_joint_table
        ``frames``: fit the frames for use together with the joint table (the joint table's
        own predicted residual always assumes this).
    joint_method
        ``"ez"`` (the model's rotations about the joint axes, default) or ``"fit"`` (least
        squares projection); see :func:`joint_corrections`.
    samples, sample_seed
        Poses sampled inside the coverage to fit frames and predict residuals.
    created
        Timestamp to record (default: now, UTC).
    **compensate_options
        Passed to :func:`compensate` for ``targets``.

    Returns
    -------
    CompensationTable
        Sealed (checksum filled in).
    """
    robot = cal.robot
    common: dict[str, Any] = {
        "model_id": cal.model_id, "robot": robot.name,
        "valid_range_deg": [(float(a), float(b)) for a, b in np.degrees(valid_range(cal))],
        "created": created if created is not None else _now(),
    }
    stats: dict[str, float] = {}
    vr = _validation_rms_mm(cal)
    if vr is not None:
        stats["model_validation_rms_mm"] = vr
    if kind == "targets":
        if targets is None and targets_p is not None and seeds_q is not None:
            p = np.atleast_2d(np.asarray(targets_p, dtype=float))
            q = np.asarray(seeds_q, dtype=float)
            q = np.broadcast_to(q, (p.shape[0], q.shape[-1])) if q.ndim == 1 else q
            targets = TargetSet(p=p, q_seed=q, R=R_targets)
        if targets is None:
            raise ConfigError("a targets table needs program targets")
        _check_targets(cal, targets)
        res = compensate(cal, targets.p, targets.q_seed, R_targets=targets.R,
                         **compensate_options)
        return targets_table(cal, targets, res, created=common["created"])
    Q = sample_poses(cal, samples, sample_seed)
    stats["nominal_residual_mm"] = nominal_residual_mm(cal, Q)
    if kind == "joint":
        joints = joint_corrections(cal, tol_deg=interp_tol_deg, method=joint_method,
                                   samples=samples, sample_seed=sample_seed)
        table = CompensationTable(kind="joint", joints=joints, predicted_residual_mm=0.0,
                                  **common)
        plain = fit_frames(cal, Q, cal.predict(Q))
        q_cmd = Q + np.radians(table.joint_offsets_deg(np.degrees(Q)))
        with_table = fit_frames(cal, Q, cal.predict(q_cmd))
        stats.update({
            "frames_only_rms_mm": plain.rms_m * 1e3,
            "with_frames_rms_mm": with_table.rms_m * 1e3,
            "grid_points": float(len(joints[0].q_deg)) if joints else 0.0,
            "interpolation_tol_deg": interp_tol_deg,
            "joint_method_fit": float(joint_method == "fit"),
        })
        return table.model_copy(update={
            "predicted_residual_mm": with_table.rms_m * 1e3, "stats": stats}).sealed()
    if kind == "frames":
        q_cmd = Q
        if with_joint_table:
            jt = CompensationTable(kind="joint", predicted_residual_mm=0.0,
                                   joints=joint_corrections(
                                       cal, tol_deg=interp_tol_deg, method=joint_method,
                                       samples=samples, sample_seed=sample_seed),
                                   **common)
            q_cmd = Q + np.radians(jt.joint_offsets_deg(np.degrees(Q)))
        fit = fit_frames(cal, Q, cal.predict(q_cmd))
        stats.update({"max_mm": float(fit.residual_m.max() * 1e3), "n_samples": float(samples),
                      "with_joint_table": float(with_joint_table)})
        return CompensationTable(kind="frames", frames=frames_payload(fit), stats=stats,
                                 predicted_residual_mm=fit.rms_m * 1e3, **common).sealed()
    raise CompensationError(f"unknown table kind {kind!r} (targets, joint, frames)")
