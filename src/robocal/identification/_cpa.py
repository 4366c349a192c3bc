"""Circle Point Analysis (CPA): the classical baseline calibration from single-joint sweeps.

For each joint a sweep moves only that joint's chain angle (coupled joints compensated) with
all others at a common home configuration. The reflector then runs on a circle about the
joint's true axis: a plane fit gives the axis direction, a circle fit in that plane a point
on the axis, and the circle phase the home position of the reflector. The six axes at home
plus the home point are a product-of-exponentials (POE) model, which is exactly the constant
kinematic model; it is converted to robocal's constant error model by a noise-free
least-squares fit, so the result is an ordinary :class:`CalibratedModel` (``kind="cpa"``).
CPA assumes perfect circles: joint-dependent errors show up as circle-fit residuals (reported
per joint) and are not modelled.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.measurements import MeasurementSet
from robocal._core.threads import blas_threads
from robocal.errors import DataError, IdentificationError
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


@dataclass(frozen=True)
class CircleFit:
    """One joint's sweep: axis line and circle (metres, tracker frame)."""

    joint: int
    centre: Array          # (3,) point on the axis
    direction: Array       # (3,) unit axis, right-handed for increasing chain angle
    radius: float
    rms_m: float           # RMS distance of the points from the fitted circle
    max_m: float
    home_point: Array      # (3,) circle point at the home chain angle
    n: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (mm)."""
        return {"joint": self.joint + 1, "centre_mm": (self.centre * 1e3).tolist(),
                "direction": self.direction.tolist(), "radius_mm": self.radius * 1e3,
                "circle_rms_mm": self.rms_m * 1e3, "circle_max_mm": self.max_m * 1e3,
                "n": self.n}


@dataclass
class CPAResult:
    """Outcome of :func:`cpa_fit`."""

    calibrated: CalibratedModel
    circles: list[CircleFit]
    home_q: Array
    home_point: Array
    conversion_rms_m: float
    validation: Accuracy | None = None
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """JSON-friendly summary (mm)."""
        return {
            "model": "cpa",
            "circles": [c.to_dict() for c in self.circles],
            "home_q_deg": np.degrees(self.home_q).tolist(),
            "home_point_mm": (self.home_point * 1e3).tolist(),
            "conversion_rms_mm": self.conversion_rms_m * 1e3,
            "validation": None if self.validation is None else self.validation.to_dict(),
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


def _fit_circle(joint: int, p: Array, t: Array, t_home: float) -> CircleFit:
    """Plane + circle fit of points ``p`` (n, 3) swept by chain angles ``t`` (n,)."""
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
    return CircleFit(joint=joint, centre=centre2, direction=n, radius=float(r),
                     rms_m=float(np.sqrt(np.mean(dist**2))), max_m=float(dist.max()),
                     home_point=home_point, n=len(p))


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
            baseline: CalibratedModel | None = None, n_convert: int = 2000, seed: int = 0
            ) -> CPAResult:
    """Circle Point Analysis from single-joint sweeps.

    Parameters
    ----------
    robot
        Robot description or name.
    sweeps
        One ``(joint index (0-based), MeasurementSet)`` per joint: poses where only that
        joint's chain angle changes; each sweep may hold the other joints at its own home.
    validation
        Poses to evaluate the CPA model on.
    baseline
        The nominal-with-base-and-reflector-fitted model of a fit on the same cell
        (``FitResult.baseline``), for the "% described" figures.
    n_convert
        Random configurations used to convert the POE model into the constant error model.

    Returns
    -------
    CPAResult
        ``calibrated`` is a constant-model :class:`CalibratedModel` with ``kind="cpa"``.

    Raises
    ------
    DataError
        Missing or degenerate sweeps, or poses that move more than one chain angle.
    """
    with blas_threads(1):
        return _cpa_fit(robot, sweeps, validation, baseline, n_convert, seed)


def _cpa_fit(robot: RobotDescription | str, sweeps: Sequence[tuple[int, MeasurementSet]],
             validation: MeasurementSet | None, baseline: CalibratedModel | None,
             n_convert: int, seed: int) -> CPAResult:
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
    raw: list[CircleFit] = []
    for j in range(rob.dof):
        ds = by_joint[j]
        th = ds.q @ C.T + off
        cf = _fit_circle(j, ds.p, th[:, j], th_home[j])
        raw.append(cf)
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
    # convert POE -> constant error model by a noise-free fit over the joint ranges
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
    notes = []
    if conv > 1e-6:
        notes.append(f"POE -> constant-model conversion residual {conv * 1e3:.4f} mm")
    cal = CalibratedModel(model=model, params=info.x, covariance=None,
                          coverage=lim.copy(), kind="cpa")
    cal.fit = {"model": "cpa", "method": "plane + circle fit per joint sweep, POE model, "
               "converted to the constant error model",
               "circles": [c.to_dict() for c in circles],
               "home_q_deg": np.degrees(home_q).tolist(),
               "conversion_rms_mm": conv * 1e3}
    cal.data = {"n_poses": int(sum(len(ds) for ds in by_joint.values())),
                "digest": [by_joint[j].digest() for j in range(rob.dof)]}
    val = None
    if validation is not None:
        val = accuracy(cal, validation, baseline=baseline)
        cal.metrics = {"validation": val.to_dict()}
    cal.model_id = cal.compute_id()
    return CPAResult(calibrated=cal, circles=circles, home_q=home_q, home_point=home_point,
                     conversion_rms_m=conv, validation=val, notes=notes)
