"""``robocal demo``: a whole calibration campaign against simulated devices, in one command.

What it does (everything in-process, loopback only, no arguments needed):

1. starts the FANUC RMI controller and LTP/1 laser-tracker simulators around one virtual
   FANUC LR Mate 200i with planted constant and joint-dependent errors (and a few % of
   injected beam breaks / unstable readings / garbage lines); with ``--robot ur10``, the
   Universal Robots simulator around a virtual UR10 instead of the FANUC one;
2. plans the campaign (stratified calibration poses, validation poses, CPA sweeps);
3. runs it through the real drivers and the daemon's campaign engine, with an SQLite store;
4. fits the constant, high-order and auto models (and CPA), and writes the report;
5. compensates the validation targets with each model and measures them again (a model
   comparison; nothing is pushed yet);
6. approves the fit and pushes the validation targets, compensated with the approved model,
   to the simulated controller's position registers (journaled, read back, verified,
   audited); the daemon then moves the robot to the pushed values and measures them with the
   tracker, before and after (the number the acceptance is about);
7. prints a summary table and says where the files are.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from robocal._core.model_names import CPA, MODELS, NOMINAL
from robocal.cli._command import command, seed
from robocal.cli._defaults import (
    DEFAULT_SEED,
    SCENARIO_HELP,
    VALIDATION_HELP,
    default_validation,
)


def register(sub: Any) -> None:
    """Add the ``demo`` subcommand."""
    p = command(sub, "demo", run)
    p.add_argument("--out", type=Path, default=Path("robocal-demo"),
                   help="output directory (default ./robocal-demo; replaced)")
    p.add_argument("--poses", type=int, default=250,
                   help="calibration poses (default 250; the high-order model needs about 64)")
    p.add_argument("--validation", type=int, default=None,
                   help=VALIDATION_HELP)
    p.add_argument("--seed", type=seed, default=DEFAULT_SEED,
                   help=f"seed of the virtual robot and plan (default {DEFAULT_SEED}, as plan, "
                        "simulate and sim)")
    p.add_argument("--scenario", default="paper", help=SCENARIO_HELP)
    p.add_argument("--fault-rate", type=float, default=0.03,
                   help="injected tracker fault rate per reading (default 0.03)")
    p.add_argument("--robot", default="fanuc_lrmate200i",
                   help="virtual robot: fanuc_lrmate200i (default; FANUC RMI simulator) or ur10 "
                        "(Universal Robots simulator: Dashboard, RTDE, primary interface)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Run the demo (one ``asyncio.run``)."""
    from robocal.errors import ConfigError

    if args.poses < 30:
        raise ConfigError("--poses must be at least 30 (the high-order model needs them)")
    if not 0.0 <= args.fault_rate <= 0.5:
        raise ConfigError("--fault-rate must be within [0, 0.5]")
    return asyncio.run(_demo(args))


class _Progress:
    """A one-line progress bar on stdout (plain lines when stdout is not a terminal)."""

    def __init__(self, quiet: bool) -> None:
        self.tty = sys.stdout.isatty() and not quiet
        self.quiet = quiet
        self._last = 0.0
        self._printed: tuple[str, int] | None = None

    def step(self, text: str) -> None:
        if self.quiet:
            return
        if self.tty:
            sys.stdout.write("\r\x1b[K")
        sys.stdout.write(f"{text}\n")
        sys.stdout.flush()

    def bar(self, label: str, done: int, total: int, extra: str = "") -> None:
        if self.quiet:
            return
        now = time.monotonic()
        if self._printed == (label, done):
            return
        self._printed = (label, done)
        if not self.tty:
            if done == total or now - self._last > 5.0:
                self._last = now
                sys.stdout.write(f"  {label}: {done}/{total} {extra}\n")
                sys.stdout.flush()
            return
        width = 32
        filled = round(width * done / total) if total else 0
        sys.stdout.write(f"\r\x1b[K  {label} [{'#' * filled}{'.' * (width - filled)}] "
                         f"{done}/{total} {extra}")
        if done == total:
            sys.stdout.write("\n")
        sys.stdout.flush()


