"""Motion safety of planned campaigns, judged by an independent swept-path check.

The check here shares no code with the planner: its own DH forward kinematics (4x4 matrices),
links as dense point chains with the documented default radii, fixed fine joint sampling, and
zero clearance (the planner keeps the cell's clearance at every one of its samples, which must
leave the links clear of floor, keep-out boxes and each other everywhere in between).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from robocal.errors import ConfigError
from robocal.kinematics import RobotDescription, load_robot
from robocal.planning import Cell, MotionChecker, Plan, load_cell, plan_campaign

from .helpers import cell_with

Array = NDArray[np.float64]
ROBOTS = ("fanuc_lrmate200i", "fanuc_lrmate200id", "ur10", "kuka_kr210_r3100")


def _dh(theta: Array, d: float, a: float, alpha: float) -> Array:
    """Standard DH link transforms (n, 4, 4) for angles theta (n,)."""
    c, s = np.cos(theta), np.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    T = np.zeros((len(theta), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2], T[:, 0, 3] = c, -s * ca, s * sa, a * c
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2], T[:, 1, 3] = s, c * ca, -c * sa, a * s
    T[:, 2, 1], T[:, 2, 2], T[:, 2, 3] = sa, ca, d
    T[:, 3, 3] = 1.0
    return T


class LinkPoints:
    """Links of a robot as chains of points with a radius each (own model of the arm)."""

    def __init__(self, robot: RobotDescription, cell: Cell, spacing: float = 0.02) -> None:
        self.robot = robot
        reach = sum(abs(j.a) + abs(j.d) for j in robot.joints)
        # the defaults documented in docs/cell-format.md, written out here
        radii = [(0.04 if i < 3 else 0.025) * reach for i in range(robot.dof)]
        radii[-1] = min(radii[-1], 0.6 * math.hypot(*robot.tool))
        if cell.robot.link_radii_mm is not None:
            radii = [r * 1e-3 for r in cell.robot.link_radii_mm]
        self.radii = radii
        self.tool_radius = cell.robot.tool_radius_mm * 1e-3
        self.spacing = spacing

    def points(self, q: Array) -> tuple[Array, Array, Array, Array]:
        """Points (n, P, 3), radius (P,), link number (P,; dof + 1 = tool), static (P,)."""
        rob = self.robot
        theta = q @ rob.coupling_matrix.T + np.array([j.theta_offset for j in rob.joints])
        n = len(q)
        T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
        pts: list[Array] = []
        rad: list[float] = []
        link: list[int] = []
        static: list[bool] = []

        def chain(p0: Array, p1: Array, r: float, k: int, fixed: bool) -> None:
            length = float(np.max(np.linalg.norm(p1 - p0, axis=1)))
            m = max(2, math.ceil(length / self.spacing) + 1)
            for t in np.linspace(0.0, 1.0, m):
                pts.append(p0 + t * (p1 - p0))
                rad.append(r)
                link.append(k)
                static.append(fixed)

        for i, j in enumerate(rob.joints):
            o = T[:, :3, 3].copy()
            z = T[:, :3, 2].copy()
            T = T @ _dh(theta[:, i], j.d, j.a, j.alpha)
            knee = o + j.d * z
            chain(o, knee, self.radii[i], i + 1, fixed=(i == 0))
            chain(knee, T[:, :3, 3], self.radii[i], i + 1, fixed=False)
        tip = T[:, :3, 3] + np.einsum("nij,j->ni", T[:, :3, :3], np.asarray(rob.tool))
        chain(T[:, :3, 3], tip, self.tool_radius, rob.dof + 1, fixed=False)
        return (np.stack(pts, axis=1), np.array(rad), np.array(link), np.array(static))


def independent_unsafe(robot: RobotDescription, cell: Cell, q_deg: Array, home_deg: Array,
                       *, step_deg: float = 0.5) -> list[int]:
    """Indices of moves (home -> q[0] -> ...) whose sampled path leaves the joint limits or
    brings a link into the floor, a keep-out box, or the base/upper arm into the wrist."""
    targets = np.radians(np.asarray(q_deg))
    starts = np.vstack([np.radians(home_deg)[None], targets[:-1]])
    k = np.maximum(1, np.ceil(np.degrees(np.abs(targets - starts)).max(axis=1) / step_deg))
    owner = np.repeat(np.arange(len(k)), (k + 1).astype(int))
    s = np.concatenate([np.linspace(0.0, 1.0, int(m) + 1) for m in k])
    q = starts[owner] + s[:, None] * (targets[owner] - starts[owner])
    lim = robot.joint_limits
    bad = ~np.all((q >= lim[:, 0] - 1e-9) & (q <= lim[:, 1] + 1e-9), axis=1)
    model = LinkPoints(robot, cell)
    lo = np.array([b.min_mm for b in cell.keep_out]).reshape(-1, 3) * 1e-3
    hi = np.array([b.max_mm for b in cell.keep_out]).reshape(-1, 3) * 1e-3
    floor = cell.floor.z_mm * 1e-3
    for c in range(0, len(q), 1000):
        P, r, link, static = model.points(q[c:c + 1000])
        mv = ~static
        below = (P[:, mv, 2] - r[mv] < floor).any(axis=1)
        g = np.maximum(np.maximum(lo[None, None] - P[:, mv, None], P[:, mv, None] - hi[None, None]),
                       0.0)
        inside = (np.linalg.norm(g, axis=-1) < r[mv][None, :, None]).any(axis=(1, 2))
        near = link <= 2
        far = link >= robot.dof - 1
        d = np.linalg.norm(P[:, near, None, :] - P[:, None, far, :], axis=-1)
        touch = (d < r[near][:, None] + r[far][None, :]).any(axis=(1, 2))
        bad[c:c + 1000] |= below | inside | touch
    return sorted({int(i) for i in owner[bad]})


@pytest.mark.parametrize("name", ROBOTS)
@pytest.mark.parametrize("seed", [0, 1])
def test_plans_have_no_unsafe_move(name: str, seed: int) -> None:
    robot = load_robot(name)
    cell = load_cell("demo")
    plan = plan_campaign(robot, cell, count=12, validation=2, cpa=False, iso=False, seed=seed,
                         candidates=64)
    q = np.array([p.joints_deg for p in plan.poses])
    assert independent_unsafe(robot, cell, q, np.array(plan.motion.home_deg)) == []
    assert all(p.move_clear for p in plan.poses) and plan.motion.blocked_moves == 0
    # what was dropped is said so, in the plan and its warnings
    if plan.dropped:
        assert any(f"{len(plan.dropped)} target(s) dropped" in w for w in plan.warnings)
        assert all("no safe route" in d.reason for d in plan.dropped)
    assert plan.count("calibration") + plan.count("validation") + len(
        [d for d in plan.dropped if d.purpose in ("calibration", "validation")]) == 14


def test_full_plan_with_cpa_and_iso_is_safe() -> None:
    robot = load_robot("fanuc_lrmate200i")
    cell = load_cell("demo")
    plan = plan_campaign(robot, cell, count=12, validation=3, cpa=True, cpa_points=4, iso=True,
                         seed=2, candidates=128)
    assert plan.count("cpa") > 0 and plan.count("iso") > 0
    q = np.array([p.joints_deg for p in plan.poses])
    assert independent_unsafe(robot, cell, q, np.array(plan.motion.home_deg)) == []


def test_independent_check_sees_a_move_through_the_floor() -> None:
    # the check of the tests must itself find what it looks for
    robot = load_robot("fanuc_lrmate200i")
    table = cell_with(load_cell("demo"), floor={"z_mm": -150.0},
                      keep_out=[load_cell("demo").to_dict()["keep_out"][1]])
    q = np.array([[0.0, 30.0, -10.0, 0.0, -60.0, 0.0], [0.0, 146.0, -105.0, 0.0, 20.0, 0.0],
                  [0.0, 30.0, -10.0, 0.0, -60.0, 0.0]])
    assert independent_unsafe(robot, table, q, q[0]) == [1, 2]
    found = MotionChecker(robot, table).check_sequence(np.radians(q), np.radians(q[0]))
    assert [u.index for u in found] == [1, 2]
    assert "floor" in found[0].reason and "146.00" in found[0].describe()


def test_swept_sampling_bounds_capsule_travel() -> None:
    # between two samples no capsule axis point travels more than its step
    robot = load_robot("ur10")
    mc = MotionChecker(robot, load_cell("demo"))
    rng = np.random.default_rng(3)
    a = rng.uniform(mc.limits[:, 0], mc.limits[:, 1], (20, 6))
    b = rng.uniform(mc.limits[:, 0], mc.limits[:, 1], (20, 6))
    q, owner, _ = mc.samples(a, b)
    A, B, _, _ = mc.capsules.segments(q)
    same = owner[1:] == owner[:-1]
    travel = np.maximum(np.linalg.norm(A[1:] - A[:-1], axis=2),
                        np.linalg.norm(B[1:] - B[:-1], axis=2))[same]
    assert (travel <= mc.step[None, :] + 1e-9).all()
    assert (mc.step <= 0.25 * mc.capsules.radius + 1e-12).all()
    assert (mc.step <= mc.clearance + 1e-12).all()


def test_unsafe_home_is_an_error() -> None:
    cell = cell_with(load_cell("demo"), motion={"home_deg": [0, 146, -105, 0, 20, 0]},
                     floor={"z_mm": -150.0}, keep_out=[])
    with pytest.raises(ConfigError, match=r"home configuration .* not safe: capsule .* floor"):
        plan_campaign("fanuc_lrmate200i", cell, count=12, cpa=False, iso=False, candidates=64)


def test_dropped_targets_survive_the_file(tmp_path) -> None:
    plan = plan_campaign("kuka_kr210_r3100", "demo", count=12, validation=2, cpa=False,
                         iso=False, seed=0, candidates=64)
    plan.save(tmp_path / "PLAN.json")
    back = Plan.load(tmp_path / "PLAN.json")
    assert back.dropped == plan.dropped
