"""Rotation vectors (UR poses): to and from rotation matrices, including angles near pi."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from robocal.kinematics import matrix_to_rotvec, rotvec_to_matrix

unit = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(
    lambda v: np.linalg.norm(v) > 1e-3)


@given(unit, st.floats(0.0, np.pi))
def test_round_trip_up_to_pi(axis, angle):
    v = np.asarray(axis) / np.linalg.norm(axis) * angle
    R = rotvec_to_matrix(v)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0.0
    back = matrix_to_rotvec(R)
    if angle < np.pi - 1e-6:
        np.testing.assert_allclose(back, v, atol=1e-9)
    else:                                     # at pi, v and -v are the same rotation
        np.testing.assert_allclose(rotvec_to_matrix(back), R, atol=1e-9)
        assert abs(np.linalg.norm(back) - np.pi) < 1e-6


def test_a_stack_of_matrices_and_the_rotation_about_z():
    vs = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [0.3, -0.2, 0.1], [np.pi, 0.0, 0.0]])
    Rs = np.stack([rotvec_to_matrix(v) for v in vs])
    np.testing.assert_allclose(matrix_to_rotvec(Rs)[:3], vs[:3], atol=1e-12)
    c, s = np.cos(0.5), np.sin(0.5)
    np.testing.assert_allclose(Rs[1], [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(np.abs(matrix_to_rotvec(Rs[3])), [np.pi, 0.0, 0.0], atol=1e-9)
