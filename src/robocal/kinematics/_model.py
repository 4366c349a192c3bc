"""Forward kinematics of the error model and its analytic Jacobians, vectorised over poses.

Chain, for joint values ``q`` (n, dof) and parameters ``x``::

    T_tracker_flange = T_ref · E_base(x_base) · T_root_dh0
                       · Π_i [ Rz(theta_i) · E_i(q_i) · Tz(d_i) Tx(a_i) Rx(alpha_i) ]
                       · T_dhn_flange
    p_tracker_smr    = T_tracker_flange · x_tool

with ``E(dx, dy, dz, ex, ey, ez) = Tx(dx) Ty(dy) Tz(dz) Rx(ex) Ry(ey) Rz(ez)``. Derivatives are
exact: a translation component moves the point along an axis of the frame it acts in; a
rotation component turns it about an axis through the translated origin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal.errors import ConfigError
from robocal.kinematics._basis import (
    BasisPlan,
    ComponentWeights,
    basis_plan,
    component_columns,
    component_weights,
    error_components,
    evaluate_basis,
)
from robocal.kinematics._robot import RobotDescription
from robocal.kinematics._spec import ErrorModelSpec, ParameterLayout

Array = NDArray[np.float64]
_OFF = ParameterLayout.OFFSET


@dataclass(frozen=True)
class ChainState:
    """Everything one forward pass produces (n poses, dof joints).

    ``p``: reflector positions (n, 3) m, tracker frame. ``R``, ``o``: flange rotation (n, 3, 3)
    and origin (n, 3). ``lin``/``ang``: per error component (base first, then joint by joint,
    six each) the linear velocity of the reflector and the angular velocity of the flange per
    unit of that component, shapes (n, 3, 6 (dof + 1)). ``jlin``/``jang``: the same per unit
    of chain angle theta_i, (n, 3, dof).
    """

    p: Array
    R: Array
    o: Array
    lin: Array
    ang: Array
    jlin: Array
    jang: Array


def _cross_axis1(a: Array, b: Array) -> Array:
    """Cross products of 3-vectors along axis 1: ``a``, ``b`` (n, 3, m) -> (n, 3, m)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _cols_rot(R: Array, i: int, j: int, c: Array, s: Array) -> None:
    """In place: columns (i, j) of R <- (c Ri + s Rj, -s Ri + c Rj), a rotation about k."""
    ri = R[:, :, i].copy()
    rj = R[:, :, j]
    R[:, :, i] = c[:, None] * ri + s[:, None] * rj
    R[:, :, j] = -s[:, None] * ri + c[:, None] * rj


def _apply_error(R: Array, o: Array, e: Array, lin_cols: list[Array], ang_cols: list[Array],
                 pivots: list[Array]) -> tuple[Array, Array]:
    """Apply E(e) (e: (n, 6)) to frame (R, o); record axes for the Jacobian."""
    n = R.shape[0]
    o_E = o + np.einsum("nij,nj->ni", R, e[:, :3])
    zeros = np.zeros((n, 3))
    for k in range(3):
        lin_cols.append(R[:, :, k].copy())
        ang_cols.append(zeros)
        pivots.append(None)  # type: ignore[arg-type]
    R = R.copy()
    ax_x = R[:, :, 0].copy()
    _cols_rot(R, 1, 2, np.cos(e[:, 3]), np.sin(e[:, 3]))       # Rx(ex)
    ax_y = R[:, :, 1].copy()
    _cols_rot(R, 2, 0, np.cos(e[:, 4]), np.sin(e[:, 4]))       # Ry(ey)
    ax_z = R[:, :, 2].copy()
    _cols_rot(R, 0, 1, np.cos(e[:, 5]), np.sin(e[:, 5]))       # Rz(ez)
    for ax in (ax_x, ax_y, ax_z):
        lin_cols.append(ax)
        ang_cols.append(ax)
        pivots.append(o_E)
    return R, o_E


