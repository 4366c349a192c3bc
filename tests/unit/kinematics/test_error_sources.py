"""Every error source of the paper maps onto the generalised model.

For each source a reference chain is built with the source's own formula (4x4 matrices, per
pose); the model with the matching terms is then fitted to it by Gauss-Newton and must
reproduce it to numerical precision.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from robocal.kinematics import ErrorModelSpec, KinematicModel, Term, load_robot

from .reference import chain, rx, ry, tr

ROBOT = load_robot("fanuc_lrmate200i")
J = 2  # the joint that carries the error (0-based: joint 3, coupled to joint 2)


def _fit_terms(terms: list[Term], target: Callable[[np.ndarray], np.ndarray],
               rng: np.random.Generator, n: int = 120) -> float:
    """Fit the given terms (base/tool fixed) to ``target`` positions; return max residual (m)."""
    return _fit_terms_spec(ErrorModelSpec(ROBOT.dof, tuple(terms)), target, rng, n)


def _at(fn: object, joint: int = J) -> list:
    out: list = [None] * ROBOT.dof
    out[joint] = fn
    return out


def _ref(**kw) -> Callable[[np.ndarray], np.ndarray]:  # type: ignore[no-untyped-def]
    tool = np.asarray(ROBOT.tool)
    return lambda q: chain(ROBOT, q, tool=tool, **kw)[0]


def const_terms(*comps: str, joint: int = J) -> list[Term]:
    return [Term(joint, c, "const") for c in comps]


def harmonic_terms(comps: tuple[str, ...], k: int = 1, joint: int = J) -> list[Term]:
    return [Term(joint, c, f, k) for c in comps for f in ("cos", "sin")]


def test_mastering_error(rng: np.random.Generator) -> None:
    dq = 1.3e-3
    ref = _ref(angle=_at(lambda th, q: th + dq))
    assert _fit_terms(const_terms("ez"), ref, rng) < 1e-12


def test_link_length_and_assembly_error(rng: np.random.Generator) -> None:
    d = ROBOT.joints[J]
    da, dd, dalpha, dth = 4e-4, -3e-4, 7e-4, 2e-4

    # E_LA post-multiplied: (T_dh)^-1 Tz(d+dd) Tx(a+da) Rx(alpha+dalpha), and a theta error
    def post(_q: float) -> np.ndarray:
        nominal = tr(z=d.d) @ tr(x=d.a) @ rx(d.alpha)
        actual = tr(z=d.d + dd) @ tr(x=d.a + da) @ rx(d.alpha + dalpha)
        return np.linalg.inv(nominal) @ actual

    ref = _ref(post=_at(post), angle=_at(lambda th, q: th + dth))
    assert _fit_terms(const_terms("dx", "dy", "dz", "ex", "ey", "ez"), ref, rng) < 1e-12


def test_rotating_centre_offset_is_first_harmonic(rng: np.random.Generator) -> None:
    # E_RC pre-multiplied: a constant translation before the joint rotation becomes
    # cos/sin(q) terms of the in-plane translation after it (a trigonometric identity).
    # The identity needs the chain angle to be the joint value: joint 1 (sign +1, uncoupled).
    off = np.array([3e-4, -2e-4, 1e-4])
    ref = _ref(pre=_at(lambda q: tr(*off), 0))
    terms = const_terms("dz", joint=0) + harmonic_terms(("dx", "dy"), joint=0)
    assert _fit_terms(terms, ref, rng) < 1e-12


def test_pitch_error_is_linear_in_q(rng: np.random.Generator) -> None:
    r = 1.0 + 2e-4  # correcting ratio: Rz(r q) on a sign +1, uncoupled joint (joint 4 is -1)
    ref = _ref(angle=_at(lambda th, q: th + (r - 1.0) * q, 0))
    terms = [*const_terms("ez", joint=0), Term(0, "ez", "poly", 1)]
    assert _fit_terms(terms, ref, rng) < 1e-12


@pytest.mark.parametrize("m", [1, 2])
def test_strain_wave_ripple(m: int, rng: np.random.Generator) -> None:
    N = ROBOT.joints[J].gear_ratio
    assert N
    A, B = 3e-5, -2e-5
    sign = ROBOT.joints[J].sign
    ref = _ref(angle=_at(
        lambda th, q: th + sign * (A * np.cos(m * N * q) + B * np.sin(m * N * q))))
    terms = [Term(J, "ez", "swcos", m), Term(J, "ez", "swsin", m)]
    assert _fit_terms(terms, ref, rng) < 1e-12


def test_bearing_wobble_and_runout(rng: np.random.Generator) -> None:
    beta, rr = 8e-5, 5e-5

    # tilt and radial runout once per revolution, in the joint's moving frame
    def post(q: float) -> np.ndarray:
        return tr(rr * np.cos(q), rr * np.sin(q), 0.0) @ rx(beta * np.cos(q)) @ ry(
            -beta * np.sin(q))

    def insert(q_all: np.ndarray) -> np.ndarray:
        theta = ROBOT.coupling_matrix @ q_all + np.array([j.theta_offset for j in ROBOT.joints])
        from .reference import rz

        T = np.eye(4)
        for i, jt in enumerate(ROBOT.joints):
            A = rz(theta[i])
            if i == J:
                A = A @ post(q_all[i])  # right after the joint rotation
            T = T @ A @ tr(z=jt.d) @ tr(x=jt.a) @ rx(jt.alpha)
        return (T @ np.array([*ROBOT.tool, 1.0]))[:3]

    terms = harmonic_terms(("dx", "dy", "ex", "ey"))
    # Rx(a)Ry(b) with small angles is matched to first order by the (ex, ey) components;
    # second-order terms (a b ~ 1e-8 rad) remain, so the tolerance is a few nanometres.
    assert _fit_terms(terms, insert, rng) < 5e-9


def test_joint_angle_map_represents_fine_periodic_error(rng: np.random.Generator) -> None:
    # a 17-cycles-per-revolution angle error is captured by a spline map with 2-degree knots
    amp = 4e-4
    ref = _ref(angle=_at(lambda th, q: th + amp * np.sin(17 * q + 0.3), 0))
    spec = ErrorModelSpec.build(ROBOT.dof, constant=False, map_spacing_deg=[2.0] + [None] * 5)
    assert len(spec.terms) == 180
    assert _fit_terms_spec(spec, ref, rng) < 3e-6  # of a 0.4 mrad x ~0.8 m = 0.3 mm effect


def _fit_terms_spec(spec: ErrorModelSpec, target, rng, n: int = 400) -> float:  # type: ignore[no-untyped-def]
    m = KinematicModel(ROBOT, spec)
    x = m.nominal_params()
    lim = ROBOT.joint_limits
    q = rng.uniform(lim[:, 0], lim[:, 1], (n, ROBOT.dof))
    y = np.array([target(qi) for qi in q])
    for _ in range(5):
        p, Jac = m.jacobian(q, x)
        A = Jac[:, :, 9:].reshape(-1, len(spec))
        x[9:] += np.linalg.lstsq(A, (y - p).ravel(), rcond=1e-10)[0]
    return float(np.abs(m.positions(q, x) - y).max())


def test_gravity_torsion(rng: np.random.Generator) -> None:
    from robocal.kinematics import gravity_torques

    robot = load_robot("ur10")
    k = 2e-6  # rad / (N m)
    spec = ErrorModelSpec(robot.dof, (Term(1, "ez", "gravity"),))
    m = KinematicModel(robot, spec)
    x = m.nominal_params()
    x[9] = k
    q = rng.uniform(-np.pi, np.pi, (30, 6))
    tau = gravity_torques(robot, q)
    # a static check of the torque model: joint 2 at shoulder-lift 0 (arm horizontal) carries
    # the full moment of links 2-6 about its axis
    q0 = np.zeros((1, 6))
    t0 = gravity_torques(robot, q0)[0, 1]
    assert 60.0 < abs(t0) < 200.0
    # the model equals the nominal chain with joint 2 turned by k * tau
    for i in range(len(q)):
        ang = [None] * 6
        ang[1] = lambda th, qq, i=i: th + k * tau[i, 1]
        pr, _ = chain(robot, q[i], angle=ang, tool=robot.tool)
        np.testing.assert_allclose(m.positions(q[i:i + 1], x)[0], pr, atol=1e-12)
