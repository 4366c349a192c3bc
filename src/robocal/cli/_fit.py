"""``robocal fit``: identify an error model from a measurement CSV and write MODEL.json."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from robocal._core.model_names import DEFAULT_MODEL, MODELS
from robocal.cli._command import command, seed


def register(sub: Any) -> None:
    """Add the ``fit`` subcommand."""
    p = command(sub, "fit", run)
    p.add_argument("--robot", help="built-in robot name or robot TOML file (required unless "
                                    "--reuse, which takes the earlier model's robot)")
    p.add_argument("--data", required=True, help="training measurements (CSV)")
    p.add_argument("--model", choices=MODELS,
                   help=f"error model (default {DEFAULT_MODEL}; not with --reuse)")
    p.add_argument("--reuse", metavar="PREVIOUS_MODEL.json",
                   help="keep the joint-dependent terms of an earlier model and refit the "
                        "joint offsets, tracker<-base transform and reflector offset, with the "
                        "link constants held near their earlier values (after re-mastering, "
                        "a crash or a tracker move; valid for the same robot with unchanged "
                        "gears, links and payload; always --validate; see docs/map-reuse.md)")
    p.add_argument("--no-fill-gaps", action="store_true",
                   help="with --reuse: keep every map knot at its earlier value, also where "
                        "the earlier data did not reach (default: the new data fill those "
                        "gaps)")
    p.add_argument("--max-rms-mm", type=float, metavar="MM",
                   help="fail (exit 1, no file written) when the RMS error (validation if "
                        "given, else training) exceeds this")
    p.add_argument("--no-sanity", action="store_true",
                   help="skip the unit and robot-variant plausibility checks")
    p.add_argument("--out", required=True, help="MODEL.json to write (atomically)")
    p.add_argument("--validate", metavar="VAL.csv", help="held-out measurements (CSV)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--tool", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="flange->reflector offset to start from, mm (default: robot file)")
    p.add_argument("--sigma-radial-um", type=float, help="tracker radial sigma, µm")
    p.add_argument("--sigma-transverse-um", type=float, help="tracker transverse sigma, µm")
    p.add_argument("--ignore-point-sigma", action="store_true",
                   help="use the tracker model even where the CSV gives sx,sy,sz")
    p.add_argument("--no-outliers", action="store_true", help="disable outlier detection")
    p.add_argument("--outlier-sigma", type=float,
                   help="fixed outlier threshold in robust sigmas")
    p.add_argument("--order", type=int, help="Fourier order of the high-order model")
    p.add_argument("--map-spacing-deg", type=float, help="joint-angle map knot spacing (auto)")
    p.add_argument("--cv-folds", type=int, help="cross-validation folds (auto)")
    p.add_argument("--seed", type=seed, help="seed of the CV folds (auto)")
    p.add_argument("--point-sigma-floor-mm", type=float, metavar="MM",
                   help="model error combined in quadrature with the data's sx,sy,sz "
                        "(default: estimated from the constant model's residuals; 0 weights "
                        "by the raw per-point sigmas)")
    p.add_argument("--no-fallback", action="store_true",
                   help="do not store the constant-model fallback")


def _options(args: argparse.Namespace) -> Any:
    from dataclasses import replace

    from robocal.identification import FitOptions, TrackerSigma

    kw: dict[str, Any] = {}
    if args.tool is not None:
        kw["tool_m"] = tuple(v * 1e-3 for v in args.tool)
    noise = TrackerSigma()
    if args.sigma_radial_um is not None:
        noise = replace(noise, radial_m=args.sigma_radial_um * 1e-6, radial_per_m=0.0)
    if args.sigma_transverse_um is not None:
        noise = replace(noise, transverse_m=args.sigma_transverse_um * 1e-6,
                        transverse_per_m=0.0)
    kw["noise"] = noise
    kw["use_point_sigma"] = not args.ignore_point_sigma
    if args.point_sigma_floor_mm is not None:
        kw["point_sigma_floor_m"] = args.point_sigma_floor_mm * 1e-3
    kw["detect_outliers"] = not args.no_outliers
    if args.outlier_sigma is not None:
        kw["outlier_sigma"] = args.outlier_sigma
    if args.order is not None:
        kw["order"] = args.order
    if args.map_spacing_deg is not None:
        kw["map_spacing_deg"] = args.map_spacing_deg
    if args.cv_folds is not None:
        kw["cv_folds"] = args.cv_folds
    if args.seed is not None:
        kw["seed"] = args.seed
    kw["fallback"] = not args.no_fallback
    if args.no_fill_gaps:
        kw["reuse_fill_gaps"] = False
    kw["sanity"] = not args.no_sanity
    return FitOptions(**kw)


def run(args: argparse.Namespace) -> int:
    """Fit, save atomically, print a summary."""
    from robocal._core.measurements import MeasurementSet
    from robocal.errors import ConfigError
    from robocal.identification import fit, refit_frozen
    from robocal.kinematics import CalibratedModel, load_robot

    if args.reuse is None and args.robot is None:
        raise ConfigError("--robot is required (unless --reuse)")
    if args.reuse is None and args.model is None:
        args.model = DEFAULT_MODEL
    if args.no_fill_gaps and args.reuse is None:
        raise ConfigError("--no-fill-gaps only applies with --reuse")
    if args.reuse is not None and args.model is not None:
        raise ConfigError("--reuse keeps the earlier model's structure; leave out --model")
    if args.max_rms_mm is not None and not args.max_rms_mm > 0:
        raise ConfigError("--max-rms-mm must be positive")
    previous = CalibratedModel.load(args.reuse) if args.reuse else None
    robot = previous.robot if previous is not None else load_robot(args.robot)
    if previous is not None and args.robot is not None \
            and load_robot(args.robot).name != robot.name:
        raise ConfigError(f"--robot {args.robot} differs from the reused model's robot "
                          f"{robot.name!r}")
    out = Path(args.out)
    if not out.parent.exists():
        raise ConfigError("directory does not exist", source=str(out.parent))
    if out.is_dir():
        raise ConfigError("is a directory", source=str(out))
    data = MeasurementSet.read_csv(args.data, dof=robot.dof)
    val = MeasurementSet.read_csv(args.validate, dof=robot.dof) if args.validate else None
    opts = _options(args)
    if previous is not None:
        res = refit_frozen(previous, data, options=opts, validation=val)
        res.calibrated.data["reused"] = str(args.reuse)
    else:
        res = fit(robot, data, args.model, options=opts, validation=val)
    if args.max_rms_mm is not None:
        acc, on = (res.validation, "validation") if res.validation is not None \
            else (res.train, "training")
        if not acc.rms_m * 1e3 <= args.max_rms_mm:
            sys.stderr.write(f"robocal fit: error: {on} RMS {acc.rms_m * 1e3:.4f} mm exceeds "
                             f"--max-rms-mm {args.max_rms_mm:g}; {out} not written\n")
            return 1
    res.calibrated.data["source"] = str(args.data)
    if args.validate:
        res.calibrated.data["validation_source"] = str(args.validate)
    res.calibrated.save(out)
    summary = res.summary()
    summary["out"] = str(out)
    summary["warnings"] = [*summary.get("warnings", []),
                           *input_warnings(args, robot, data, previous is None)]
    if args.json:
        sys.stdout.write(json.dumps(summary, indent=1) + "\n")
    else:
        sys.stdout.write(format_summary(summary))
    return 0


def _same_file(a: str, b: str) -> bool:
    """Same path or the same bytes (a copy of the training file is no held-out set)."""
    import hashlib

    pa, pb = Path(a), Path(b)
    try:
        if pa.resolve() == pb.resolve():
            return True
        if pa.stat().st_size != pb.stat().st_size:
            return False
        return hashlib.sha256(pa.read_bytes()).digest() == hashlib.sha256(
            pb.read_bytes()).digest()
    except OSError:
        return False


def input_warnings(args: argparse.Namespace, robot: Any, data: Any, fresh: bool) -> list[str]:
    """Warnings about the inputs: the validation file is the training file; an auto fit on
    fewer poses than the full auto model's identifiable parameters need."""
    out: list[str] = []
    if args.validate and _same_file(args.data, args.validate):
        out.append(f"--validate {args.validate} holds the same data as --data {args.data}: "
                   "its figures are training figures, not held-out accuracy")
    if fresh and args.model == "auto":
        import numpy as np

        from robocal.planning import DesignSpace, model_spec

        lim = robot.joint_limits
        q = np.random.default_rng(0).uniform(lim[:, 0], lim[:, 1], (400, robot.dof))
        ds = DesignSpace(robot, model_spec(robot, "auto"), q, np.asarray(robot.tool))
        if len(data) < ds.min_poses:
            out.append(f"{len(data)} poses are fewer than the {ds.min_poses} the auto model "
                       f"needs ({ds.identifiable} identifiable parameters, 3 equations per "
                       f"pose; {ds.recommended_poses} recommended): the auto selection is "
                       "limited to what these poses carry; measure more poses (robocal plan "
                       "--model auto) or fit --model constant")
    return out