def _plan(args: argparse.Namespace, validation: int) -> tuple[dict[str, Any], str]:
    """The campaign's PLAN.json document (robocal.planning; its errors end the demo)."""
    from robocal.planning import plan_campaign

    plan = plan_campaign(args.robot, "demo", count=args.poses, model="high-order",
                         validation=validation, cpa=True, cpa_points=24, iso=True,
                         seed=args.seed, candidates=1024)
    plan.save(args.out / "PLAN.json")
    return plan.model_dump(mode="json"), "robocal.planning (stratified design, demo cell)"


async def _follow(svc: Any, cid: str, progress: _Progress, label: str,
                  until: tuple[str, ...], timeout: float) -> dict[str, Any]:
    """Show progress of one campaign until it reaches one of ``until`` (or a final state)."""
    total = svc.store.campaign(cid).poses_total
    retries = 0
    async with asyncio.timeout(timeout), svc.events.subscribe() as q:
        while True:
            rec = svc.store.campaign(cid)
            if rec.state.value in until or rec.state.value in ("aborted", "faulted"):
                progress.bar(label, rec.poses_measured, total,
                             f"{retries} retries" if retries else "")
                return svc.status(cid)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.5):
                    ev = await q.get()
                    if ev is None:
                        raise RuntimeError("the service stopped")
                    if ev.get("campaign") != cid:
                        continue
                    if ev["kind"] == "retry":
                        retries += 1
                    if ev["kind"] == "pose":
                        progress.bar(label, int(ev["poses_measured"]), total,
                                     f"{retries} retries" if retries else "")


def _fmt(v: Any, digits: int = 3, unit: str = "") -> str:
    if isinstance(v, int | float) and math.isfinite(float(v)):
        return f"{v:.{digits}f}{unit}"
    return "-"


async def _demo(args: argparse.Namespace) -> int:
    from robocal.daemon.logging import configure_logging

    t_start = time.perf_counter()
    out: Path = args.out.resolve()
    if out.exists():
        if not (out / "PLAN.json").exists() and any(out.iterdir()):
            from robocal.errors import ConfigError

            raise ConfigError("exists and does not look like a demo directory; choose another "
                              "--out", source=str(out))
        shutil.rmtree(out)
    out.mkdir(parents=True)
    args.out = out
    with (out / "daemon.log").open("w") as log_file:
        # The daemon's JSON log goes to a file; the console shows progress and results.
        configure_logging("info", "json", stream=log_file)
        try:
            figures = await _run(args, t_start)
        finally:
            configure_logging("info", "json", stream=sys.stderr)
    (out / "summary.json").write_text(json.dumps(figures, indent=1, default=str))
    _print_summary(figures)
    # the demo runs the whole job: a push that was refused or failed is a failed demo
    push = figures.get("push")
    if isinstance(push, dict) and push.get("error"):
        return 1
    return 0 if figures.get("state") in ("pushed", "fitted", "approved") else 1


