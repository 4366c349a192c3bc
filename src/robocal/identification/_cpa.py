"""Circle Point Analysis (CPA): the classical baseline calibration from single-joint sweeps.

For each joint a sweep moves only that joint's chain angle (coupled joints compensated) with
all others at a common home configuration. The reflector then runs on a circle about the
joint's true axis: a plane fit gives the axis direction, a circle fit in that plane a point
on the axis, and the circle phase the home position of the reflector. The six axes at home
plus the home point are a product-of-exponentials (POE) model, which is exactly the constant
kinematic model; it is converted to robocal's constant error model by a noise-free
least-squares fit, so the result is an ordinary :class:`CalibratedModel`. That is classical
CPA (``kind="cpa-classical"``, kept and reported as such).

Each circle is fitted on its own, so a short arc or a small radius leaves its axis poorly
determined, and nothing ties the six fits together. The *polish* (ADR 0021) therefore
re-fits the constant model by robust maximum likelihood on all the sweep points at once,
started from the classical model: the same engine and whitening as ``fit(..., "constant")``,
only on the sweep poses. That model is the CPA result (``kind="cpa"``).

CPA assumes perfect circles: joint-dependent errors show up as circle-fit residuals (reported
per joint against what the tracker noise alone would leave) and are not modelled. The
diagnosis names each weak joint: arcs under :data:`CPA_MIN_ARC_DEG`, radii under
:data:`CPA_MIN_RADIUS_MM`, circle residuals over :data:`CPA_MAX_NOISE_RATIO` times the noise.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import reduce
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.measurements import MeasurementSet
from robocal._core.threads import blas_threads
from robocal.errors import DataError, IdentificationError, NotConverged, NotIdentifiable
from robocal.identification._engine import Engine, EngineSettings
from robocal.identification._metrics import Accuracy, accuracy
from robocal.identification._solver import Problem, analyse_jacobian, levenberg_marquardt
from robocal.kinematics import (
    CalibratedModel,
    ErrorModelSpec,
    KinematicModel,
    RobotDescription,
    load_robot,
    rigid_fit,
)

Array = NDArray[np.float64]

#: Most re-weighting rounds of the polish (variance components per sweep).
POLISH_ROUNDS = 6
#: Arcs shorter than this (deg) leave a circle's centre and axis poorly determined.
CPA_MIN_ARC_DEG = 90.0
#: Circles smaller than this (mm) leave the axis direction poorly determined.
CPA_MIN_RADIUS_MM = 100.0
#: Circle residuals above this multiple of the tracker noise reveal joint-dependent errors (at
#: 2x, three quarters of the residual variance is not noise; pure noise stays within ~1.3x).
CPA_MAX_NOISE_RATIO = 2.0


@dataclass(frozen=True)
class CircleFit:
    """One joint's sweep: axis line and circle (metres, tracker frame).

    ``arc``: the chain-angle range the sweep covered, rad. ``noise_m``: the RMS distance from
    the circle that the tracker noise alone would leave (NaN when unknown).
    """

    joint: int
    centre: Array          # (3,) point on the axis
    direction: Array       # (3,) unit axis, right-handed for increasing chain angle
    radius: float
    rms_m: float           # RMS distance of the points from the fitted circle
    max_m: float
    home_point: Array      # (3,) circle point at the home chain angle
    n: int
    arc: float = math.nan
    noise_m: float = math.nan

    @property
    def noise_ratio(self) -> float:
        """Circle residual RMS over what the tracker noise alone leaves (NaN when unknown)."""
        return self.rms_m / self.noise_m if self.noise_m > 0 else math.nan

    def issues(self) -> list[dict[str, Any]]:
        """Why this circle limits CPA, if it does: short arc, small radius, joint-dependent
        errors. Each item: ``joint`` (1-based), ``issue``, ``value``, ``limit``, ``unit``,
        ``text`` (one sentence, mm/deg)."""
        k = self.joint + 1
        out: list[dict[str, Any]] = []
        arc = math.degrees(self.arc)
        if arc < CPA_MIN_ARC_DEG:
            out.append({"joint": k, "issue": "short arc", "value": arc,
                        "limit": CPA_MIN_ARC_DEG, "unit": "deg",
                        "text": f"J{k}: arc of only {arc:.0f}° (< {CPA_MIN_ARC_DEG:g}°), "
                                "so the circle's centre and axis are poorly determined"})
        r = self.radius * 1e3
        if r < CPA_MIN_RADIUS_MM:
            out.append({"joint": k, "issue": "small radius", "value": r,
                        "limit": CPA_MIN_RADIUS_MM, "unit": "mm",
                        "text": f"J{k}: circle radius of only {r:.0f} mm "
                                f"(< {CPA_MIN_RADIUS_MM:g} mm), so the axis direction is "
                                "poorly determined"})
        ratio = self.noise_ratio
        if ratio > CPA_MAX_NOISE_RATIO:
            out.append({"joint": k, "issue": "joint-dependent errors", "value": ratio,
                        "limit": CPA_MAX_NOISE_RATIO, "unit": "x noise",
                        "text": f"J{k}: circle residual {self.rms_m * 1e3:.3f} mm RMS is "
                                f"{ratio:.1f}× the tracker noise ({self.noise_m * 1e3:.4f} mm): "
                                "CPA cannot describe joint-dependent errors"})
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (mm, deg)."""
        return {"joint": self.joint + 1, "centre_mm": (self.centre * 1e3).tolist(),
                "direction": self.direction.tolist(), "radius_mm": self.radius * 1e3,
                "circle_rms_mm": self.rms_m * 1e3, "circle_max_mm": self.max_m * 1e3,
                "n": self.n, "arc_deg": _finite(math.degrees(self.arc)),
                "noise_rms_mm": _finite(self.noise_m * 1e3),
                "noise_ratio": _finite(self.noise_ratio),
                "issues": [i["issue"] for i in self.issues()]}


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