class KinematicModel:
    """A robot's error model: forward kinematics and analytic Jacobians for N poses at once.

    Parameters
    ----------
    robot
        Nominal description.
    spec
        Which joint error terms the model has.
    T_ref
        Reference pose of the robot base in the tracker frame (4, 4), m. The base parameters
        are a small correction applied after it.
    """

    def __init__(self, robot: RobotDescription, spec: ErrorModelSpec,
                 T_ref: Array | None = None) -> None:
        if spec.dof != robot.dof:
            raise ConfigError(f"error model has {spec.dof} joints, robot {robot.name!r} has "
                              f"{robot.dof}")
        self.robot = robot
        self.spec = spec
        self.layout = ParameterLayout(spec)
        self.T_ref = np.eye(4) if T_ref is None else np.asarray(T_ref, dtype=float).copy()
        self._cols = component_columns(spec)
        self._plan = basis_plan(spec, robot)
        self._is_map = np.array([t.family == "map" for t in spec.terms], dtype=bool)
        # basis plans of term subsets (basis()), by the subset's index bytes
        self._sub_plans: dict[bytes, tuple[ErrorModelSpec, BasisPlan]] = {}
        # what the last parameter vector fixes, arranged for the passes (_Prepared)
        self._prepared: _Prepared | None = None
        # joints whose error components are constants: their errors and DH transform fold
        # into one fixed transform per parameter vector
        self._const_joints = frozenset(
            range(robot.dof)) - frozenset(t.joint for t in spec.terms if t.family != "const")
        # joints with a joint-dependent error term (the others add nothing to dE/dq)
        self._dep_joints = frozenset(t.joint for t in spec.terms
                                     if t.family not in ("const", "gravity"))
        self._theta_off = np.array([j.theta_offset for j in robot.joints])
        self._C = robot.coupling_matrix
        self._coupled = not np.array_equal(self._C, np.eye(robot.dof))
        self._dh = [(j.d, j.a, math.cos(j.alpha), math.sin(j.alpha)) for j in robot.joints]
        # fixed robot root -> DH frame 0 and DH frame n -> flange transforms (None: identity)
        self._T_base = robot.T_root_dh0 if robot.has_base else None
        self._T_flange = robot.T_dhn_flange if robot.has_flange else None

    # -- parameters -----------------------------------------------------------------------
    @property
    def size(self) -> int:
        """Number of parameters."""
        return self.layout.size

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names."""
        return self.layout.names

    def nominal_params(self) -> Array:
        """Parameter vector of the nominal robot: zero errors, the robot file's tool offset."""
        x = np.zeros(self.size)
        x[ParameterLayout.TOOL] = self.robot.tool
        return x

    def with_spec(self, spec: ErrorModelSpec) -> KinematicModel:
        """Return a model of the same robot and reference with another spec."""
        return KinematicModel(self.robot, spec, self.T_ref)

    def transfer(self, x: Array, other: KinematicModel) -> Array:
        """Map parameters ``x`` of this model onto ``other`` by name (missing names -> 0)."""
        out = other.nominal_params()
        idx = {n: i for i, n in enumerate(self.names)}
        for j, name in enumerate(other.names):
            if name in idx:
                out[j] = x[idx[name]]
        return out

    # -- evaluation -------------------------------------------------------------------------
    def _check(self, q: Array, x: Array) -> tuple[Array, Array]:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        x = np.asarray(x, dtype=float)
        if q.shape[1] != self.robot.dof:
            raise ConfigError(f"joint array has {q.shape[1]} columns, robot has "
                              f"{self.robot.dof} joints")
        if x.shape != (self.size,):
            raise ConfigError(f"parameter vector has shape {x.shape}, model needs ({self.size},)")
        return q, x

    def joint_errors(self, q: Array, x: Array, *, derivative: bool = False
                     ) -> tuple[Array, Array | None, Array]:
        """Error component values E (n, dof, 6), optional dE/dq_i (n, dof, 6), and basis B."""
        q, x = self._check(q, x)
        n, dof = q.shape
        B, dB = evaluate_basis(self.spec, self.robot, q, derivative=derivative,
                               plan=self._plan)
        coef = x[_OFF:]
        E = np.zeros((n, dof * 6))
        if coef.size:
            # scatter-add term contributions into their component columns
            contrib = B * coef
            E = _scatter_columns(contrib, self._cols, dof * 6)
        dE = None
        if dB is not None:
            dE = (_scatter_columns(dB * coef, self._cols, dof * 6) if coef.size
                  else np.zeros((n, dof * 6))).reshape(n, dof, 6)
        return E.reshape(n, dof, 6), dE, B

    def _errors_t(self, q: Array, x: Array, *, derivative: bool = False
                  ) -> tuple[Array, Array | None]:
        """E and optionally dE/dq_i as (6 dof, n) rows, without the basis matrix."""
        return error_components(self._plan, self.robot, q, self._prepare(x).weights,
                                derivative=derivative)

    def _prepare(self, x: Array) -> _Prepared:
        """What ``x`` fixes for the passes, computed once per parameter vector."""
        key = x.tobytes()
        prep = self._prepared
        if prep is not None and prep.key == key:
            return prep
        w = component_weights(self._plan, x[_OFF:], self._cols, self.robot.dof)
        R = self.T_ref[:3, :3, None].copy()
        o = self.T_ref[:3, 3, None].copy()
        _soa_error(R, o, x[ParameterLayout.BASE][:, None])
        if self._T_base is not None:
            R, o = _soa_fixed(R, o, self._T_base)
        fixed = {}
        for i in self._const_joints:
            Ri, oi = np.eye(3)[:, :, None], np.zeros((3, 1))
            _soa_error(Ri, oi, w.e0[6 * i:6 * i + 6, None])
            d, a, ca, sa = self._dh[i]
            oi += d * Ri[:, 2] + a * Ri[:, 0]
            _soa_rot(Ri, 1, 2, ca, sa)
            fixed[i] = (np.ascontiguousarray(Ri[:, :, 0].T), oi)
        prep = _Prepared(key=key, weights=w, R0=R[:, :, 0].copy(), o0=o[:, 0].copy(),
                         fixed=fixed)
        self._prepared = prep
        return prep

    def _errors(self, q: Array, x: Array, *, derivative: bool = False
                ) -> tuple[Array, Array | None]:
        """E (n, dof, 6) and optionally dE/dq_i (n, dof, 6), without the basis matrix."""
        n, dof = q.shape
        E, dE = self._errors_t(q, x, derivative=derivative)
        return E.T.reshape(n, dof, 6), None if dE is None else dE.T.reshape(n, dof, 6)

    def _chain(self, q: Array, x: Array, E: Array) -> ChainState:
        n, dof = q.shape
        theta = q @ self._C.T + self._theta_off
        R0 = np.broadcast_to(self.T_ref[:3, :3], (n, 3, 3)).copy()
        o0 = np.broadcast_to(self.T_ref[:3, 3], (n, 3)).copy()
        lin_cols: list[Array] = []
        ang_cols: list[Array] = []
        pivots: list[Array] = []
        R, o = _apply_error(R0, o0, np.broadcast_to(x[ParameterLayout.BASE], (n, 6)), lin_cols,
                            ang_cols, pivots)
        R, o = _fixed(R, o, self._T_base)
        jaxes = []
        jorig = []
        for i in range(dof):
            jaxes.append(R[:, :, 2].copy())
            jorig.append(o)
            R = R.copy()
            _cols_rot(R, 0, 1, np.cos(theta[:, i]), np.sin(theta[:, i]))
            R, o = _apply_error(R, o, E[:, i, :], lin_cols, ang_cols, pivots)
            d, a, ca, sa = self._dh[i]
            o = o + d * R[:, :, 2] + a * R[:, :, 0]
            _cols_rot(R, 1, 2, np.full(n, ca), np.full(n, sa))
        R, o = _fixed(R, o, self._T_flange)
        p = o + R @ x[ParameterLayout.TOOL]
        lin = np.stack(lin_cols, axis=2)
        ang = np.stack(ang_cols, axis=2)
        ks = [k for k, piv in enumerate(pivots) if piv is not None]
        if ks:
            # all rotation columns at once: one cross product per pose and column, not a
            # numpy call per column (there are 3 per error term)
            levers = np.stack([np.broadcast_to(p - pivots[k], p.shape) for k in ks], axis=2)
            lin[:, :, ks] = _cross_axis1(lin[:, :, ks], levers)
        jang = np.stack(jaxes, axis=2)
        lever = p[:, None, :] - np.stack(jorig, axis=1)  # (n, dof, 3)
        jlin = _cross_axis1(jang, lever.transpose(0, 2, 1))
        return ChainState(p=p, R=R, o=o, lin=lin, ang=ang, jlin=jlin, jang=jang)

    def positions(self, q: Array, x: Array) -> Array:
        """Reflector positions (n, 3) m in the tracker frame for joint values ``q`` (n, dof)."""
        q, x = self._check(q, x)
        E, _ = self._errors_t(q, x)
        return self._fk_fast(q, x, E)[0]

    def flange_poses(self, q: Array, x: Array) -> tuple[Array, Array, Array]:
        """Return reflector positions (n, 3), flange rotations (n, 3, 3) and origins (n, 3)."""
        q, x = self._check(q, x)
        E, _ = self._errors_t(q, x)
        return self._fk_fast(q, x, E)

    def _fk_fast(self, q: Array, x: Array, E: Array) -> tuple[Array, Array, Array]:
        R, o, _ = self._soa_pass(q, x, E, None)
        p = o + _soa_apply(R, x[ParameterLayout.TOOL])
        return p.T.copy(), np.ascontiguousarray(R.transpose(2, 0, 1)), o.T.copy()

    def _soa_pass(self, q: Array, x: Array, E: Array, dE: Array | None
                  ) -> tuple[Array, Array, list[tuple[int, Array, Array, Array, Array]]]:
        """Forward pass in structure-of-arrays layout: R (3, 3, n) (R[:, k] is column k of
        every pose's rotation, contiguous rows), origin (3, n); error components ``E`` as
        (6 dof, n) rows.

        With ``dE`` (6 dof, n) it also records, per joint i: its axis and origin before
        the joint, and (for joints with joint-dependent errors) the velocity v and angular
        velocity w (3, n) its error components give per unit of q_i and their pivot.
        """
        n, dof = q.shape
        theta = (q @ self._C.T + self._theta_off).T            # (dof, n)
        Et, dEt = E, dE                                         # (6 dof, n) rows
        prep = self._prepare(x)
        R = np.repeat(prep.R0[:, :, None], n, axis=2)
        o = np.repeat(prep.o0[:, None], n, axis=1)
        rec: list[tuple[int, Array, Array, Array, Array]] = []
        # every cosine and sine of the pass in two calls each (one per joint costs more
        # than the arithmetic on small batches)
        ct, st = np.cos(theta), np.sin(theta)
        varying = [i for i in range(dof) if i not in prep.fixed]
        ang = Et.reshape(dof, 6, n)[varying, 3:]
        ce, se = np.cos(ang), np.sin(ang)
        jac = dEt is not None
        for i in range(dof):
            z_i, o_i = (R[:, 2].copy(), o.copy()) if jac else (R[:, 2], o)
            _soa_rot(R, 0, 1, ct[i], st[i])
            e = Et[6 * i:6 * i + 6]
            if i in prep.fixed:
                # constant errors and the DH transform as one: R <- R M, o <- o + R t
                Mt, t = prep.fixed[i]
                o += _soa_apply(R, t)
                R = np.matmul(Mt, R)
                if dEt is not None:
                    rec.append((i, z_i, o_i, np.empty((0, n)), o))
                continue
            k = varying.index(i)
            if dEt is not None and i in self._dep_joints:
                de = dEt[6 * i:6 * i + 6]
                v = _soa_apply(R, de[:3])
                w = _soa_error(R, o, e, de, (ce[k], se[k]))
                rec.append((i, z_i, o_i, np.concatenate([v, w]), o.copy()))
            else:
                _soa_error(R, o, e, cs=(ce[k], se[k]))
                if dEt is not None:
                    rec.append((i, z_i, o_i, np.empty((0, n)), o))
            d, a, ca, sa = self._dh[i]
            if d != 0.0 and a != 0.0:
                o += d * R[:, 2] + a * R[:, 0]
            elif d != 0.0:
                o += d * R[:, 2]
            elif a != 0.0:
                o += a * R[:, 0]
            if sa != 0.0 or ca != 1.0:
                _soa_rot(R, 1, 2, ca, sa)
        if self._T_flange is not None:
            R, o = _soa_fixed(R, o, self._T_flange)
        return R, o, rec

    def jacobian(self, q: Array, x: Array) -> tuple[Array, Array]:
        """Reflector positions (n, 3) and d position / d parameters (n, 3, n_params)."""
        q, x = self._check(q, x)
        E, _, B = self.joint_errors(q, x)
        st = self._chain(q, x, E)
        n = q.shape[0]
        J = np.empty((n, 3, self.size))
        J[:, :, :6] = st.lin[:, :, :6]
        J[:, :, 6:9] = st.R
        if B.shape[1]:
            # np.take: a fancy index on the last axis gathers element by element, ~4x
            # slower at the ~1,600 columns of the auto superset
            np.multiply(np.take(st.lin, 6 + self._cols, axis=2), B[:, None, :],
                        out=J[:, :, _OFF:])
        return st.p, J

    def basis(self, q: Array, terms: NDArray[np.intp] | None = None) -> Array:
        """Basis values (n, len(terms)) of the terms ``terms`` (indices into the spec's
        terms; None: all) at joint values ``q`` (n, dof) rad."""
        if terms is None:
            return evaluate_basis(self.spec, self.robot, q, plan=self._plan)[0]
        key = np.asarray(terms, dtype=np.intp).tobytes()
        sub = self._sub_plans.get(key)
        if sub is None:
            spec = ErrorModelSpec(self.spec.dof, tuple(self.spec.terms[int(t)] for t in terms),
                                  self.spec.map_knots, label=self.spec.label)
            sub = self._sub_plans[key] = (spec, basis_plan(spec, self.robot))
        return evaluate_basis(sub[0], self.robot, q, plan=sub[1])[0]

    @property
    def term_is_map(self) -> NDArray[np.bool_]:
        """Per term: is it a joint-angle map knot (n_terms,)."""
        return self._is_map.copy()

    @property
    def term_components(self) -> NDArray[np.intp]:
        """Error component column (joint * 6 + component) of each term, shape (n_terms,)."""
        return self._cols.copy()

    def jacobian_factors(self, q: Array, x: Array, *, orientation: bool = False,
                         terms: NDArray[np.intp] | None = None
                         ) -> tuple[Array, Array, Array, Array, Array]:
        """The Jacobian in factored form: positions (n, 3), flange rotations (n, 3, 3), the
        columns of the base and tool parameters ``head`` (n, m, 9), the sensitivity to each
        error component ``sens`` (n, m, 6 dof) and the basis ``B`` (n, len(terms)) of the
        terms ``terms`` (indices into the spec's terms; None: all).

        Column ``9 + t`` of :meth:`jacobian` (m = 3) or :meth:`pose_jacobian` (m = 6,
        ``orientation``) is ``sens[:, :, term_components[t]] * B[:, None, i]`` for
        ``t = terms[i]``: a caller that knows which basis columns are sparse (joint-angle map
        knots, four per pose) asks for the others only and forms normal matrices without
        the dense map columns.
        """
        q, x = self._check(q, x)
        E, _ = self._errors(q, x)
        B = self.basis(q, terms)
        st = self._chain(q, x, E)
        n = q.shape[0]
        m = 6 if orientation else 3
        head = np.zeros((n, m, _OFF))
        head[:, :3, :6] = st.lin[:, :, :6]
        head[:, :3, 6:9] = st.R
        if orientation:
            head[:, 3:, :6] = st.ang[:, :, :6]
            sens = np.concatenate([st.lin[:, :, 6:], st.ang[:, :, 6:]], axis=1)
        else:
            sens = st.lin[:, :, 6:]
        return st.p, st.R, head, sens, B

    def pose_jacobian(self, q: Array, x: Array) -> tuple[Array, Array, Array]:
        """Positions (n, 3), flange rotations (n, 3, 3) and d pose / d parameters (n, 6, P).

        Rows 0-2: reflector position (m per unit parameter); rows 3-5: angular velocity of
        the flange frame (rad per unit parameter, tracker frame).
        """
        q, x = self._check(q, x)
        E, _, B = self.joint_errors(q, x)
        st = self._chain(q, x, E)
        n = q.shape[0]
        J = np.zeros((n, 6, self.size))
        J[:, :3, :6] = st.lin[:, :, :6]
        J[:, 3:, :6] = st.ang[:, :, :6]
        J[:, :3, 6:9] = st.R
        if B.shape[1]:
            np.multiply(np.take(st.lin, 6 + self._cols, axis=2), B[:, None, :],
                        out=J[:, :3, _OFF:])
            np.multiply(np.take(st.ang, 6 + self._cols, axis=2), B[:, None, :],
                        out=J[:, 3:, _OFF:])
        return st.p, st.R, J

    def joint_jacobian(self, q: Array, x: Array) -> tuple[Array, Array, Array]:
        """Positions (n, 3), flange rotations (n, 3, 3), and the 6 x dof Jacobian (n, 6, dof).

        Rows 0-2: reflector velocity, rows 3-5: flange angular velocity (tracker frame), per
        unit of joint value (rad), including the joint-dependent error terms and couplings.
        """
        q, x = self._check(q, x)
        E, dE = self._errors_t(q, x, derivative=True)
        assert dE is not None
        return self._joint_chain(q, x, E, dE)

    def _joint_chain(self, q: Array, x: Array, E: Array, dE: Array
                     ) -> tuple[Array, Array, Array]:
        """Positions, flange rotations and the 6 x dof joint Jacobian from one pass that
        records only the joint axes and, per joint with joint-dependent errors, the velocity
        its error components give per unit of the joint value (no column per component)."""
        n, dof = q.shape
        R, o, rec = self._soa_pass(q, x, E, dE)
        p = o + _soa_apply(R, x[ParameterLayout.TOOL])            # (3, n)
        Jt = np.empty((6, dof, n))                                # per theta, then per q
        for i, z_i, o_i, _, _ in rec:
            Jt[3:, i] = z_i
            Jt[:3, i] = _soa_cross(z_i, p - o_i)
        if self._coupled:
            Jt = np.matmul(self._C.T, Jt)                         # J_q = J_theta C
        for i, _, _, vw, piv in rec:
            if vw.size:
                w = vw[3:]
                Jt[:3, i] += vw[:3] + _soa_cross(w, p - piv)
                Jt[3:, i] += w
        return (p.T.copy(), np.ascontiguousarray(R.transpose(2, 0, 1)),
                np.ascontiguousarray(Jt.transpose(2, 0, 1)))

    def state(self, q: Array, x: Array) -> ChainState:
        """Full chain state, for callers that need the component sensitivities."""
        q, x = self._check(q, x)
        E, _ = self._errors(q, x)
        return self._chain(q, x, E)

    def base_transform(self, x: Array) -> Array:
        """T_tracker_base (4, 4) including the base correction in ``x``."""
        R, o = _apply_error_fast(self.T_ref[None, :3, :3].copy(), self.T_ref[None, :3, 3].copy(),
                                 x[None, :6])
        T = np.eye(4)
        T[:3, :3] = R[0]
        T[:3, 3] = o[0]
        return T

    def rebased(self, x: Array) -> tuple[KinematicModel, Array]:
        """Fold the base correction of ``x`` into the reference; return (model, params)."""
        m = KinematicModel(self.robot, self.spec, self.base_transform(x))
        x2 = x.copy()
        x2[ParameterLayout.BASE] = 0.0
        return m, x2