async def _run(args: argparse.Namespace, t_start: float) -> dict[str, Any]:
    import numpy as np

    from robocal.daemon.config import parse_config
    from robocal.daemon.pushing import ideal_positions
    from robocal.daemon.service import CalibrationService
    from robocal.drivers.sim import (
        FanucSimOptions,
        FaultConfig,
        LtpSimOptions,
        SimCell,
        UrSimOptions,
    )

    out: Path = args.out
    progress = _Progress(args.quiet)
    validation = args.validation if args.validation is not None \
        else default_validation(args.poses)
    progress.step(f"robocal demo: virtual {args.robot} with planted '{args.scenario}' errors, "
                  f"{args.fault_rate:.0%} injected tracker faults")

    t0 = time.perf_counter()
    plan_doc, plan_how = _plan(args, validation)
    n_total = sum(1 for p in plan_doc["poses"] if p.get("measure", True))
    progress.step(f"  planned {n_total} poses to measure ({plan_how}) "
                  f"in {time.perf_counter() - t0:.1f} s")

    faults = FaultConfig.uniform(args.fault_rate, seed=args.seed)
    ur = args.robot.startswith("ur")  # UR arms go through the UR simulator and driver
    robot_kind: Literal["universal_robots", "fanuc_rmi"] = (
        "universal_robots" if ur else "fanuc_rmi")
    cell = SimCell(robot=args.robot, scenario=args.scenario, seed=args.seed,
                   fanuc=False if ur else FanucSimOptions(time_scale=0.0005), modbus=False,
                   ur=UrSimOptions(time_scale=0.0005) if ur else False,
                   ltp=LtpSimOptions(time_scale=0.0005), faults=faults)
    figures: dict[str, Any] = {}
    async with cell:
        config = parse_config({
            "data_dir": str(out / "state"),
            "robot_description": args.robot,
            "cell": "demo",
            "robot": {"kind": robot_kind, "options": cell.robot_options(robot_kind)},
            "tracker": {"kind": "ltp", "options": {**cell.tracker_options("tcp"),
                                                   "stab_ms": 100}},
            "limits": {"joint_margin_deg": 0.5, "speed_pct": 100.0},
            "measurement": {"samples": 5, "settle_s": 0.0, "backoff_s": 0.01, "retries": 8},
            "fit": {"models": list(MODELS), "select": "auto", "executor": "process"},
            # the production targets are the validation poses; every one is re-measured
            "compensation": {"kind": "targets", "verify_count": validation},
            "logging": {"level": "info", "format": "json"},
        }, source="demo")
        svc = CalibrationService(config)
        await svc.start()
        try:
            figures = await _campaign(args, svc, plan_doc, progress, ideal_positions, np)
        finally:
            await svc.stop()
            # Let the simulators see the drivers' connections close before they stop.
            await asyncio.sleep(0.1)
    figures["wall_time_s"] = round(time.perf_counter() - t_start, 1)
    injected: dict[str, int] = {}
    for sim in (cell.fanuc_sim, cell.ur_sim, cell.ltp_sim):
        for name, n in (sim.faults.counts if sim is not None else {}).items():
            injected[name] = injected.get(name, 0) + n
    figures["faults_injected"] = injected
    return figures


async def _campaign(args: argparse.Namespace, svc: Any, plan_doc: dict[str, Any],
                    progress: _Progress, ideal_positions: Any, np: Any) -> dict[str, Any]:

    figures: dict[str, Any] = {"robot": args.robot, "scenario": args.scenario,
                               "seed": args.seed}
    t0 = time.perf_counter()
    st = await svc.create(plan_doc, actor="demo", name="demo campaign")
    cid = st["id"]
    st = await _follow(svc, cid, progress, "measuring", ("measured", "fitted"), 600.0)
    t_meas = time.perf_counter() - t0
    figures.update(campaign=cid, poses_measured=st["poses_measured"],
                   poses_total=st["poses_total"], measure_s=round(t_meas, 1),
                   pose_overhead_ms=None if svc._overhead() is None
                   else round(svc._overhead() * 1e3, 2))
    if st["state"] not in ("measured", "fitted"):
        figures["state"] = st["state"]
        figures["reason"] = st["reason"]
        return figures
    progress.step(f"  measured {st['poses_measured']} poses in {t_meas:.1f} s "
                  f"(median {figures['pose_overhead_ms']} ms per pose)")
    t1 = time.perf_counter()
    # the report renders in the fit worker meanwhile (awaited before the summary)
    st = await svc.wait(cid, ["fitted", "faulted"], timeout=600.0, report=False)
    figures["fit_s"] = round(time.perf_counter() - t1, 1)
    figures["fits"] = st["fits"]
    figures["state"] = st["state"]
    if st["state"] != "fitted":
        figures["reason"] = st["reason"]
        return figures
    fitted = [k for k, v in st["fits"].items() if k != NOMINAL and not v.get("error")]
    progress.step(f"  fitted {', '.join(fitted)} "
                  f"in {figures['fit_s']} s (worker process)")
    campaign_dir = svc.config.data_dir / "campaigns" / cid
    figures["files"] = {"plan": str(args.out / "PLAN.json"), "campaign": str(campaign_dir),
                        "store": str(svc.config.db_path)}
    try:
        await _compensate_and_push(args, svc, cid, st, plan_doc, progress, ideal_positions, np,
                                   figures)
    finally:
        await svc.fits.report_settled(cid, 600.0)
    for name in ("html", "json"):
        p = campaign_dir / f"report.{name}"
        if p.exists():
            figures["files"][f"report_{name}"] = str(p)
    return figures


