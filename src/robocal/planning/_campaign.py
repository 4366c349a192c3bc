"""Planning a whole measurement campaign: candidates, selection, extras, ordering, PLAN.json."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.stats import qmc

from robocal import __version__
from robocal._core.threads import single_threaded
from robocal.errors import ConfigError
from robocal.identification import TrackerSigma, whitening
from robocal.kinematics import ErrorModelSpec, RobotDescription, load_robot
from robocal.planning._cell import Cell, builtin_cells, load_cell
from robocal.planning._cpa import cpa_sweeps
from robocal.planning._design import DesignSpace, Observability, model_spec
from robocal.planning._feasibility import Feasibility, FeasibilityChecker
from robocal.planning._iso import iso_cube
from robocal.planning._order import insert_via_points, move_times, order_poses, two_opt
from robocal.planning._plan import (
    CandidateInfo,
    CpaInfo,
    IsoInfo,
    ModelInfo,
    MotionInfo,
    ObservabilityInfo,
    ObservabilitySection,
    Plan,
    PlannedPose,
    RobotInfo,
)

Array = NDArray[np.float64]

#: Candidate draws stop at this many Sobol points even if fewer are feasible.
MAX_DRAWS = 2**20


@single_threaded
def draw_candidates(checker: FeasibilityChecker, *, target: int, seed: int,
                    max_draws: int = MAX_DRAWS) -> tuple[Array, Feasibility, dict[str, int]]:
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
    sampler = qmc.Sobol(d=dof, scramble=True, seed=np.random.default_rng(seed))
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


def _order_measured(checker: FeasibilityChecker, q: Array, speed: Array, home: Array,
                    rounds: int = 3) -> NDArray[np.intp]:
    """Order poses by move time; re-run 2-opt with penalties on moves that collide."""
    order = order_poses(q, speed, start=home)
    D = move_times(q[:, None, :], q[None, :, :], speed)
    s = move_times(home[None, :], q, speed)
    penalty = 10.0 * float(D.max() + 1.0)
    for _ in range(rounds):
        seq = q[order]
        starts = np.vstack([home[None, :], seq[:-1]])
        clear = checker.path_clear(starts, seq)
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


def _detours(checker: FeasibilityChecker, seq: Array, home: Array, pool: Array, speed: Array,
             *, tries: int = 64) -> tuple[Array, NDArray[np.bool_]]:
    """Insert one collision-free detour pose into every move whose straight path collides.

    The detour is the pool pose with the shortest total time a -> c -> b whose two moves are
    both clear; moves without such a pose stay as they are (flagged by the caller).

    Returns
    -------
    q : ndarray, shape (m', dof)
        The sequence with detours.
    is_detour : ndarray of bool, shape (m',)
    """
    starts = np.vstack([home[None, :], seq[:-1]])
    clear = checker.path_clear(starts, seq)
    rows: list[Array] = []
    flags: list[bool] = []
    for i in range(len(seq)):
        if not clear[i] and len(pool):
            a, b = starts[i], seq[i]
            cost = move_times(a, pool, speed) + move_times(pool, b, speed)
            cand = np.argsort(cost, kind="stable")[:tries]
            c = pool[cand]
            ok = (checker.path_clear(np.broadcast_to(a, c.shape), c)
                  & checker.path_clear(c, np.broadcast_to(b, c.shape)))
            if ok.any():
                rows.append(c[int(np.argmax(ok))])
                flags.append(True)
        rows.append(seq[i])
        flags.append(False)
    return np.array(rows), np.array(flags, dtype=bool)


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
    seed: int = 0,
    candidates: int = 4096,
    max_draws: int = MAX_DRAWS,
    exchange_passes: int = 2,
) -> Plan:
    """Plan a calibration campaign for one robot in one cell.

    Parameters
    ----------
    robot
        Description, built-in name or robot TOML path.
    cell
        Cell description, built-in name (``"demo"``) or TOML path.
    count
        Calibration poses, chosen D-optimally for ``model`` from the feasible candidates.
    model
        ``"constant"``, ``"high-order"``, ``"auto"`` (see :func:`model_spec`) or a spec.
    validation
        Validation poses: a seeded random sample of the remaining feasible candidates
        (disjoint from the calibration set; random so that they represent the workspace).
    cpa
        Add single-joint circle-point-analysis sweeps, ``cpa_points`` per joint.
    iso
        Add the ISO 9283 test-cube poses P1..P5 (a warning if no cube fits).
    seed
        Seeds the Sobol scrambling, the validation sample and the CPA jitter; the plan is a
        deterministic function of its inputs and this seed.
    candidates
        Feasible candidates to choose from (more draws are made until there are this many,
        up to ``max_draws`` Sobol points).
    exchange_passes
        Fedorov exchange passes after the greedy D-optimal build-up.

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
    if isinstance(robot, RobotDescription):
        robot_name, rob = robot.name, robot
    else:
        robot_name, rob = str(robot), load_robot(robot)
    if isinstance(cell, Cell):
        the_cell, cell_source = cell, f"<{cell.name}>"
    else:
        the_cell, cell_source = load_cell(cell), str(cell)
        if not cell_source.endswith(".toml") and cell_source in builtin_cells():
            cell_source = f"builtin:{cell_source}"
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
    spec = model_spec(rob, model)
    model_name = model if isinstance(model, str) else spec.label
    checker = FeasibilityChecker(rob, the_cell)
    home = _home(rob, the_cell, checker.ranges)
    warnings: list[str] = []

    # -- candidates and selection -------------------------------------------------------------
    target = max(candidates, 2 * (count + validation))
    q_c, feas_c, counts = draw_candidates(checker, target=target, seed=seed,
                                          max_draws=max_draws)
    n_c = len(q_c)
    if n_c < count + validation:
        why = ", ".join(f"{k} {v}" for k, v in counts.items()
                        if k not in ("drawn", "screened") and v)
        detail = (f"of the {counts['screened']} facing the tracker, rejected by: {why}"
                  if counts["screened"] else "none faces the tracker within the acceptance "
                  "angle and range")
        raise ConfigError(
            f"only {n_c} of {counts['drawn']} candidate poses are feasible in cell "
            f"{the_cell.name!r}, fewer than the {count + validation} requested ({detail}); "
            "check the tracker position, reflector direction and keep-out boxes")
    # weight each candidate by the tracker's noise there (radial vs transverse, growing with
    # range), as the maximum-likelihood fit will
    W = whitening(feas_c.reflector, TrackerSigma(position=tuple(checker.tracker)))
    ds = DesignSpace(rob, spec, q_c, np.asarray(checker.tool_offset), weights=W)
    if count < ds.min_poses:
        raise ConfigError(
            f"count {count} is below the {ds.min_poses} poses the {model_name} model needs "
            f"({ds.identifiable} identifiable parameters, 3 equations per pose; "
            f"{ds.recommended_poses} recommended)")
    if count < ds.recommended_poses:
        warnings.append(f"{count} calibration poses are fewer than the {ds.recommended_poses} "
                        f"recommended for {ds.identifiable} identifiable parameters")
    cal = ds.select(count, exchange_passes=exchange_passes)
    rest = np.setdiff1d(np.arange(n_c), cal)
    rng_val = np.random.default_rng([seed, 1])
    val = np.sort(rng_val.choice(rest, size=validation, replace=False)) if validation else (
        np.zeros(0, dtype=np.intp))
    baseline = np.random.default_rng([seed, 2]).choice(n_c, size=count, replace=False)
    obs = ObservabilitySection(calibration=_obs_info(ds.observability(cal)),
                               random_baseline=_obs_info(ds.observability(baseline)))

    # -- extras ---------------------------------------------------------------------------------
    sweeps = []
    if cpa:
        sweeps = cpa_sweeps(checker, q_c, points=cpa_points, rng=np.random.default_rng([seed, 3]))
        got = {s.joint for s in sweeps}
        missing = [j for j in range(1, rob.dof + 1) if j not in got]
        if missing:
            warnings.append("no CPA sweep with the reflector visible throughout was found for "
                            f"joint(s) {', '.join(map(str, missing))}")
        for s in sweeps:
            if s.width < math.radians(30.0):
                warnings.append(f"CPA sweep of joint {s.joint} spans only "
                                f"{math.degrees(s.width):.0f} deg: a poor circle fit")
    cube = iso_cube(checker, q_c, feas_c) if iso else None
    if iso and cube is None:
        warnings.append("no feasible ISO 9283 cube was found; iso-P1..P5 left out")

    # -- ordering -------------------------------------------------------------------------------
    speed = np.array([j.max_speed for j in rob.joints]) * the_cell.motion.speed_fraction
    meas_idx = np.concatenate([cal, val])
    purposes_meas = ["calibration"] * len(cal) + ["validation"] * len(val)
    order = _order_measured(checker, q_c[meas_idx], speed, home)
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
        seq_q.append(cube.q)
        seq_p += [f"iso-P{k}" for k in range(1, 6)]
    q_seq, detour = _detours(checker, np.vstack(seq_q), home, q_c, speed)
    it = iter(seq_p)
    seq_p = ["via" if d else next(it) for d in detour]
    max_step = math.radians(the_cell.motion.max_joint_step_deg)
    q_all, is_via = insert_via_points(q_seq, max_step, start=home)
    purposes: list[str] = []
    it = iter(seq_p)
    for v in is_via:
        purposes.append("via" if v else next(it))

    # the file holds degrees rounded to 1e-6 deg (17 nrad); check what is written
    q_deg = np.round(np.degrees(q_all), 6) + 0.0
    q_all = np.radians(q_deg)
    final = checker.check(q_all)
    clear = checker.path_clear(np.vstack([home[None, :], q_all[:-1]]), q_all)
    bad = [i for i, p in enumerate(purposes) if p != "via" and not final.ok[i]]
    if bad:  # pragma: no cover - margins of exactly zero cut by rounding
        raise ConfigError(f"internal: planned poses {bad[:5]} fail their checks after rounding")
    blocked = int(np.count_nonzero(~clear))
    if blocked:
        warnings.append(f"{blocked} move(s) could not be verified collision free along the "
                        "joint-interpolated path (move_clear = false): teach a detour there")

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
            move_clear=bool(clear[i])))
    prev = np.vstack([home[None, :], q_all[:-1]])
    motion = MotionInfo(
        max_joint_step_deg=the_cell.motion.max_joint_step_deg,
        speed_fraction=the_cell.motion.speed_fraction,
        home_deg=[round(float(v), 6) for v in np.degrees(home)],
        move_time_s=round(float(move_times(prev, q_all, speed).sum()), 3),
        joint_travel_deg=[round(float(v), 3) for v in np.degrees(np.abs(q_all - prev).sum(0))],
        via_points=purposes.count("via"), blocked_moves=blocked)
    rejected = {k: v for k, v in counts.items() if k not in ("drawn", "screened")}
    return Plan(
        robocal_version=__version__,
        robot=RobotInfo(name=robot_name, source=rob.source, description=rob.to_dict()),
        cell=the_cell, cell_source=cell_source, seed=seed,
        model=ModelInfo(name=model_name, label=spec.label, parameters=len(ds.names)),
        candidates=CandidateInfo(drawn=counts["drawn"], screened=counts["screened"],
                                 feasible=n_c, rejected=rejected),
        observability=obs, unidentifiable=list(ds.unidentifiable), motion=motion,
        iso9283=None if cube is None else IsoInfo(
            centre_mm=[round(float(v) * 1e3, 3) for v in cube.centre],
            side_mm=round(cube.side * 1e3, 3)),
        cpa=[CpaInfo(joint=s.joint, span_deg=[round(math.degrees(v), 3) for v in s.span],
                     points=len(s.q)) for s in sweeps],
        warnings=warnings, poses=poses)
