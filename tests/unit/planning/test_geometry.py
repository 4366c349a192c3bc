"""Link frames, capsule model and the vectorised distance queries against brute force."""

from __future__ import annotations

import numpy as np
import pytest

from robocal.kinematics import ErrorModelSpec, KinematicModel, builtin_robots, load_robot
from robocal.planning import (
    CapsuleModel,
    default_link_radii,
    link_frames,
    segment_box_distance,
    segment_distance,
)
from robocal.planning._geometry import point_box_distance


@pytest.mark.parametrize("name", builtin_robots())
def test_link_frames_match_the_kinematic_model(name: str, rng: np.random.Generator) -> None:
    robot = load_robot(name)
    lim = robot.joint_limits
    q = rng.uniform(lim[:, 0], lim[:, 1], (40, robot.dof))
    model = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
    x = model.nominal_params()
    p, R, o = model.flange_poses(q, x)
    O, Rs, _ = link_frames(robot, q)
    np.testing.assert_allclose(O[:, -1], o, atol=1e-12)
    np.testing.assert_allclose(Rs[:, -1], R, atol=1e-12)
    cm = CapsuleModel(robot, tuple(default_link_radii(robot)), robot.tool, 0.02)
    A, B, _Rf, refl = cm.segments(q)
    np.testing.assert_allclose(refl, p, atol=1e-12)
    # the capsule axes form one connected polyline from the base to the reflector
    np.testing.assert_allclose(A[:, 1:], B[:, :-1], atol=1e-12)
    np.testing.assert_allclose(A[:, 0], 0.0, atol=1e-12)


def test_capsule_model_static_base_and_pairs() -> None:
    robot = load_robot("fanuc_lrmate200i")
    cm = CapsuleModel(robot, (0.05,) * 6, robot.tool, 0.02)
    assert cm.names == ("j1.d", "j1.a", "j2.a", "j3.a", "j4.d", "j6.d", "tool")
    assert cm.static.tolist() == [True] + [False] * 6
    pairs = {(cm.names[a], cm.names[b]) for a, b in cm.pairs}
    # chain neighbours are never checked; nor capsules closer along the chain than their radii
    for k in range(len(cm) - 1):
        assert (cm.names[k], cm.names[k + 1]) not in pairs
    assert ("j2.a", "j4.d") not in pairs  # 75 mm elbow offset < 2 x 50 mm
    assert ("j2.a", "j6.d") in pairs and ("j1.d", "tool") in pairs
    with pytest.raises(Exception, match="link_radii_mm needs 6"):
        CapsuleModel(robot, (0.05,) * 5, robot.tool, 0.02)


def _brute_segments(P1, Q1, P2, Q2, k=201):
    s = np.linspace(0, 1, k)
    X = P1[:, None, None, :] + s[None, :, None, None] * (Q1 - P1)[:, None, None, :]
    Y = P2[:, None, None, :] + s[None, None, :, None] * (Q2 - P2)[:, None, None, :]
    return np.linalg.norm(X - Y, axis=-1).min(axis=(1, 2))


def test_segment_distance_matches_brute_force(rng: np.random.Generator) -> None:
    n = 200
    P1, Q1, P2, Q2 = (rng.normal(size=(n, 3)) for _ in range(4))
    # degenerate and parallel cases
    Q1[:40] = P1[:40]
    Q2[40:80] = P2[40:80]
    Q1[80:100], Q2[80:100] = P1[80:100], P2[80:100]
    shift = np.array([0.3, 0.2, 0.1])
    P2[100:140] = P1[100:140] + shift
    Q2[100:140] = Q1[100:140] + shift
    d, s, t = segment_distance(P1, Q1, P2, Q2)
    brute = _brute_segments(P1, Q1, P2, Q2)
    assert np.all(d <= brute + 1e-12)
    assert np.all(brute - d < 0.03)  # grid resolution of the brute force
    assert np.all((s >= 0) & (s <= 1) & (t >= 0) & (t <= 1))
    c = np.linalg.norm((P1 + s[:, None] * (Q1 - P1)) - (P2 + t[:, None] * (Q2 - P2)), axis=1)
    np.testing.assert_allclose(c, d, atol=1e-12)


def test_segment_box_distance_matches_brute_force(rng: np.random.Generator) -> None:
    n = 200
    P, Q = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    lo = np.array([-0.2, -0.3, -0.1])
    hi = np.array([0.3, 0.2, 0.4])
    d, t = segment_box_distance(P, Q, lo, hi)
    s = np.linspace(0, 1, 2001)
    brute = point_box_distance(P[:, None, :] + s[None, :, None] * (Q - P)[:, None, :], lo,
                               hi).min(axis=1)
    assert np.all(d <= brute + 1e-6) and np.all(brute - d < 2e-3)  # bracket 2e-7 x length
    np.testing.assert_allclose(point_box_distance(P + t[:, None] * (Q - P), lo, hi), d,
                               atol=1e-12)
    assert np.any(d == 0.0)  # some segments cross the box