def _f(v: Any, fmt: str = "{:.4f}") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)


def format_summary(s: dict[str, Any]) -> str:
    """Human-readable table of a fit summary (mm, %)."""
    tr, va = s["train"], s.get("validation")
    lines = [f"robocal fit: {s['robot']}, model {s['model']} (id {s['model_id']})"]
    n_out = len(s["outliers"])
    lines.append(f"poses: {tr['n']} used, {n_out} outlier(s) excluded"
                 + (f"; validation {va['n']} ({len(s['validation_outliers'])} gross "
                    "outlier(s) screened)" if va else ""))
    rows = [("RMS [mm]", "rms_mm", "{:.4f}"), ("mean [mm]", "mean_mm", "{:.4f}"),
            ("max [mm]", "max_mm", "{:.4f}"),
            ("% described (RMS)", "percent_described_rms", "{:.1f}"),
            ("% described (mean)", "percent_described_mean", "{:.1f}"),
            ("% described (R^2)", "percent_described_r2", "{:.1f}"),
            ("baseline RMS [mm]", "baseline_rms_mm", "{:.4f}")]
    lines.append(f"  {'':24s}{'train':>12s}{'validation':>12s}")
    for label, key, fmt in rows:
        lines.append(f"  {label:24s}{_f(tr[key], fmt):>12s}"
                     f"{_f(va[key], fmt) if va else '-':>12s}")
    lines.append("  baseline = " + s["baseline"])
    lines.append(f"identifiability: rank {s['rank']}, condition number "
                 f"{_f(s['condition_number'], '{:.3g}')}; {len(s['removed'])} parameter(s) "
                 "held fixed (redundant or unobservable)")
    if s["removed"]:
        lines.append("  held fixed: " + ", ".join(s["removed"]))
    lines.append(f"parameters: {s['n_free']} estimated of {s['n_params']} "
                 f"(effective {s['dof_effective']:.1f}); terms "
                 + ", ".join(f"{k} {v}" for k, v in s["terms"].items()))
    lines.append(f"variance factor {_f(s['variance_factor'], '{:.3g}')} "
                 f"(sigma0 {_f(s['sigma0'], '{:.3g}')}); {s['iterations']} iteration(s), "
                 f"{'converged' if s['converged'] else 'NOT converged (' + s['status'] + ')'}, "
                 f"{s['elapsed_s']:.2f} s")
    if s["outliers"]:
        lines.append("outliers: " + ", ".join(s["outliers"]))
    if s.get("validation_outliers"):
        lines.append("validation outliers: " + ", ".join(s["validation_outliers"]))
    groups = [e for e in s.get("selection", []) if e.get("action") == "final"]
    if groups:
        lines.append("auto terms: " + (", ".join(groups[0]["groups"]) or "constant only"))
    thermal = [e for e in s.get("selection", []) if e.get("action") == "thermal"]
    if thermal and thermal[0].get("considered"):
        t = thermal[0]
        lines.append("thermal term: " + (
            "taken, " + ", ".join(f"{c:+.5f}" for c in t["coef_mm_per_c"]) + " mm/degC per link"
            if t["selected"] else f"not taken (CV gain {t['gain_percent']:.2f} %)"))
    for w in s.get("warnings", []):
        lines.append("WARNING: " + w)
    lines.append(f"wrote {s['out']}")
    return "\n".join(lines) + "\n"