@dataclass(frozen=True)
class _Prepared:
    """What one parameter vector fixes: the error-term weights, the frame before joint 1
    (``R0`` (3, 3), ``o0`` (3,): reference, base errors and root -> DH 0) and, per joint
    with constant errors, ``(M^T, t)``: rotation (3, 3, transposed for ``np.matmul``) and
    translation (3, 1) of its errors and DH transform after the joint rotation."""

    key: bytes
    weights: ComponentWeights
    R0: Array
    o0: Array
    fixed: dict[int, tuple[Array, Array]]


def _scatter_columns(values: Array, cols: NDArray[np.intp], width: int) -> Array:
    """Sum columns of ``values`` (n, T) into ``width`` columns by index ``cols`` (T,)."""
    S = np.zeros((values.shape[1], width))
    S[np.arange(values.shape[1]), cols] = 1.0
    return values @ S


def _fixed(R: Array, o: Array, T: Array | None) -> tuple[Array, Array]:
    """Frame (R (n, 3, 3), o (n, 3)) followed by the fixed transform T (4, 4), if any."""
    if T is None:
        return R, o
    return R @ T[:3, :3], o + R @ T[:3, 3]


def _apply_error_fast(R: Array, o: Array, e: Array) -> tuple[Array, Array]:
    o = o + np.einsum("nij,nj->ni", R, e[:, :3])
    _cols_rot(R, 1, 2, np.cos(e[:, 3]), np.sin(e[:, 3]))
    _cols_rot(R, 2, 0, np.cos(e[:, 4]), np.sin(e[:, 4]))
    _cols_rot(R, 0, 1, np.cos(e[:, 5]), np.sin(e[:, 5]))
    return R, o


