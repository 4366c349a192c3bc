"""``robocal report``: the calibration report of a model file or of a daemon campaign.

    robocal report [--model] MODEL.json --out report.html [--data MEAS.csv] [--validate VAL.csv]
                   [--compare NAME=MODEL.json ...]
    robocal report CAMPAIGN_ID --out report.html [--config CONFIG.toml]

Writes ``report.html`` (self-contained) and ``report.json`` beside it, prints the verdict.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robocal.cli._command import command

if TYPE_CHECKING:
    from robocal.report import Acceptance, ReportInput

DEFAULT_CONFIG = "/etc/robocal/config.toml"


def register(sub: Any) -> None:
    """Add the ``report`` subcommand."""
    p = command(sub, "report", run)
    p.add_argument("source", metavar="MODEL.json|CAMPAIGN_ID", nargs="?",
                   help="a model file or a campaign id (or give --model)")
    p.add_argument("--model", metavar="MODEL.json",
                   help="the model file to report on (as 'robocal fit --out' wrote it)")
    p.add_argument("--out", default="report.html", metavar="report.html",
                   help="output page (default report.html); the JSON goes beside it")
    p.add_argument("--data", metavar="MEAS.csv", help="calibration measurements")
    p.add_argument("--validate", metavar="VAL.csv", help="held-out validation measurements")
    p.add_argument("--compare", action="append", default=[], metavar="NAME=MODEL.json",
                   help="another model to compare (e.g. constant=MODEL-constant.json, "
                        "nominal=..., cpa=...); repeatable")
    p.add_argument("--config", metavar="CONFIG.toml",
                   help="daemon configuration, for CAMPAIGN_ID (default $ROBOCAL_CONFIG, "
                        f"then {DEFAULT_CONFIG})")
    p.add_argument("--selected", metavar="NAME", help="model the verdict is about")
    p.add_argument("--max-rms-mm", type=float, metavar="MM",
                   help="acceptance: held-out RMS limit (default 0.5 mm for a robot whose "
                        "link lengths |a|+|d| add up to at most 2 m, in proportion above, e.g. "
                        "1.01 mm for the KUKA KR 210 R3100's 4.06 m)")
    p.add_argument("--max-error-mm", type=float, metavar="MM",
                   help="acceptance: held-out max-error limit (default: none)")
    p.add_argument("--min-described", type=float, metavar="PERCENT",
                   help="acceptance: %% of the nominal error to describe (default 50)")
    p.add_argument("--no-sanity", action="store_true",
                   help="skip the unit plausibility checks of --data/--validate (joints in "
                        "radians, positions in metres), as 'robocal fit --no-sanity'")
    p.add_argument("--targets", metavar="FILE",
                   help="the production program (TARGETS.csv or JOINTS.csv), overlaid on the "
                        "per-joint coverage")
    p.add_argument("--title", help="page title")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def _model_name(kind: str) -> str:
    from robocal.report import KNOWN_MODELS

    k = kind.split(":", 1)[0]
    return k if k in KNOWN_MODELS else "model"


def _acceptance(args: argparse.Namespace, base: Acceptance | None = None) -> Acceptance:
    from robocal.report import Acceptance

    kw: dict[str, Any] = {}
    if args.max_rms_mm is not None:
        kw["max_rms_mm"] = args.max_rms_mm
        kw["scale_with_reach"] = False  # a limit given is the limit
    if args.max_error_mm is not None:
        kw["max_error_mm"] = args.max_error_mm
    if args.min_described is not None:
        kw["min_percent_described"] = args.min_described
    return dataclasses.replace(base or Acceptance(), **kw)


def _compare(items: Sequence[str]) -> dict[str, Any]:
    from robocal.errors import ConfigError
    from robocal.kinematics import CalibratedModel

    out = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ConfigError(f"--compare needs NAME=MODEL.json, got {item!r}")
        out[name] = CalibratedModel.load(path)
    return out


def input_from_model_file(path: str | Path, *, data: str | None = None,
                          validate: str | None = None, compare: Sequence[str] = (),
                          sanity: bool = True) -> ReportInput:
    """A :class:`~robocal.report.ReportInput` from a MODEL.json (+ optional CSV files)."""
    from robocal._core.measurements import MeasurementSet
    from robocal.kinematics import CalibratedModel
    from robocal.report import ReportInput

    cm = CalibratedModel.load(path)
    dof = cm.robot.dof
    name = _model_name(cm.kind)
    models: dict[str, Any] = {**_compare(compare), name: cm}
    cal = MeasurementSet.read_csv(data, dof=dof) if data else None
    val = MeasurementSet.read_csv(validate, dof=dof) if validate else None
    if sanity:  # the same refusal as 'robocal fit' (one line, exit 2)
        from robocal.identification import sanity_check

        for what, ms in ((data, cal), (validate, val)):
            if ms is not None:
                sanity_check(cm.robot, ms, what=str(what))
    notes = [f"model file: {Path(path).name}"]
    if cal is None and val is None:
        notes.append("made from the model file alone: accuracy figures are the metrics stored "
                     "in it")
    return ReportInput(models=models, calibration=cal, validation=val, robot=cm.robot,
                       selected=name, notes=notes)


def input_from_campaign(cid: str, config: str | Path) -> ReportInput:
    """A :class:`~robocal.report.ReportInput` from a campaign in the daemon's SQLite store.

    Uses the store's measurements (purpose ``calibration`` / ``validation`` / ``iso-Pk``),
    its fitted models (MODEL.json texts and fit summaries: outliers, status) and its
    selected model.
    """
    from robocal._core.measurements import MeasurementSet
    from robocal.daemon.config import load_config
    from robocal.daemon.fitting import measurement_set, rows_by_purpose, temperature_log
    from robocal.daemon.schemas import Measurement
    from robocal.daemon.store import Store
    from robocal.errors import ConfigError
    from robocal.kinematics import CalibratedModel
    from robocal.report import MeasurementLog, ReportInput, model_entry

    cfg = load_config(config)
    db = Path(cfg.db_path)
    if not db.exists():
        raise ConfigError("the daemon's store does not exist (has the daemon run?)",
                          source=str(db))
    store = Store(db).open()
    try:
        rec = store.campaign(cid)
        rows = store.measurements(cid)
        fits = store.fits(cid)
        texts = {name: store.model_json(cid, name) for name in fits}
    finally:
        store.close()
    models: dict[str, Any] = {}
    for name, summ in fits.items():
        text = texts.get(name)
        if not text:
            continue
        cm = CalibratedModel.from_dict(json.loads(text), source=f"campaign {cid} / {name}")
        summ = summ if isinstance(summ, dict) else {}
        stored = {k: summ[k] for k in ("train", "validation") if isinstance(summ.get(k), dict)}
        # the same reading of MODEL.json as the daemon's own report (removed parameters,
        # rank and singular values from the fit), with the store's summaries on top
        base = model_entry(name, cm)
        models[name] = dataclasses.replace(
            base, outliers=tuple(str(o) for o in summ.get("outliers") or ()) or base.outliers,
            status=str(summ.get("status", "")) or base.status,
            stored=stored or dict(cm.metrics))

    def mset(sel: list[Measurement], *, commanded: bool = False) -> MeasurementSet | None:
        return measurement_set(sel, commanded=commanded) if sel else None

    by_purpose = rows_by_purpose(rows)
    cal = mset(by_purpose.calibration)
    val = mset(by_purpose.validation)
    selected = rec.selected_model if rec.selected_model in models else None
    iso_rows = by_purpose.iso
    # commanded joints: AP compares with where the controller meant to go
    iso_set = mset(iso_rows, commanded=True)
    weather: list[dict[str, float]] = []
    for r in rows:  # each change of the weather once, not a copy per pose
        if r.weather and (not weather or weather[-1] != dict(r.weather)):
            weather.append(dict(r.weather))
    log = MeasurementLog(planned=rec.poses_total, measured=len(rows),
                         retries=sum(max(0, r.attempts - 1) for r in rows),
                         beam_losses=sum(r.beam_losses for r in rows),
                         weather=weather, tracker=str(cfg.tracker.kind),
                         controller=str(cfg.robot.kind),
                         extra={"campaign state": rec.state.value,
                                "campaign name": rec.name, "created by": rec.created_by},
                         **temperature_log(rows))
    robot = next((m.calibrated.robot for m in models.values()), None)
    targets = None
    if robot is not None and cfg.compensation.targets_file is not None:
        from robocal.planning import read_program_joints

        # the program the push compensates, overlaid on the coverage
        targets = read_program_joints(cfg.compensation.targets_file, dof=robot.dof)
    return ReportInput(models=models, calibration=cal, validation=val, robot=robot,
                       selected=selected, iso_measurements=iso_set, targets=targets,
                       iso_purposes=[r.purpose for r in iso_rows], log=log, campaign_id=cid,
                       notes=[f"plan digest {rec.plan_digest}",
                              f"config digest {rec.config_digest}"])


def _daemon_config(given: str | None) -> str:
    """The daemon configuration for a campaign source: --config, $ROBOCAL_CONFIG, the default."""
    import os

    from robocal.errors import ConfigError

    path = given or os.environ.get("ROBOCAL_CONFIG") or DEFAULT_CONFIG
    if not Path(path).exists():
        what = (f"--config {path}: file not found" if given else
                f"ROBOCAL_CONFIG={path}: file not found" if os.environ.get("ROBOCAL_CONFIG")
                else f"no daemon configuration at {path}")
        raise ConfigError(
            f"{what}. A campaign id is looked up in the daemon's "
            "store: give --config FILE (the daemon's configuration) or set ROBOCAL_CONFIG; "
            "for a model file give its path (MODEL.json)")
    return path


def run(args: argparse.Namespace) -> int:
    """Build the input, write the report, print where and the verdict."""
    from robocal.errors import ConfigError
    from robocal.report import write_report

    if (args.source is None) == (args.model is None):
        raise ConfigError("give one source: MODEL.json (or --model MODEL.json) or a "
                          "CAMPAIGN_ID")
    if args.model is not None:
        args.source = args.model
    src = Path(args.source)
    if args.model is not None or src.suffix.lower() == ".json" or src.exists():
        inp = input_from_model_file(src, data=args.data, validate=args.validate,
                                    compare=args.compare, sanity=not args.no_sanity)
    else:
        if args.data or args.validate or args.compare:
            raise ConfigError("--data, --validate and --compare apply to a MODEL.json source, "
                              "not to a campaign")
        inp = input_from_campaign(args.source, _daemon_config(args.config))
    if args.selected:
        inp.selected = args.selected
    if args.title:
        inp.title = args.title
    if args.targets:
        from robocal.planning import read_program_joints

        dof = inp.robot.dof if inp.robot is not None else None
        if dof is None:
            raise ConfigError("--targets needs a robot (a model file or campaign)")
        inp.targets = read_program_joints(args.targets, dof=dof)
    inp.acceptance = _acceptance(args, inp.acceptance)
    html_path, json_path = write_report(inp, args.out)
    summary = json.loads(json_path.read_text(encoding="utf-8"))
    if args.json:
        sys.stdout.write(json.dumps({"html": str(html_path), "json": str(json_path),
                                     "verdict": summary["verdict"]}) + "\n")
    else:
        sys.stdout.write(f"{summary['verdict']['headline']}\nwrote {html_path} and "
                         f"{json_path}\n")
    # scripts and CI gate on the exit code: a failed calibration is not a success
    return 1 if summary["verdict"].get("outcome") == "failed" else 0