async def _compensate_and_push(args: argparse.Namespace, svc: Any, cid: str,
                               st: dict[str, Any], plan_doc: dict[str, Any],
                               progress: _Progress, ideal_positions: Any, np: Any,
                               figures: dict[str, Any]) -> None:
    """Compensate the validation targets, verify them, approve and push (into ``figures``)."""
    from robocal.daemon import parse_plan, plan_from_poses
    from robocal.errors import RobocalError

    # Compensation of the validation targets, measured again on the simulated robot.
    val = [p for p in svc.store.poses(cid) if p.purpose == "validation"]
    rows = {m.pose_idx: m for m in svc.store.measurements(cid)}
    q_val = np.radians(np.array([p.q_deg for p in val], dtype=float))
    p_val = np.array([rows[p.idx].p_mm for p in val], dtype=float) * 1e-3
    ref = svc.fitted_model(cid, "auto")
    targets = ideal_positions(ref, q_val)
    comp: dict[str, Any] = {"targets": len(val),
                            "before": _errors(np, p_val - targets)}
    from robocal.compensation import compensate

    for name in MODELS:
        if name not in st["fits"] or st["fits"][name].get("error"):
            continue
        cal = svc.fitted_model(cid, name)
        res = compensate(cal, targets, q_val)
        ok = np.asarray(res.ok, dtype=bool)
        if not ok.any():
            comp[name] = {"error": "no target converged"}
            continue
        q_cmd = np.degrees(res.q[ok])
        # each target from home and back: the planner chose every validation pose reachable
        # from home, while a straight move between two of them may not be safe
        home = [float(v) for v in plan_doc["motion"]["home_deg"]]
        legs = [q for t in q_cmd.tolist() for q in (home, t)]
        doc = plan_from_poses(legs, robot=args.robot,
                              purposes=["via", "verification"] * len(q_cmd))
        vst = await svc.create(parse_plan(doc, source="verification", strict=False),
                               actor="demo", name=f"verify {name}", measure_only=True)
        vst = await _follow(svc, vst["id"], progress, f"verifying {name:10s}", ("measured",),
                            300.0)
        if vst["state"] != "measured":
            comp[name] = {"error": f"verification {vst['state']}: {vst['reason']}"}
            continue
        p_after = np.array([m.p_mm for m in svc.store.measurements(vst["id"])]) * 1e-3
        comp[name] = {**_errors(np, p_after - targets[ok]),
                      "converged": int(ok.sum())}
    figures["compensation"] = comp

    # Approve and push the compensated validation targets, then the daemon measures them.
    try:
        await svc.approve(cid, actor="demo")
        pushed = await svc.push(cid, actor="demo")
        figures["state"] = pushed["state"]
        key = pushed["push"]["key"]
        progress.step("  pushed the compensated targets; measuring them again (before/after)")
        await svc.wait_verification(key, timeout=600.0)
        st = svc.status(cid)
        figures["push"] = {**st["push"], "state": st["state"],
                           "verification_detail": (st["compensation"][-1] or {}).get(
                               "verification")}
        figures["compensation_status"] = st["compensation"]
    except RobocalError as err:
        figures["push"] = {"error": str(err)}
        figures["state"] = svc.store.campaign(cid).state.value


def _errors(np: Any, d: Any) -> dict[str, float]:
    e = np.linalg.norm(np.asarray(d, dtype=float), axis=1) * 1e3
    return {"rms_mm": round(float(np.sqrt(np.mean(e**2))), 5),
            "mean_mm": round(float(np.mean(e)), 5), "max_mm": round(float(np.max(e)), 5)}


def _print_summary(f: dict[str, Any]) -> None:
    w = sys.stdout.write
    w("\n")
    if f.get("state") not in ("fitted", "approved", "pushed"):
        w(f"campaign {f.get('campaign', '?')} ended {f.get('state')}: {f.get('reason', '')}\n")
        return
    _print_fits(w, f)
    _print_compensation(w, f.get("compensation") or {})
    _print_push(w, f.get("push") or {})
    files = f.get("files") or {}
    w(f"\nDone in {f.get('wall_time_s')} s (measuring {f.get('measure_s')} s, fitting "
      f"{f.get('fit_s')} s).\n")
    if files.get("report_html"):
        w(f"Report:  {files['report_html']}\n         {files.get('report_json', '')}\n")
    else:
        w("Report:  not written (see daemon.log)\n")
    w(f"Files:   {Path(files.get('plan', '.')).parent} (PLAN.json, summary.json, daemon.log, "
      "state/ with the SQLite store and MODEL-*.json)\n")