# -- structure-of-arrays helpers: R (3, 3, n) with R[:, k] column k, vectors (3, n) ----------
def _soa_rot(R: Array, i: int, j: int, c: Array | float, s: Array | float) -> None:
    """In place: columns (i, j) <- (c Ri + s Rj, -s Ri + c Rj), a rotation about axis k."""
    ri = R[:, i].copy()
    rj = R[:, j]
    Ri = R[:, i]
    Ri *= c
    Ri += s * rj
    rj *= c                 # in place, same values as c rj - s ri
    rj -= s * ri


def _soa_apply(R: Array, v: Array) -> Array:
    """R v for v (3,), (3, 1) or (3, n): (3, n)."""
    return R[:, 0] * v[0] + R[:, 1] * v[1] + R[:, 2] * v[2]


def _soa_cross(a: Array, b: Array) -> Array:
    """Cross products of (3, n) vectors."""
    return np.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def _soa_fixed(R: Array, o: Array, T: Array) -> tuple[Array, Array]:
    """Frame followed by the fixed transform T (4, 4)."""
    Rn = np.einsum("imn,mk->ikn", R, T[:3, :3])
    return Rn, o + _soa_apply(R, T[:3, 3])


def _soa_error(R: Array, o: Array, e: Array, de: Array | None = None,
               cs: tuple[Array, Array] | None = None) -> Array | None:
    """In place: apply E(e) (e (6, n) or (6, 1)) to frame (R, o).

    With ``de`` (6, n): also return the angular velocity (3, n) of the frame per unit of
    the joint value whose error components change by ``de`` (rotation axes as they are when
    each rotation acts). ``cs``: cosines and sines (3, n) of ``e[3:]`` when already known.
    """
    c, s = (np.cos(e[3:]), np.sin(e[3:])) if cs is None else cs
    o += _soa_apply(R, e[:3])
    w = None if de is None else R[:, 0] * de[3]
    _soa_rot(R, 1, 2, c[0], s[0])       # Rx(ex)
    if w is not None and de is not None:
        w += R[:, 1] * de[4]
    _soa_rot(R, 2, 0, c[1], s[1])       # Ry(ey)
    if w is not None and de is not None:
        w += R[:, 2] * de[5]
    _soa_rot(R, 0, 1, c[2], s[2])       # Rz(ez)
    return w