@dataclass(frozen=True)
class CPAPolish:
    """What the polish (robust constant-model ML fit on the sweep points) did.

    ``sweep_rms_classical_m`` / ``sweep_rms_m``: RMS position error (m) of the classical and
    the polished model over the sweep points the fit kept. ``sweep_noise_factor``: per joint
    sweep, the factor on the tracker noise the fit settled on (1: noise alone).
    """

    converged: bool
    status: str
    iterations: int
    n_free: int
    rank: int
    condition: float
    removed: tuple[str, ...]
    outliers: tuple[str, ...]
    variance_factor: float
    sweep_rms_classical_m: float
    sweep_rms_m: float
    n_points: int
    sweep_noise_factor: tuple[float, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (mm)."""
        return {"converged": self.converged, "status": self.status,
                "iterations": self.iterations, "n_free": self.n_free, "rank": self.rank,
                "condition_number": _finite(self.condition), "removed": list(self.removed),
                "outliers": list(self.outliers),
                "variance_factor": _finite(self.variance_factor),
                "sweep_points": self.n_points,
                "sweep_noise_factor": list(self.sweep_noise_factor),
                "sweep_rms_mm": {"classical": self.sweep_rms_classical_m * 1e3,
                                 "polished": self.sweep_rms_m * 1e3}}


@dataclass
class CPAResult:
    """Outcome of :func:`cpa_fit`.

    ``calibrated``: the CPA model (``kind="cpa"``): classical CPA polished by the
    constant-model ML fit on the sweep points, or classical CPA itself when the polish was
    off or failed (``polish`` None, see ``notes``). ``classical``: classical CPA
    (``kind="cpa-classical"``). ``validation`` / ``classical_validation``: their accuracy on
    the held-out poses.
    """

    calibrated: CalibratedModel  # kind "cpa"
    classical: CalibratedModel  # kind "cpa-classical"
    circles: list[CircleFit]  # one per swept joint
    home_q: Array  # (dof,) rad: the pose every sweep starts from
    home_point: Array  # (3,) m: its circle point
    #: RMS residual of the circles -> DH conversion (noise-free fit over random poses), m
    conversion_rms_m: float
    validation: Accuracy | None = None
    classical_validation: Accuracy | None = None
    polish: CPAPolish | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def outliers(self) -> list[str]:
        """Sweep poses the polish rejected as outliers (pose ids)."""
        return [] if self.polish is None else list(self.polish.outliers)

    @property
    def diagnosis(self) -> list[dict[str, Any]]:
        """Every weakness of the circle fits (see :meth:`CircleFit.issues`)."""
        return [i for c in self.circles for i in c.issues()]

    def summary(self) -> dict[str, Any]:
        """JSON-friendly summary (mm): both models' held-out RMS side by side."""

        def rms(a: Accuracy | None) -> float | None:
            return None if a is None else _finite(a.rms_m * 1e3)

        base = self.validation if self.validation is not None else self.classical_validation
        return {
            "model": "cpa",
            "method": self.calibrated.fit.get("method"),
            "circles": [c.to_dict() for c in self.circles],
            "diagnosis": self.diagnosis,
            "home_q_deg": np.degrees(self.home_q).tolist(),
            "home_point_mm": (self.home_point * 1e3).tolist(),
            "conversion_rms_mm": self.conversion_rms_m * 1e3,
            "validation": None if self.validation is None else self.validation.to_dict(),
            "validation_rms_mm": {
                "classical": rms(self.classical_validation),
                "polished": None if self.polish is None else rms(self.validation),
                "nominal": (None if base is None or base.baseline_rms_m is None
                            else base.baseline_rms_m * 1e3)},
            "classical": {"model_id": self.classical.model_id,
                          "validation": (None if self.classical_validation is None
                                         else self.classical_validation.to_dict())},
            "polish": None if self.polish is None else {"model_id": self.calibrated.model_id,
                                                        **self.polish.to_dict()},
            "notes": list(self.notes),
        }


# ----------------------------------------------------------------------------------------------
def cpa_sweeps(robot: RobotDescription | str, *, home: Array | None = None,
               n_points: int = 15, span_deg: float = 240.0, margin_deg: float = 5.0
               ) -> list[tuple[int, Array]]:
    """Joint values for one CPA sweep per joint (test and simulation helper).

    Parameters
    ----------
    robot
        Robot description or name.
    home
        Home joint values (dof,) rad; default: the middle of each joint range.
    n_points
        Poses per sweep.
    span_deg
        Largest sweep span per joint (deg), centred on home, clipped to the limits.
    margin_deg
        Distance kept from the joint limits (deg).

    Returns
    -------
    list of (joint index, q (n_points, dof) rad)
        Only the joint's chain angle changes; joints coupled to it are compensated so that
        the other chain angles stay at their home values.
    """
    rob = load_robot(robot) if isinstance(robot, str) else robot
    lim = rob.joint_limits
    m = math.radians(margin_deg)
    q0 = lim.mean(axis=1) if home is None else np.asarray(home, dtype=float)
    Cinv = np.linalg.inv(rob.coupling_matrix)
    out = []
    for i in range(rob.dof):
        d = Cinv[:, i]                     # joint-value change per unit of chain angle i
        lo, hi = -math.radians(span_deg) / 2, math.radians(span_deg) / 2
        for j in np.flatnonzero(np.abs(d) > 1e-12):
            a = (lim[j, 0] + m - q0[j]) / d[j]
            b = (lim[j, 1] - m - q0[j]) / d[j]
            lo, hi = max(lo, min(a, b)), min(hi, max(a, b))
        if hi - lo < math.radians(10.0):
            raise IdentificationError(f"joint {i + 1}: home is too close to the limits for a "
                                      "CPA sweep")
        t = np.linspace(lo, hi, n_points)
        out.append((i, q0[None, :] + t[:, None] * d[None, :]))
    return out


def _fit_circle(joint: int, p: Array, t: Array, t_home: float,
                cov: Array | None = None) -> CircleFit:
    """Plane + circle fit of points ``p`` (n, 3) swept by chain angles ``t`` (n,) rad.

    ``cov`` (n, 3, 3) m^2: the points' covariances, for the noise level of the circle residual.
    """
    if len(p) < 4:
        raise DataError(f"joint {joint + 1}: a CPA sweep needs at least 4 poses, got {len(p)}")
    c0 = p.mean(axis=0)
    _, S, Vt = np.linalg.svd(p - c0)
    if S[1] < 1e-6 * max(S[0], 1e-300):
        raise DataError(f"joint {joint + 1}: sweep points are collinear (no circle)")
    u, v, n = Vt[0], Vt[1], Vt[2]
    xy = np.stack([(p - c0) @ u, (p - c0) @ v], axis=1)
    # algebraic (Kasa) fit, then geometric Gauss-Newton
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    sol = np.linalg.lstsq(A, (xy**2).sum(axis=1), rcond=None)[0]
    cxy = sol[:2]
    r = math.sqrt(max(sol[2] + cxy @ cxy, 0.0))
    for _ in range(20):
        d = xy - cxy
        rho = np.linalg.norm(d, axis=1)
        rho[rho == 0] = 1e-300
        res = rho - r
        J = np.column_stack([-d / rho[:, None], -np.ones(len(xy))])
        step = np.linalg.lstsq(J, -res, rcond=None)[0]
        cxy = cxy + step[:2]
        r = r + step[2]
        if np.linalg.norm(step) < 1e-12:
            break
    centre2 = c0 + cxy[0] * u + cxy[1] * v
    # direction: right-handed rotation for increasing chain angle
    rel = p - centre2
    order = np.argsort(t)
    cr = np.cross(rel[order][:-1], rel[order][1:]) @ n
    dt = np.diff(t[order])
    if np.sum(cr * np.sign(dt)) < 0:
        n = -n
    # off-plane offset and in-plane residuals
    off = (p - centre2) @ n
    inplane = rel - off[:, None] * n
    dist = np.sqrt((np.linalg.norm(inplane, axis=1) - r) ** 2 + off**2)
    # phase: angle of each point about n, minus the chain angle
    e1 = inplane[order[0]] / np.linalg.norm(inplane[order[0]])
    e2 = np.cross(n, e1)
    ang = np.arctan2(inplane @ e2, inplane @ e1)
    phi0 = float(np.angle(np.mean(np.exp(1j * (ang - t)))))
    a_home = phi0 + t_home
    home_point = centre2 + r * (math.cos(a_home) * e1 + math.sin(a_home) * e2) \
        + float(np.mean(off)) * n
    noise = math.nan
    if cov is not None:
        # noise moves a point off the circle along the radial and the axial direction; the
        # plane and circle fits absorb 6 of the 2n such coordinates
        rho = np.linalg.norm(inplane, axis=1, keepdims=True)
        ur = inplane / np.where(rho > 0, rho, 1.0)
        var = np.einsum("ni,nij,nj->n", ur, cov, ur) + np.einsum("i,nij,j->n", n, cov, n)
        noise = math.sqrt(float(np.mean(var)) * max(2 * len(p) - 6, 1) / (2 * len(p)))
    return CircleFit(joint=joint, centre=centre2, direction=n, radius=float(r),
                     rms_m=float(np.sqrt(np.mean(dist**2))), max_m=float(dist.max()),
                     home_point=home_point, n=len(p), arc=float(np.ptp(t)), noise_m=noise)


def _covariances(ds: MeasurementSet, settings: EngineSettings) -> Array:
    """Point covariances (n, 3, 3) m^2 as the ML fit weights them: the per-point sigmas when
    given (and used), else the tracker noise model."""
    if settings.use_point_sigma and ds.sigma is not None and np.all(ds.sigma > 0):
        return np.einsum("ni,ij->nij", ds.sigma**2, np.eye(3))
    return settings.noise.covariances(ds.p)


def _sweep_set(sweeps: Sequence[MeasurementSet]) -> MeasurementSet:
    """All sweep points as one set (positions only); pose ids made unique (``Jk:``) if needed."""
    sets = [s.without_orientation() for s in sweeps]
    ids = [pid for s in sets for pid in s.pose_id]
    if len(set(ids)) != len(ids):
        sets = [replace(s, pose_id=tuple(f"J{k + 1}:{pid}" for pid in s.pose_id))
                for k, s in enumerate(sets)]
    return reduce(MeasurementSet.concat, sets)


def _rotate(p: Array, c: Array, n: Array, ang: Array) -> Array:
    """Rotate points p (m, 3) about the line (c, n) by angles ang (m,) (Rodrigues)."""
    v = p - c
    ca, sa = np.cos(ang)[:, None], np.sin(ang)[:, None]
    return c + v * ca + np.cross(n, v) * sa + n * (v @ n)[:, None] * (1 - ca)


Rigid = tuple[Array, Array]


def _rotation_about(c: Array, n: Array, a: float) -> Rigid:
    """Rigid transform (R, t) of a rotation by ``a`` about the line through c along n."""
    K = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
    R = np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * (K @ K)
    return R, c - R @ c


def _invert(T: Rigid) -> Rigid:
    R, t = T
    return R.T, -R.T @ t


def _chain_transform(circles: Sequence[CircleFit], h: Array, r: Array,
                     joints: range) -> Rigid:
    """Product of exp(xi_k (h_k - r_k)) over ``joints`` in order (axes at configuration r)."""
    R, t = np.eye(3), np.zeros(3)
    for k in joints:
        c = circles[k]
        Rk, tk = _rotation_about(c.centre, c.direction, float(h[k] - r[k]))
        R, t = R @ Rk, R @ tk + t
    return R, t


def poe_positions(circles: Sequence[CircleFit], home_point: Array, theta_home: Array,
                  theta: Array) -> Array:
    """Reflector positions (m, 3) of the POE model for chain angles ``theta`` (m, dof)."""
    p = np.broadcast_to(home_point, (theta.shape[0], 3)).copy()
    for c in sorted(circles, key=lambda c: -c.joint):   # distal joint first
        p = _rotate(p, c.centre, c.direction, theta[:, c.joint] - theta_home[c.joint])
    return p


def cpa_fit(robot: RobotDescription | str, sweeps: Sequence[tuple[int, MeasurementSet]], *,
            validation: MeasurementSet | None = None,
            baseline: CalibratedModel | None = None, n_convert: int = 2000, seed: int = 0,
            polish: bool = True, options: EngineSettings | None = None) -> CPAResult:
    """Circle Point Analysis from single-joint sweeps, then its polish.

    Parameters
    ----------
    robot
        Robot description or name.
    sweeps
        One ``(joint index (0-based), MeasurementSet)`` per joint: poses where only that
        joint's chain angle changes; each sweep may hold the other joints at its own home.
    validation
        Poses to evaluate both CPA models on.
    baseline
        The nominal-with-base-and-reflector-fitted model of a fit on the same cell
        (``FitResult.baseline``), for the "% described" figures.
    n_convert
        Random configurations used to convert the POE model into the constant error model.
    polish
        Re-fit the constant model by robust ML on all sweep points, started from classical
        CPA (ADR 0021). Off: ``calibrated`` is classical CPA.
    options
        Tracker noise model, outlier test and solver settings of the polish and of the
        circles' noise levels (a :class:`FitOptions` will do); default ``EngineSettings()``.

    Returns
    -------
    CPAResult
        ``calibrated`` (``kind="cpa"``, polished) and ``classical``
        (``kind="cpa-classical"``), both constant-model :class:`CalibratedModel` objects.

    Raises
    ------
    DataError
        Missing or degenerate sweeps, or poses that move more than one chain angle.
    """
    with blas_threads(1):
        return _cpa_fit(robot, sweeps, validation, baseline, n_convert, seed, polish,
                        options or EngineSettings())


def _cpa_fit(robot: RobotDescription | str, sweeps: Sequence[tuple[int, MeasurementSet]],
             validation: MeasurementSet | None, baseline: CalibratedModel | None,
             n_convert: int, seed: int, polish: bool, settings: EngineSettings) -> CPAResult:
    rob = load_robot(robot) if isinstance(robot, str) else robot
    by_joint = {int(j): ds for j, ds in sweeps}
    missing = [j + 1 for j in range(rob.dof) if j not in by_joint]
    if missing:
        raise DataError(f"CPA needs one sweep per joint; missing joints {missing}")
    C = rob.coupling_matrix
    off = np.array([j.theta_offset for j in rob.joints])
    homes = []
    for j in range(rob.dof):
        ds = by_joint[j]
        if ds.dof != rob.dof:
            raise DataError(f"sweep of joint {j + 1} has {ds.dof} joint columns, robot has "
                            f"{rob.dof}")
        th = ds.q @ C.T + off
        others = np.delete(th, j, axis=1)
        if np.ptp(others, axis=0).max(initial=0.0) > 1e-6:
            raise DataError(f"sweep of joint {j + 1} moves other chain angles too")
        homes.append(th[0])
    # Each sweep may hold the other joints at its own home. The reference configuration r
    # takes, per joint, the median of the other sweeps' homes; every measured axis is moved
    # to r through the upstream joints' axes already found (product of exponentials), so a
    # common home is the special case in which every transform below is the identity.
    H = np.array(homes)
    th_home = np.array([np.median(np.delete(H[:, k], k)) for k in range(rob.dof)])
    circles: list[CircleFit] = []
    for j in range(rob.dof):
        ds = by_joint[j]
        th = ds.q @ C.T + off
        cf = _fit_circle(j, ds.p, th[:, j], th_home[j], _covariances(ds, settings))
        G = _chain_transform(circles, H[j], th_home, range(j))
        R, t = _invert(G)
        circles.append(replace(cf, centre=R @ cf.centre + t, direction=R @ cf.direction))
    # reflector position at r, from every sweep point mapped back to r
    backs = []
    for j in range(rob.dof):
        ds = by_joint[j]
        th = ds.q @ C.T + off
        Gi = _invert(_chain_transform(circles, H[j], th_home, range(j)))
        Di = _invert(_chain_transform(circles, H[j], th_home, range(j + 1, rob.dof)))
        pts = ds.p @ Gi[0].T + Gi[1]
        c = circles[j]
        pts = _rotate(pts, c.centre, c.direction, -(th[:, j] - th_home[j]))
        backs.append(pts @ Di[0].T + Di[1])
    home_point = np.vstack(backs).mean(axis=0)
    circles = [replace(c, home_point=home_point) for c in circles]
    home_q = np.linalg.solve(C, th_home - off)
    classical, conv = _classical_model(rob, circles, home_point, th_home, home_q, n_convert,
                                       seed)
    notes = []
    if conv > 1e-6:
        notes.append(f"POE -> constant-model conversion residual {conv * 1e3:.4f} mm")
    points = _sweep_set([by_joint[j] for j in range(rob.dof)])
    classical.data = {"n_poses": len(points),
                      "digest": [by_joint[j].digest() for j in range(rob.dof)]}
    cls_val = None
    if validation is not None:
        cls_val = accuracy(classical, validation, baseline=baseline)
        classical.metrics = {"validation": cls_val.to_dict()}
    classical.model_id = classical.compute_id()
    info: CPAPolish | None = None
    cal = None
    if polish:
        try:
            sweep_of = np.repeat(np.arange(rob.dof), [len(by_joint[j]) for j in range(rob.dof)])
            cal, info = _polish(rob, classical, points, sweep_of, settings)
        except (NotIdentifiable, NotConverged) as err:
            notes.append(f"the polish failed, classical CPA is the result: {err}")
    else:
        notes.append("not polished: classical CPA is the result")
    if cal is None:
        cal = CalibratedModel(model=classical.model, params=classical.params.copy(),
                              coverage=classical.coverage, kind="cpa")
        cal.fit = {**classical.fit, "model": "cpa"}
    cal.fit.update({"circles": [c.to_dict() for c in circles],
                    "diagnosis": [i for c in circles for i in c.issues()],
                    "home_q_deg": np.degrees(home_q).tolist(), "conversion_rms_mm": conv * 1e3,
                    "classical": {"model": classical.to_dict(),
                                  "validation": None if cls_val is None else cls_val.to_dict()}})
    cal.data = dict(classical.data)
    val = None
    if validation is not None:
        val = accuracy(cal, validation, baseline=baseline) if info is not None else cls_val
        cal.metrics = {"validation": None if val is None else val.to_dict(),
                       "classical_validation": None if cls_val is None else cls_val.to_dict()}
    cal.model_id = cal.compute_id()
    return CPAResult(calibrated=cal, classical=classical, circles=circles, home_q=home_q,
                     home_point=home_point, conversion_rms_m=conv, validation=val,
                     classical_validation=cls_val, polish=info, notes=notes)


def _classical_model(rob: RobotDescription, circles: list[CircleFit], home_point: Array,
                     th_home: Array, home_q: Array, n_convert: int, seed: int
                     ) -> tuple[CalibratedModel, float]:
    """The POE model (axes at ``th_home`` rad, reflector ``home_point`` m) as a constant-model
    :class:`CalibratedModel` (``kind="cpa-classical"``), by a noise-free least-squares fit
    over ``n_convert`` random configurations; also the fit's RMS residual (m)."""
    C = rob.coupling_matrix
    off = np.array([j.theta_offset for j in rob.joints])
    rng = np.random.default_rng(seed)
    lim = rob.joint_limits
    qc = rng.uniform(lim[:, 0], lim[:, 1], (n_convert, rob.dof))
    pc = poe_positions(circles, home_point, th_home, qc @ C.T + off)
    spec = ErrorModelSpec.constant(rob.dof)
    m0 = KinematicModel(rob, ErrorModelSpec(rob.dof, ()))
    T = rigid_fit(m0.positions(qc, m0.nominal_params()), pc)
    model = KinematicModel(rob, spec, T)
    W = np.broadcast_to(np.eye(3) / 1e-5, (n_convert, 3, 3)).copy()
    prob = Problem(model, qc, pc, W)
    rows = np.arange(n_convert)
    x0 = model.nominal_params()
    _, keep, _ = analyse_jacobian(prob, x0, rows, np.arange(model.size), tol=1e-6)
    info = levenberg_marquardt(prob, x0, np.flatnonzero(keep), rows, max_iter=200)
    conv = float(np.sqrt(np.mean(np.sum((model.positions(qc, info.x) - pc) ** 2, axis=1))))
    cal = CalibratedModel(model=model, params=info.x, covariance=None,
                          coverage=lim.copy(), kind="cpa-classical")
    cal.fit = {"model": "cpa-classical", "method": "plane + circle fit per joint sweep, POE "
               "model, converted to the constant error model",
               "circles": [c.to_dict() for c in circles],
               "diagnosis": [i for c in circles for i in c.issues()],
               "home_q_deg": np.degrees(home_q).tolist(),
               "conversion_rms_mm": conv * 1e3}
    return cal, conv


def _polish(rob: RobotDescription, classical: CalibratedModel, points: MeasurementSet,
            sweep_of: NDArray[np.intp], settings: EngineSettings
            ) -> tuple[CalibratedModel, CPAPolish]:
    """Robust constant-model ML fit on the sweep ``points``, started from ``classical``.

    ``sweep_of`` (n,): the sweep (joint index) of each point. Each sweep's noise is the
    tracker's times a factor of at least 1, its own residual RMS in units of the tracker noise
    (variance components, re-estimated until they settle): a sweep whose points carry
    joint-dependent errors then weighs less, instead of pulling the axes the other sweeps
    determine towards errors a constant model cannot describe. With noise alone every factor
    is 1 and the fit is plain ML. Raises NotIdentifiable / NotConverged like
    :meth:`Engine.solve`.
    """
    engine = Engine(rob, points, settings)
    W0 = engine.W.copy()
    factor = np.ones(int(sweep_of.max()) + 1)
    x = classical.params
    for _ in range(POLISH_ROUNDS):
        engine.W = W0 / factor[sweep_of][:, None, None]
        sol = engine.solve(classical.model, x, what="CPA polish")
        x = sol.x
        r = np.einsum("nij,nj->ni", W0, points.p - classical.model.positions(points.q, x))
        r2 = np.sum(r**2, axis=1)          # squared residual in tracker-noise units
        new = factor.copy()
        for k in range(len(factor)):
            mine = (sweep_of == k) & sol.inliers
            if mine.any():
                new[k] = max(1.0, math.sqrt(float(np.mean(r2[mine])) / 3.0))
        if np.all(np.abs(new / factor - 1.0) < 0.02):
            break
        factor = new
    inl = sol.inliers

    def rms(x: Array) -> float:
        r = points.p[inl] - classical.model.positions(points.q[inl], x)
        return float(np.sqrt(np.mean(np.sum(r**2, axis=1))))

    outliers = tuple(points.pose_id[i] for i in np.flatnonzero(~inl))
    info = CPAPolish(converged=bool(sol.info.converged), status=str(sol.info.status),
                     iterations=int(sol.info.iterations), n_free=sol.n_free,
                     rank=int(sol.ident.rank), condition=float(sol.ident.cond),
                     removed=tuple(sol.removed), outliers=outliers,
                     variance_factor=float(sol.variance_factor),
                     sweep_rms_classical_m=rms(classical.params), sweep_rms_m=rms(sol.x),
                     n_points=len(points), sweep_noise_factor=tuple(float(f) for f in factor))
    cal = CalibratedModel(model=classical.model, params=sol.x, covariance=sol.covariance,
                          coverage=rob.joint_limits.copy(), kind="cpa")
    cal.fit = {
        "model": "cpa",
        "method": "classical CPA (plane + circle fit per joint sweep, POE model) polished by "
                  "a robust constant-model maximum-likelihood fit on all sweep points, each "
                  "sweep's noise scaled by its own residuals (variance components)",
        "solver": {"method": "levenberg-marquardt", "iterations": info.iterations,
                   "converged": info.converged, "status": info.status,
                   "message": sol.info.message},
        "identifiability": {"rank": info.rank, "condition_number": _finite(info.condition),
                            "removed": list(info.removed),
                            "singular_values": [float(v) for v in sol.ident.singular_values],
                            "note": "column-scaled whitened Jacobian of the sweep points"},
        "n_params": classical.model.size, "n_free": info.n_free,
        "dof_effective": sol.dof_effective,
        "variance_factor": _finite(info.variance_factor),
        "covariance": "a-posteriori: variance factor x inverse normal matrix",
        "outliers": {"pose_ids": list(outliers),
                     "test": "normalised (deletion) residual, chi-square 3 dof, robust scale"},
        "polish": info.to_dict(),
        "sigma_source": engine.sigma_source,
    }
    return cal, info
