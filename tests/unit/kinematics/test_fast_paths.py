"""The fast evaluation paths agree with the full ones: distinct harmonics evaluated once and
combined by matrix products, and the joint-only Jacobian against the all-columns chain."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from robocal.kinematics import ErrorModelSpec, KinematicModel, load_robot
from robocal.kinematics._basis import basis_plan, evaluate_basis
from robocal.kinematics._spec import COMPONENTS, Term


def _rich_spec(dof: int) -> ErrorModelSpec:
    """Every family the fast path splits: const, poly, harmonics, strain wave, map, gravity."""
    terms = []
    for j in range(dof):
        for c in COMPONENTS:
            terms.append(Term(j, c, "const"))
            terms += [Term(j, c, "cos", k) for k in (1, 2, 7)]
            terms += [Term(j, c, "sin", k) for k in (1, 2, 7)]
        terms += [Term(j, "ez", "poly", 1), Term(j, "ez", "swcos", 1),
                  Term(j, "ez", "swsin", 2), Term(j, "ez", "gravity")]
    terms += [Term(1, "ez", "map", r) for r in range(12)]
    # a second map with knots missing (the data left a gap), listed out of order
    terms += [Term(3, "ez", "map", r) for r in (17, 2, 3, 9, 10, 11, 12, 30, 31)]
    knots = tuple({1: 12, 3: 36}.get(j, 0) for j in range(dof))
    return ErrorModelSpec(dof, tuple(terms), knots)


def _old_basis(spec: ErrorModelSpec, robot, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference: one cosine or sine per column, as the basis was evaluated before."""
    B = np.zeros((len(q), len(spec.terms)))
    dB = np.zeros_like(B)
    for k, t in enumerate(spec.terms):
        if t.family in ("cos", "sin", "swcos", "swsin"):
            f = t.index * ((robot.joints[t.joint].gear_ratio or 0.0)
                           if t.family.startswith("sw") else 1.0)
            a = f * q[:, t.joint]
            B[:, k] = np.cos(a) if t.family.endswith("cos") else np.sin(a)
            dB[:, k] = -f * np.sin(a) if t.family.endswith("cos") else f * np.cos(a)
    return B, dB


@pytest.fixture
def robot():
    r = load_robot("fanuc_lrmate200i")
    joints = tuple(dataclasses.replace(j, gear_ratio=100.0 + i, mass=2.0, com=(0.01, 0.0, 0.02))
                   for i, j in enumerate(r.joints))
    return dataclasses.replace(r, joints=joints)


def test_harmonics_once_match_one_per_column(robot, rng: np.random.Generator) -> None:
    spec = _rich_spec(robot.dof)
    plan = basis_plan(spec, robot)
    assert plan.freq.size == robot.dof * 3 + robot.dof * 2       # 1, 2, 7 and two sw per joint
    q = rng.uniform(-2.5, 2.5, (50, robot.dof))
    B, dB = evaluate_basis(spec, robot, q, derivative=True)
    Bh, dBh = _old_basis(spec, robot, q)
    h = plan.h_terms
    assert np.array_equal(B[:, h], Bh[:, h]) and np.allclose(dB[:, h], dBh[:, h], rtol=1e-14)


def test_error_components_and_joint_jacobian_match_the_full_chain(
        robot, rng: np.random.Generator) -> None:
    spec = _rich_spec(robot.dof)
    model = KinematicModel(robot, spec)
    x = model.nominal_params() + rng.normal(0, 1e-4, model.size)
    q = rng.uniform(-2.5, 2.5, (40, robot.dof))
    E_ref, dE_ref, _ = model.joint_errors(q, x, derivative=True)   # via B, one column a term
    E, dE = model._errors(q, x, derivative=True)
    assert dE is not None and dE_ref is not None
    assert np.abs(E - E_ref).max() < 1e-15 and np.abs(dE - dE_ref).max() < 1e-12
    # joint Jacobian from the chain with every error-component column
    st = model.state(q, x)
    C = robot.coupling_matrix
    J_ref = np.concatenate([st.jlin @ C, st.jang @ C], axis=1)
    for i in range(robot.dof):
        sl = slice(6 + 6 * i, 12 + 6 * i)
        J_ref[:, :3, i] += np.einsum("nkc,nc->nk", st.lin[:, :, sl], dE_ref[:, i])
        J_ref[:, 3:, i] += np.einsum("nkc,nc->nk", st.ang[:, :, sl], dE_ref[:, i])
    p, R, J = model.joint_jacobian(q, x)
    assert np.abs(p - st.p).max() < 1e-15 and np.abs(R - st.R).max() < 1e-15
    assert np.abs(J - J_ref).max() < 1e-14
    # a nominal model (no terms) and one with constant terms only take the same path
    for sp in (ErrorModelSpec(robot.dof, ()),
               ErrorModelSpec(robot.dof, tuple(t for t in spec.terms if t.family == "const"))):
        m = KinematicModel(robot, sp)
        xs = m.nominal_params() + rng.normal(0, 1e-4, m.size)
        st = m.state(q, xs)
        _, _, J = m.joint_jacobian(q, xs)
        assert np.abs(J - np.concatenate([st.jlin @ C, st.jang @ C], axis=1)).max() < 1e-14
