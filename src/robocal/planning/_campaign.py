"""Planning a whole measurement campaign: candidates, selection, extras, ordering, PLAN.json."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from robocal import __version__
from robocal._core.threads import single_threaded
from robocal.errors import ConfigError
from robocal.identification import CPA_MIN_ARC_DEG, CPA_MIN_RADIUS_MM, TrackerSigma, whitening
from robocal.kinematics import ErrorModelSpec, RobotDescription, load_robot
from robocal.planning._cell import Cell, builtin_cells, load_cell
from robocal.planning._coverage import (
    TARGET_MARGIN_DEG,
    ensure_span,
    excluded_families,
    family,
    joint_coverage,
    read_program_joints,
    required_span,
    widen_for_targets,
    winding_ranges,
)
from robocal.planning._cpa import CpaSweep, cpa_sweeps
from robocal.planning._design import (
    DESIGNS,
    DesignSpace,
    Observability,
    design_note,
    model_spec,
)
from robocal.planning._feasibility import Feasibility, FeasibilityChecker
from robocal.planning._geometry import link_frames, nearest_rows, range_scaled
from robocal.planning._iso import ISO_CYCLES, IsoCube, iso_cube
from robocal.planning._motion import MotionChecker
from robocal.planning._order import (
    move_times,
    order_poses,
    pairwise_move_times,
    shortest_path,
    two_opt,
)
from robocal.planning._plan import (
    CandidateInfo,
    CapsuleInfo,
    CpaInfo,
    DroppedTarget,
    ExcludedFamily,
    IsoInfo,
    JointCoverage,
    ModelInfo,
    MotionInfo,
    ObservabilityInfo,
    ObservabilitySection,
    Plan,
    PlannedPose,
    RobotInfo,
)
from robocal.planning._sobol import Sobol

Array = NDArray[np.float64]

#: Candidate draws stop at this many Sobol points even if fewer are feasible.
MAX_DRAWS = 2**20
# CPA arcs shorter than CPA_MIN_ARC_DEG and circles smaller than CPA_MIN_RADIUS_MM get a
# warning: the fit of a circle's centre and axis degrades quickly below them (ADR 0004); the
# CPA fit diagnoses its circles with the same limits (ADR 0021).


def cpa_radius(robot: RobotDescription, joint: int, q: Array, reflector: Array) -> float:
    """Radius (m) of the circle the reflector (3,) m describes about ``joint``'s axis at ``q``
    (dof,) rad: its distance from the axis (z of frame joint-1 through that frame's origin)."""
    O, R, _ = link_frames(robot, q[None, :])
    z = R[0, joint - 1][:, 2]
    v = reflector - O[0, joint - 1]
    return float(np.linalg.norm(v - (v @ z) * z))


@single_threaded
def draw_candidates(checker: FeasibilityChecker, *, target: int, seed: int,
                    max_draws: int = MAX_DRAWS, collided: list[Array] | None = None
                    ) -> tuple[Array, Feasibility, dict[str, int]]:
    """Draw scrambled Sobol candidates inside the working ranges until ``target`` are feasible.

    Points are drawn in power-of-two batches (doubling the total each time, which keeps the
    Sobol balance), screened cheaply (limits, range, facing), and the survivors fully checked.

    Parameters
    ----------
    checker
        Feasibility checker of the robot in its cell.
    target
        Feasible candidates wanted.
    seed
        Seed of the scrambling.
    max_draws
        Stop after this many points in total.
    collided
        When given, the screened candidates that fail a collision check (floor, keep-out,
        self-collision) are appended to it, rad.

    Returns
    -------
    q : ndarray, shape (n, dof)
        The first ``target`` feasible candidates in draw order (fewer if the draws ran
        out), rad.
    feasibility : Feasibility
        Their check results.
    counts : dict
        ``drawn``, ``screened`` (passed the cheap screen) and, per check, how many screened
        candidates failed it.
    """
    dof = checker.robot.dof
    lo, hi = checker.ranges[:, 0], checker.ranges[:, 1]
    sampler = Sobol(dof, np.random.default_rng(seed))
    m = max(10, math.ceil(math.log2(max(1, 16 * target))))
    m = min(m, max(1, int(math.log2(max_draws))))
    batch = sampler.random_base2(m)
    drawn = 0
    screened = 0
    rejected: dict[str, int] = {}
    qs: list[Array] = []
    fs: list[Feasibility] = []
    n_ok = 0
    while True:
        q = lo + batch * (hi - lo)
        drawn += len(q)
        q = q[checker.screen(q)]
        screened += len(q)
        f = checker.check(q)
        for k, v in f.rejected().items():
            rejected[k] = rejected.get(k, 0) + v
        qs.append(q[f.ok])
        fs.append(f.subset(f.ok))
        if collided is not None:
            collided.append(q[~f.collision_free])
        n_ok += int(f.ok.sum())
        if n_ok >= target or 2 * drawn > max_draws:
            break
        batch = sampler.random(drawn)
    keep = np.arange(min(target, n_ok))  # the first ones in draw order: evenly spread
    feas = Feasibility(**{k: np.concatenate([getattr(p, k) for p in fs])[keep]
                          for k in Feasibility.__dataclass_fields__})
    counts = {"drawn": drawn, "screened": screened, **rejected}
    return np.concatenate(qs)[keep], feas, counts


def _obs_info(o: Observability) -> ObservabilityInfo:
    def r(v: float) -> float:
        return float(f"{v:.6g}")

    return ObservabilityInfo(
        poses=o.poses, parameters=o.parameters, identifiable=o.identifiable,
        min_poses=o.min_poses, recommended_poses=o.recommended_poses,
        O1=r(o.O1), O2=r(o.O2), O3=r(o.O3), O4=r(o.O4), O5=r(o.O5),
        condition_number=None if not math.isfinite(o.condition_number)
        else r(o.condition_number))


def _home(robot: RobotDescription, cell: Cell, ranges: Array) -> Array:
    h = cell.motion.home_deg
    if h is None:
        return np.clip(np.zeros(robot.dof), ranges[:, 0], ranges[:, 1])
    if len(h) != robot.dof:
        raise ConfigError(f"home_deg needs {robot.dof} entries, got {len(h)}",
                          source=f"cell {cell.name!r}", key="motion.home_deg")
    return np.radians(np.asarray(h, dtype=float))


def _round_deg(q: Array) -> Array:
    """Joint values (..., dof) rad as the plan file holds them: degrees rounded to 1e-6."""
    return np.radians(np.round(np.degrees(q), 6) + 0.0)


def split_legs(q_from: Array, q_to: Array, max_step: float
               ) -> tuple[Array, Array, NDArray[np.intp]]:
    """Cut legs q_from[k] -> q_to[k] (m, dof) rad into moves of at most ``max_step`` rad per
    joint, by evenly spaced via-points on the straight joint-space line (rounded as in the
    file, so that what is checked is what is written).

    Returns
    -------
    starts, ends : ndarray, shape (M, dof)
        The moves, leg after leg, rad.
    owner : ndarray of int, shape (M,)
        Leg of each move.
    """
    q_from = np.atleast_2d(q_from)
    q_to = np.atleast_2d(q_to)
    d = q_to - q_from
    k = np.maximum(1, np.ceil(np.abs(d).max(axis=1) / max_step - 1e-9)).astype(np.intp)
    owner = np.repeat(np.arange(len(k)), k)
    first = np.concatenate([[0], np.cumsum(k)[:-1]])
    m = np.arange(int(k.sum())) - np.repeat(first, k) + 1       # 1 .. k within each leg
    ends = _round_deg(q_from[owner] + d[owner] * (m / k[owner])[:, None])
    last = m == k[owner]
    ends[last] = q_to[owner[last]]
    starts = np.empty_like(ends)
    starts[1:] = ends[:-1]
    starts[first] = q_from
    return starts, ends, owner


def _legs_safe(motion: MotionChecker, q_from: Array, q_to: Array, max_step: float,
               *, explain: bool = False) -> tuple[NDArray[np.bool_], list[str]]:
    """Whether each leg (with its via-points) is safe along its swept path, and why not
    (reasons only with ``explain``).

    Verdicts are kept in ``motion.leg_verdicts``: ordering, reachability and routing check
    many of the same legs, and each is swept once (an unsafe leg is checked again only when
    its reason is wanted and was not recorded).
    """
    q_from = np.broadcast_to(np.atleast_2d(q_from), np.shape(np.atleast_2d(q_to)))
    q_to = np.atleast_2d(q_to)
    n = len(q_to)
    step = np.float64(max_step).tobytes()
    keys = [a.tobytes() + b.tobytes() + step for a, b in zip(q_from, q_to, strict=True)]
    known = motion.leg_verdicts
    todo = [i for i, k in enumerate(keys)
            if k not in known or (explain and not known[k][0] and not known[k][1])]
    if todo:
        idx = np.array(todo, dtype=np.intp)
        starts, ends, owner = split_legs(q_from[idx], q_to[idx], max_step)
        res = motion.check_moves(starts, ends, explain=explain)
        ok_t = np.ones(len(idx), dtype=bool)
        ok_t[owner[~res.safe]] = False
        why_t = [""] * len(idx)
        for i in np.flatnonzero(~res.safe)[::-1]:   # keep the first failing move of a leg
            why_t[int(owner[i])] = res.reasons[i]
        for k, good, reason in zip(idx, ok_t, why_t, strict=True):
            known[keys[int(k)]] = (bool(good), reason)
    ok = np.array([known[k][0] for k in keys], dtype=bool).reshape(n)
    return ok, [known[k][1] for k in keys]


def _order_measured(motion: MotionChecker, q: Array, speed: Array, home: Array,
                    max_step: float, rounds: int = 3) -> NDArray[np.intp]:
    """Order poses by move time; re-run 2-opt with penalties on moves that are not safe."""
    order = order_poses(q, speed, start=home)
    D = pairwise_move_times(q, speed)
    s = move_times(home[None, :], q, speed)
    penalty = 10.0 * float(D.max() + 1.0)
    for _ in range(rounds):
        seq = q[order]
        starts = np.vstack([home[None, :], seq[:-1]])
        clear, _ = _legs_safe(motion, starts, seq, max_step)
        if clear.all():
            break
        for k in np.flatnonzero(~clear):
            b = order[k]
            if k == 0:
                s[b] += penalty
            else:
                a = order[k - 1]
                D[a, b] += penalty
                D[b, a] += penalty
        order = two_opt(order, D, s)
    return order


class _Roadmap:
    """A lazily checked roadmap over safe poses for detours (lazy PRM).

    Nodes are safe poses (the pool, home, and every target reached so far); each is joined to
    its ``k`` nearest nodes by move time. A route is the shortest path by move time whose
    edges are not known to be unsafe; its unchecked edges are then checked in one batch,
    unsafe ones removed, and the search repeated. The legs the plan takes are known safe, so
    a route can always lead back the way the robot came (moves are reversible), and edge
    results are kept for later detours.
    """

    def __init__(self, motion: MotionChecker, pool: Array, home: Array, speed: Array,
                 max_step: float, *, k: int = 8) -> None:
        self.motion = motion
        self.speed = speed
        self.max_step = max_step
        self.k = k
        self.nodes = np.vstack([pool, home[None, :]])
        self.home = len(pool)
        self._key: dict[tuple[int, int], int] = {}
        self.ei: list[int] = []
        self.ej: list[int] = []
        self.ew: list[float] = []
        self.state: list[int] = []                 # 0 unknown, 1 safe, -1 unsafe
        n = len(self.nodes)
        if n > 1:
            D = pairwise_move_times(self.nodes, speed)
            np.fill_diagonal(D, np.inf)
            kk = min(k, n - 1)
            part = np.argpartition(D, kk - 1, axis=1)[:, :kk]
            nn = np.take_along_axis(
                part, np.argsort(np.take_along_axis(D, part, axis=1), axis=1), axis=1)
            for i, row in enumerate(nn):
                for j in row:
                    self._edge(i, int(j), 0)

    def _edge(self, u: int, v: int, state: int) -> int:
        key = (min(u, v), max(u, v))
        e = self._key.get(key)
        if e is None:
            e = len(self.ei)
            self._key[key] = e
            self.ei.append(key[0])
            self.ej.append(key[1])
            self.ew.append(float(move_times(self.nodes[u], self.nodes[v], self.speed)))
            self.state.append(state)
        elif state:
            self.state[e] = state
        return e

    def add_target(self, q: Array, came_from: int) -> int:
        """Add a reached target (dof,) rad, joined safely to ``came_from`` and (unchecked)
        to its nearest nodes; return its node index."""
        t = move_times(q, self.nodes, self.speed)
        self.nodes = np.vstack([self.nodes, q[None, :]])
        idx = len(self.nodes) - 1
        for j in np.argsort(t)[:self.k]:
            self._edge(idx, int(j), 0)
        self._edge(came_from, idx, 1)
        return idx

    def mark_safe(self, path: list[int]) -> None:
        """Record the consecutive legs of a node path as safe."""
        for u, v in itertools.pairwise(path):
            self._edge(u, v, 1)

    def route(self, a: int, b: Array, *, rounds: int = 5) -> list[int] | None:
        """Node indices of a safe route from node ``a`` to pose ``b`` (exclusive), or None.

        Up to ``rounds`` lazy searches for a short route, then one over known-safe edges.
        """
        n = len(self.nodes)
        t = move_times(b, self.nodes, self.speed)
        near = np.union1d(np.argsort(t)[:self.k], [self.home])
        near = near[near != a]
        ok, _ = _legs_safe(self.motion, self.nodes[near],
                           np.broadcast_to(b, (len(near), b.size)), self.max_step)
        nb = near[ok]
        if not len(nb):
            return None
        goal = n
        for r in range(rounds + 1):
            st = np.array(self.state, dtype=np.int8)
            # the last round uses known-safe edges only: the way back along the legs taken
            # (to home, say) always exists, so a target reachable from home is reached
            use = st >= 0 if r < rounds else st == 1
            i = np.concatenate([np.array(self.ei)[use], nb])
            j = np.concatenate([np.array(self.ej)[use], np.full(len(nb), goal)])
            w = np.concatenate([np.array(self.ew)[use], t[nb]])
            path = shortest_path(n + 1, i, j, w, a, goal)
            if path is None:
                return None
            nodes = path[:-1]                                # a, ..., last node before b
            eidx = [self._key[(min(u, v), max(u, v))] for u, v in itertools.pairwise(nodes)]
            todo = [e for e in eidx if self.state[e] == 0]
            if todo:
                todo_a = np.array(todo)
                ok_e, _ = _legs_safe(self.motion, self.nodes[np.array(self.ei)[todo_a]],
                                     self.nodes[np.array(self.ej)[todo_a]], self.max_step)
                for e, good in zip(todo, ok_e, strict=True):
                    self.state[e] = 1 if good else -1
            if all(self.state[e] == 1 for e in eidx):
                return nodes[1:]
        return None


def _safe_route(motion: MotionChecker, seq: Array, purposes: list[str], home: Array,
                pool: Array, speed: Array, max_step: float
                ) -> tuple[Array, list[str], list[DroppedTarget]]:
    """Route through the targets ``seq`` (n, dof) with only safe moves.

    A leg whose straight path (via-points included) is not safe gets detour via-points: the
    shortest safe route over a roadmap of the ``pool`` poses, home and the targets reached so
    far; a target that no route reaches is dropped, and the next target is approached from
    the last one reached.

    Returns
    -------
    q : ndarray, shape (m, dof)
        Targets and detour via-points in order (before the step via-points), rad.
    purposes : list of str
        Their purposes (``"via"`` for detours).
    dropped : list of DroppedTarget
    """
    ok, why = _legs_safe(motion, np.vstack([home[None, :], seq[:-1]]), seq, max_step,
                         explain=True)
    roadmap = _Roadmap(motion, pool, home, speed, max_step)
    rows: list[Array] = []
    out_p: list[str] = []
    dropped: list[DroppedTarget] = []
    cur = roadmap.home
    cur_is_prev = True          # ``ok`` holds for the leg from the previous target
    for i, b in enumerate(seq):
        if cur_is_prev:
            safe, reason = bool(ok[i]), why[i]
        else:
            o, w = _legs_safe(motion, roadmap.nodes[cur][None, :], b[None, :], max_step,
                              explain=True)
            safe, reason = bool(o[0]), w[0]
        via: list[int] | None = []
        if not safe:
            via = roadmap.route(cur, b)
            if via is None:
                dropped.append(DroppedTarget(
                    purpose=purposes[i], joints_deg=[float(v) for v in np.degrees(b)],
                    reason=f"no safe route from the previous target: {reason}"))
                cur_is_prev = False
                continue
            roadmap.mark_safe([cur, *via])
            rows += [roadmap.nodes[v] for v in via]
            out_p += ["via"] * len(via)
        rows.append(b)
        out_p.append(purposes[i])
        cur = roadmap.add_target(b, via[-1] if via else cur)
        cur_is_prev = True
    dof = seq.shape[1]
    return np.array(rows).reshape(-1, dof), out_p, dropped


def _detour_pool(motion: MotionChecker, q_c: Array, seed: int, n: int = 1024) -> Array:
    """Up to ``n`` collision-free poses for the roadmap: half from the feasible candidates,
    the rest Sobol points that pass the motion checks (no need to face the tracker), rounded
    as in the file."""
    lo, hi = motion.limits[:, 0], motion.limits[:, 1]
    sob = Sobol(motion.robot.dof, np.random.default_rng([seed, 4]))
    q = _round_deg(lo + sob.random_base2(int(math.log2(2 * n))) * (hi - lo))
    q = q[~motion.bad(q)]
    own = _round_deg(q_c[:n // 2])
    return np.vstack([own, q[:n - len(own)]])


@single_threaded
def plan_campaign(
    robot: RobotDescription | str | Path,
    cell: Cell | str | Path,
    *,
    count: int,
    model: str | ErrorModelSpec = "constant",
    validation: int = 0,
    cpa: bool = False,
    cpa_points: int = 12,
    iso: bool = True,
    iso_cycles: int = ISO_CYCLES,
    seed: int = 0,
    candidates: int = 4096,
    max_draws: int = MAX_DRAWS,
    exchange_passes: int = 2,
    design: str = "stratified",
    targets: str | Path | None = None,
    target_margin_deg: float = TARGET_MARGIN_DEG,
) -> Plan:
    """Plan a calibration campaign for one robot in one cell.

    Parameters
    ----------
    robot
        Description, built-in name or robot TOML path.
    cell
        Cell description, built-in name (``"demo"``) or TOML path.
    count
        Calibration poses, chosen for ``model`` from the feasible candidates (see ``design``).
    model
        ``"constant"``, ``"high-order"``, ``"auto"`` (see :func:`model_spec`) or a spec.
    validation
        Validation poses: a seeded random sample of the remaining feasible candidates
        (disjoint from the calibration set; random so that they represent the workspace).
    cpa
        Add single-joint circle-point-analysis sweeps, ``cpa_points`` per joint.
    iso
        Add the ISO 9283 test-cube poses P1..P5 (a warning if no cube fits).
    iso_cycles
        Times the robot visits P1..P5 in that order; ISO 9283 asks for 30 cycles, from which
        the report computes pose accuracy (AP) and repeatability (RP).
    seed
        Seeds the Sobol scrambling, the validation sample and the CPA jitter; the plan is a
        deterministic function of its inputs and this seed.
    candidates
        Feasible candidates to choose from (more draws are made until there are this many,
        up to ``max_draws`` Sobol points).
    exchange_passes
        Fedorov exchange passes after the greedy D-optimal build-up.
    design
        ``"stratified"`` (default): one pose per k-means stratum of the joint space, D-optimal
        within strata, so that the poses represent the workspace (a model that lacks some of
        the robot's errors then fits their average, not their extremes); ``"d-optimal"``: the
        most information for the model, no coverage (see docs/adr/0004).
    targets
        The production program (TARGETS.csv or JOINTS.csv, see docs/compensation-tables.md):
        the working ranges are widened to its joint ranges plus ``target_margin_deg`` (within
        the robot limits; twice that while drawing candidates) and the calibration poses made
        to span them (ADR 0026).

    Returns
    -------
    Plan
        Ordered poses and all figures; write it with :meth:`Plan.save`.

    Raises
    ------
    ConfigError
        On bad input: unknown robot, cell or model; counts out of range; too few feasible
        candidates; fewer poses than the model needs.
    """
    robot_name, rob, the_cell, cell_source = _resolve(robot, cell)
    _check_arguments(iso_cycles=iso_cycles, seed=seed, count=count, validation=validation,
                     cpa=cpa, cpa_points=cpa_points, candidates=candidates, design=design)
    spec = model_spec(rob, model)
    model_name = model if isinstance(model, str) else spec.label
    checker = FeasibilityChecker(rob, the_cell)
    motion = MotionChecker(rob, the_cell, limits=checker.ranges)
    home = _round_deg(_home(rob, the_cell, checker.ranges))
    if motion.bad(home[None, :])[0]:
        raise ConfigError(f"the home configuration {np.round(np.degrees(home), 3).tolist()} deg "
                          f"is not safe: {motion.explain(home[None, :])[0]}",
                          source=f"cell {the_cell.name!r}", key="motion.home_deg")
    warnings: list[str] = []
    margin = math.radians(target_margin_deg)
    q_prog = None if targets is None else read_program_joints(targets, dof=rob.dof)
    # checker.ranges and motion.limits are one array: narrowed or widened in place
    ranges, notes = winding_ranges(motion, home, checker.ranges)
    if q_prog is not None:
        # twice the margin: candidates beyond the targets' margin must exist to be chosen
        ranges, more = widen_for_targets(ranges, rob.joint_limits, q_prog, 2.0 * margin)
        notes += more
    checker.ranges[:] = ranges
    warnings += notes
    collided: list[Array] = []
    q_c, feas_c, counts = _feasible_candidates(checker, the_cell.name,
                                               target=max(candidates, 2 * (count + validation)),
                                               need=count + validation, seed=seed,
                                               max_draws=max_draws, collided=collided)
    excluded = excluded_families(checker, np.vstack(collided), counts["screened"])
    # as the file holds them (1e-6 deg), so that the legs checked while choosing and ordering
    # are the legs routed and written, and their verdicts are reused
    q_c = _round_deg(q_c)
    ds = cell_design_space(checker, spec, q_c, feas_c)
    if count < ds.min_poses:
        raise ConfigError(
            f"count {count} is below the {ds.min_poses} poses the {model_name} model needs "
            f"({ds.identifiable} identifiable parameters, 3 equations per pose; "
            f"{ds.recommended_poses} recommended)")
    if count < ds.recommended_poses:
        warnings.append(f"{count} calibration poses are fewer than the {ds.recommended_poses} "
                        f"recommended for {ds.identifiable} identifiable parameters")
    max_step = math.radians(the_cell.motion.max_joint_step_deg)
    unreachable: list[int] = []
    cal, val = _choose_poses(ds, motion, home, max_step, count=count, validation=validation,
                             seed=seed, design=design, exchange_passes=exchange_passes,
                             warnings=warnings, span=required_span(q_c, q_prog, margin),
                             unreachable=unreachable)
    if unreachable:
        # only the candidates the selection proposed were checked: a lower bound
        excluded.append(family("feasible but no safe straight move from home (a pocket of "
                               "the capsule model; among the candidates the selection "
                               "proposed)", q_c[np.array(unreachable)], counts["screened"]))
    baseline = np.random.default_rng([seed, 2]).choice(len(q_c), size=count, replace=False)
    obs = ObservabilitySection(calibration=_obs_info(ds.observability(cal)),
                               random_baseline=_obs_info(ds.observability(baseline)))
    sweeps = (_cpa_extras(checker, rob, q_c, cpa_points, seed, warnings,
                          reachable=lambda q: _legs_safe(motion, home, q, max_step)[0])
              if cpa else [])
    cube = iso_cube(checker, q_c, feas_c) if iso else None
    if iso and cube is None:
        warnings.append("no feasible ISO 9283 cube was found; iso-P1..P5 left out")
    speed = np.array([j.max_speed for j in rob.joints]) * the_cell.motion.speed_fraction
    q_all, purposes, dropped = _route(motion, q_c, cal, val, sweeps, cube, iso_cycles, home,
                                      speed, max_step, seed, the_cell.name)
    final = checker.check(q_all)
    bad = [i for i, p in enumerate(purposes) if p != "via" and not final.ok[i]]
    if bad:  # pragma: no cover - margins of exactly zero cut by rounding
        raise ConfigError(f"internal: planned poses {bad[:5]} fail their checks after rounding")
    unsafe = motion.check_sequence(q_all, home, purposes)
    if unsafe:  # pragma: no cover - every leg was checked exactly as written
        raise ConfigError("internal: the planned route has unsafe moves: "
                          + "; ".join(u.describe() for u in unsafe[:3]))
    if dropped:
        kinds: dict[str, int] = {}
        for d in dropped:
            kinds[d.purpose] = kinds.get(d.purpose, 0) + 1
        warnings.append(f"{len(dropped)} target(s) dropped, no safe route found to them ("
                        + ", ".join(f"{v} {k}" for k, v in kinds.items())
                        + "): see 'dropped' in the plan")
    poses = _planned_poses(q_all, purposes, final)
    q_cal = q_all[np.array([p == "calibration" for p in purposes])]
    coverage = joint_coverage(rob, checker.ranges, q_cal, q_prog, margin)
    uncovered = [f"J{c['joint']}" for c in coverage if c["targets_covered"] is False]
    if uncovered:
        warnings.append(f"the calibration poses do not cover the program's range of "
                        f"{', '.join(uncovered)} (plus {target_margin_deg:g} deg): no feasible, "
                        "safely reachable pose there; see 'coverage' and 'excluded'")
    prev = np.vstack([home[None, :], q_all[:-1]])
    motion_info = MotionInfo(
        max_joint_step_deg=the_cell.motion.max_joint_step_deg,
        speed_fraction=the_cell.motion.speed_fraction,
        home_deg=[round(float(v), 6) for v in np.degrees(home)],
        move_time_s=round(float(move_times(prev, q_all, speed).sum()), 3),
        joint_travel_deg=[round(float(v), 3) for v in np.degrees(np.abs(q_all - prev).sum(0))],
        via_points=purposes.count("via"), blocked_moves=0)
    rejected = {k: v for k, v in counts.items() if k not in ("drawn", "screened")}
    return Plan(
        robocal_version=__version__,
        robot=RobotInfo(name=robot_name, source=rob.source, description=rob.to_dict()),
        cell=the_cell, cell_source=cell_source, seed=seed,
        model=ModelInfo(name=model_name, label=spec.label, parameters=len(ds.names),
                        design="stratified" if design == "stratified" else "d-optimal",
                        design_note=design_note(model_name, design)),
        candidates=CandidateInfo(drawn=counts["drawn"], screened=counts["screened"],
                                 feasible=len(q_c), rejected=rejected),
        observability=obs, unidentifiable=list(ds.unidentifiable), motion=motion_info,
        iso9283=None if cube is None else IsoInfo(
            centre_mm=[round(float(v) * 1e3, 3) for v in cube.centre],
            side_mm=round(cube.side * 1e3, 3), cycles=iso_cycles),
        cpa=[CpaInfo(joint=s.joint, span_deg=[round(math.degrees(v), 3) for v in s.span],
                     points=len(s.q), radius_mm=round(1e3 * cpa_radius(
                         rob, s.joint, s.q[0], s.feasibility.reflector[0]), 3))
             for s in sweeps],
        warnings=warnings, dropped=dropped,
        coverage=[JointCoverage.model_validate(c) for c in coverage],
        targets_source=None if targets is None else str(targets),
        capsules=CapsuleInfo(
            link_radii_mm=[round(r * 1e3, 3) for r in checker.capsules.radii],
            tool_radius_mm=the_cell.robot.tool_radius_mm, source=checker.radii_source),
        excluded=[ExcludedFamily.model_validate(e) for e in excluded], poses=poses)


def cell_design_space(checker: FeasibilityChecker, spec: ErrorModelSpec, q: Array,
                      feasibility: Feasibility) -> DesignSpace:
    """The design space of feasible candidates ``q`` (n, dof) rad in ``checker``'s cell.

    Each candidate is weighted by the tracker's noise where its reflector is (radial vs
    transverse, growing with range), as the maximum-likelihood fit will weight it.
    """
    W = whitening(feasibility.reflector, TrackerSigma(position=tuple(checker.tracker)))
    return DesignSpace(checker.robot, spec, q, np.asarray(checker.tool_offset), weights=W)


def _resolve(robot: RobotDescription | str | Path, cell: Cell | str | Path
             ) -> tuple[str, RobotDescription, Cell, str]:
    """Robot name and description, cell and where the cell came from."""
    if isinstance(robot, RobotDescription):
        robot_name, rob = robot.name, robot
    else:
        robot_name, rob = str(robot), load_robot(robot)
    if isinstance(cell, Cell):
        return robot_name, rob, cell, f"<{cell.name}>"
    the_cell, cell_source = load_cell(cell), str(cell)
    if not cell_source.endswith(".toml") and cell_source in builtin_cells():
        cell_source = f"builtin:{cell_source}"
    return robot_name, rob, the_cell, cell_source


def _check_arguments(*, iso_cycles: int, seed: int, count: int, validation: int, cpa: bool,
                     cpa_points: int, candidates: int, design: str) -> None:
    """One clear error for the first argument out of range."""
    if not 1 <= iso_cycles <= 1000:
        raise ConfigError(f"iso_cycles must be 1..1000, got {iso_cycles}")
    if seed < 0:
        raise ConfigError(f"seed must not be negative, got {seed}")
    if count < 1:
        raise ConfigError(f"count must be at least 1, got {count}")
    if validation < 0:
        raise ConfigError(f"validation must not be negative, got {validation}")
    if cpa and cpa_points < 3:
        raise ConfigError(f"a CPA circle needs at least 3 points per joint, got {cpa_points}")
    if candidates < 1:
        raise ConfigError(f"candidates must be positive, got {candidates}")
    if design not in DESIGNS:
        raise ConfigError(f"unknown design {design!r} (choose from {', '.join(DESIGNS)})")


def _feasible_candidates(checker: FeasibilityChecker, cell_name: str, *, target: int,
                         need: int, seed: int, max_draws: int,
                         collided: list[Array] | None = None
                         ) -> tuple[Array, Feasibility, dict[str, int]]:
    """Feasible candidates (see :func:`draw_candidates`); an error naming the checks that
    rejected the others when fewer than ``need`` are found."""
    q_c, feas_c, counts = draw_candidates(checker, target=target, seed=seed,
                                          max_draws=max_draws, collided=collided)
    if len(q_c) < need:
        why = ", ".join(f"{k} {v}" for k, v in counts.items()
                        if k not in ("drawn", "screened") and v)
        detail = (f"of the {counts['screened']} facing the tracker, rejected by: {why}"
                  if counts["screened"] else "none faces the tracker within the acceptance "
                  "angle and range")
        raise ConfigError(
            f"only {len(q_c)} of {counts['drawn']} candidate poses are feasible in cell "
            f"{cell_name!r}, fewer than the {need} requested ({detail}); "
            "check the tracker position, reflector direction and keep-out boxes")
    return q_c, feas_c, counts


def _choose_poses(ds: DesignSpace, motion: MotionChecker, home: Array, max_step: float, *,
                  count: int, validation: int, seed: int, design: str, exchange_passes: int,
                  warnings: list[str], span: Array | None = None,
                  unreachable: list[int] | None = None
                  ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Calibration poses by ``design`` and random validation poses, all reachable from home.

    A pose whose straight move from home is not safe (under the capsule model, e.g. the
    KR210's forearm folded over its shoulder) may lie in a pocket no route reaches. Only the
    chosen poses are checked (checking every candidate costs tens of seconds); unreachable
    ones are excluded and the choice repeated. With ``span`` (dof, 2) rad the calibration
    poses are then made to span it (:func:`ensure_span`). The candidates found unreachable
    are appended to ``unreachable``.
    """
    q_c = ds.q
    n_c = len(q_c)
    allowed = np.ones(n_c, dtype=bool)
    checked = np.zeros(n_c, dtype=bool)

    def reachable(idx: NDArray[np.intp]) -> NDArray[np.intp]:
        new = idx[~checked[idx]]
        if len(new):
            ok, _ = _legs_safe(motion, np.broadcast_to(home, (len(new), q_c.shape[1])),
                               q_c[new], max_step)
            checked[new] = True
            allowed[new[~ok]] = False
            if unreachable is not None:
                unreachable.extend(int(i) for i in new[~ok])
        return idx[~allowed[idx]]

    strata: NDArray[np.intp] | None = None
    cal = np.zeros(0, dtype=np.intp)
    misses = np.zeros(count, dtype=np.intp)       # unreachable poses chosen per stratum
    for _ in range(30):
        near = _near_reachable(q_c, checked, allowed)
        if design != "stratified":
            cal = ds.select(count, allowed=allowed, exchange_passes=exchange_passes)
        else:
            # the strata are kept while each still has an allowed member: only the strata
            # whose pose turned out unreachable choose again (a third of a UR10's candidates
            # in the demo cell), so the poses already checked stay
            refilled = None
            if strata is not None:
                misses[~allowed[cal]] += 1
                refilled = ds.refill_strata(cal, strata, allowed, prefer=near,
                                            release=misses >= 2)
            if refilled is None:
                cal, strata = ds.stratify(count, allowed=allowed)
                misses[:] = 0
            else:
                cal = refilled
        if span is not None:
            # an end of a joint's range often lies in such a pocket: its neighbours are
            # tried only when no candidate there is preferred
            ends_ok = allowed & near
            cal = ensure_span(q_c, cal, ends_ok if ends_ok.any() else allowed, span)
        if not len(reachable(cal)) or allowed.sum() < count + validation + count:
            break
    rest = np.setdiff1d(np.arange(n_c), cal)
    # validation poses stand for the program: drawn inside the joint ranges the calibration
    # poses span, where the model is meant to be used (a pose beyond them is extrapolation,
    # which fit warns about and a push refuses); all candidates when too few lie inside
    lo, hi = q_c[cal].min(axis=0), q_c[cal].max(axis=0)
    inside = rest[np.all((q_c[rest] >= lo) & (q_c[rest] <= hi), axis=1)]
    if len(inside[allowed[inside]]) >= 2 * validation:
        rest = inside
    rng_val = np.random.default_rng([seed, 1])
    val = np.zeros(0, dtype=np.intp)
    for _ in range(4):
        pool_v = np.setdiff1d(rest[allowed[rest]], val)
        need = validation - len(val)
        if need <= 0 or len(pool_v) < need:
            break
        val = np.sort(np.concatenate([val, rng_val.choice(pool_v, size=need, replace=False)]))
        reachable(val)
        val = val[allowed[val]]
    if len(val) < validation:
        warnings.append(f"only {len(val)} of {validation} validation poses could be chosen "
                        "among candidates reachable from home")
    return cal, val


def _near_reachable(q: Array, checked: NDArray[np.bool_], allowed: NDArray[np.bool_]
                    ) -> NDArray[np.bool_]:
    """Candidates (n,) whose nearest checked candidate (joint values scaled by their range)
    was reachable from home. Straight moves from home to nearby configurations sweep nearly
    the same space, so a pocket that one move cannot reach usually holds its neighbours too:
    refilling a stratum elsewhere saves checking them one after another."""
    idx = np.flatnonzero(checked)
    if not len(idx):
        return np.ones(len(q), dtype=bool)
    x = range_scaled(q)
    return np.asarray(allowed[idx[nearest_rows(x, x[idx])]], dtype=bool)


def _cpa_extras(checker: FeasibilityChecker, rob: RobotDescription, q_c: Array,
                cpa_points: int, seed: int, warnings: list[str],
                reachable: Callable[[Array], NDArray[np.bool_]] | None = None
                ) -> list[CpaSweep]:
    """CPA sweeps, with a warning per missing joint, short arc and small circle;
    ``reachable``: see :func:`cpa_sweeps`."""
    sweeps = cpa_sweeps(checker, q_c, points=cpa_points, rng=np.random.default_rng([seed, 3]),
                        reachable=reachable)
    got = {s.joint for s in sweeps}
    missing = [j for j in range(1, rob.dof + 1) if j not in got]
    if missing:
        warnings.append("no CPA sweep with the reflector visible throughout was found for "
                        f"joint(s) {', '.join(map(str, missing))}")
    for s in sweeps:
        if s.width < math.radians(CPA_MIN_ARC_DEG):
            warnings.append(f"CPA sweep of joint {s.joint} spans only "
                            f"{math.degrees(s.width):.0f} deg (< {CPA_MIN_ARC_DEG:g}): the "
                            "circle's centre and axis are poorly determined")
        r = cpa_radius(rob, s.joint, s.q[0], s.feasibility.reflector[0])
        if r < CPA_MIN_RADIUS_MM * 1e-3:
            warnings.append(f"CPA circle of joint {s.joint} has a radius of only "
                            f"{1e3 * r:.0f} mm (< {CPA_MIN_RADIUS_MM:g}): its axis "
                            "direction is poorly determined; a longer reflector offset "
                            "helps")
    return sweeps


def _route(motion: MotionChecker, q_c: Array, cal: NDArray[np.intp], val: NDArray[np.intp],
           sweeps: list[CpaSweep], cube: IsoCube | None, iso_cycles: int, home: Array,
           speed: Array, max_step: float, seed: int, cell_name: str
           ) -> tuple[Array, list[str], list[DroppedTarget]]:
    """Order the targets, route every leg safely (via-points, detours) and split the legs.

    Returns all joint positions (m, dof) rad as written (rounded to 1e-6 deg), their
    purposes ("via" for leg steps) and the targets dropped for want of a safe route.
    """
    meas_idx = np.concatenate([cal, val])
    purposes_meas = ["calibration"] * len(cal) + ["validation"] * len(val)
    order = _order_measured(motion, q_c[meas_idx], speed, home, max_step)
    seq_q: list[Array] = [q_c[meas_idx[order]]]
    seq_p: list[str] = [purposes_meas[i] for i in order]
    last = seq_q[0][-1]
    for s in sweeps:
        qs = s.q
        if move_times(last, qs[-1], speed) < move_times(last, qs[0], speed):
            qs = qs[::-1]
        seq_q.append(qs)
        seq_p += [f"cpa-j{s.joint}"] * len(qs)
        last = qs[-1]
    if cube is not None:
        seq_q.append(np.tile(cube.q, (iso_cycles, 1)))
        seq_p += [f"iso-P{k}" for k in range(1, 6)] * iso_cycles
    # the file holds degrees rounded to 1e-6 deg (17 nrad): plan and check what is written
    pool = _detour_pool(motion, q_c, seed)
    q_seq, seq_p, dropped = _safe_route(motion, _round_deg(np.vstack(seq_q)), seq_p, home,
                                        pool, speed, max_step)
    if not len(q_seq):
        raise ConfigError(f"no target can be reached safely from home in cell "
                          f"{cell_name!r}: {dropped[0].reason}" if dropped else
                          "nothing to plan")
    _, q_all, owner = split_legs(np.vstack([home[None, :], q_seq[:-1]]), q_seq, max_step)
    is_target = np.r_[owner[1:] != owner[:-1], True]
    purposes = [seq_p[owner[i]] if is_target[i] else "via" for i in range(len(q_all))]
    return q_all, purposes, dropped


def _planned_poses(q_all: Array, purposes: list[str], final: Feasibility) -> list[PlannedPose]:
    """The plan's pose records: joints in degrees, reflector in mm, margins of measured ones."""
    q_deg = np.round(np.degrees(q_all), 6) + 0.0
    poses = []
    for i, p in enumerate(purposes):
        vis = p != "via"
        poses.append(PlannedPose(
            index=i, purpose=p, measure=vis, joints_deg=[float(v) for v in q_deg[i]],
            reflector_mm=[round(float(v) * 1e3, 4) for v in final.reflector[i]],
            angle_margin_deg=round(math.degrees(float(final.angle_margin[i])), 3) if vis
            else None,
            sight_margin_mm=round(float(final.sight_margin[i]) * 1e3, 3) if vis else None,
            collision_margin_mm=round(min(float(final.collision_margin[i]), 1e6) * 1e3, 3),
            range_mm=round(float(final.range[i]) * 1e3, 3),
            move_clear=True))   # every leg was routed safely (unsafe targets are dropped)
    return poses