def _print_fits(w: Callable[[str], Any], f: dict[str, Any]) -> None:
    """The held-out accuracy table of every fitted model."""
    fits = f.get("fits", {})
    w(f"Held-out accuracy ({f.get('poses_measured')} poses measured; validation poses not "
      "used for fitting)\n")
    w(f"  {'model':12s} {'RMS mm':>9s} {'mean mm':>9s} {'max mm':>9s} {'% described':>12s}"
      f" {'fit s':>7s}\n")
    for name in (NOMINAL, "cpa classical", CPA, *MODELS):
        s = fits.get(name)
        if name == "cpa classical":  # classical CPA rides in the cpa fit's summary
            det = (fits.get("cpa") or {}).get("details")
            det = det if isinstance(det, dict) else {}
            cls = det.get("classical") or {}
            s = {"validation": cls.get("validation")} if det.get("polish") else None
        if not s:
            continue
        if s.get("error"):
            w(f"  {name:12s} not available: {s['error'][:70]}\n")
            continue
        v = s.get("validation") or {}
        pct = v.get("percent_described_rms")
        if name == NOMINAL:
            pct = 0.0
        w(f"  {name:13s}{_fmt(v.get('rms_mm'), 4):>9s} {_fmt(v.get('mean_mm'), 4):>9s} "
          f"{_fmt(v.get('max_mm'), 4):>9s} {_fmt(pct, 1, ' %'):>12s} "
          f"{_fmt(s.get('seconds'), 2):>7s}\n")
    w("  nominal = nominal kinematics with only the tracker<-base transform and the reflector\n"
      "  fitted: the honest baseline of '% described'.")
    if CPA in fits:
        w(" cpa = Circle Point Analysis from single-joint\n"
          "  sweeps, polished by a constant-model ML fit on the sweep points (cpa classical:\n"
          "  before the polish); its arcs are as wide as the reflector stays visible (spans in\n"
          "  PLAN.json, 'cpa'), and short arcs, small radii and joint-dependent errors limit\n"
          "  what it can recover.")
    w("\n")


def _print_compensation(w: Callable[[str], Any], comp: dict[str, Any]) -> None:
    """Errors measured again at the compensated validation targets."""
    if comp:
        w(f"\nCompensation of {comp.get('targets')} validation targets, measured again\n")
        w(f"  {'commands':22s} {'RMS mm':>9s} {'mean mm':>9s} {'max mm':>9s}\n")
        rows = [("nominal (before)", comp.get("before"))]
        rows += [(f"{m} compensated", comp.get(m)) for m in MODELS if m in comp]
        for label, e in rows:
            if not e:
                continue
            if "error" in e:
                w(f"  {label:22s} {e['error']}\n")
                continue
            w(f"  {label:22s} {_fmt(e['rms_mm'], 4):>9s} {_fmt(e['mean_mm'], 4):>9s} "
              f"{_fmt(e['max_mm'], 4):>9s}\n")


def _print_push(w: Callable[[str], Any], push: dict[str, Any]) -> None:
    """What was pushed and what the robot measured after it."""
    if push:
        if "error" in push:
            w(f"\nPush: {push['error']}\n")
        else:
            w(f"\nApproved ({push.get('model')}) and pushed as push {push.get('key')}: "
              f"{push['kind']} table {push['checksum'][:16]} (journaled, written, read back, "
              "verified, audited)\n")
            w(f"  predicted residual {_fmt(push.get('predicted_rms_mm'), 4)} mm (targets "
              f"solved on the model; its held-out accuracy {_fmt(push.get('model_accuracy_mm'), 4)}"
              f" mm) against {_fmt(push.get('nominal_rms_mm'), 4)} mm nominal\n")
            if push.get("measured_after_rms_mm") is not None:
                w(f"  measured on the robot after the push, {push.get('measured_n')} pushed "
                  f"targets: {_fmt(push.get('measured_before_rms_mm'), 4)} mm RMS before -> "
                  f"{_fmt(push.get('measured_after_rms_mm'), 4)} mm RMS after\n")
            else:
                v = push.get("verification_detail") or {}
                w(f"  not measured after the push: {v.get('reason', push.get('verification'))}"
                  "\n")
