"""``robocal fit`` and ``robocal predict`` end to end on the virtual LR Mate 200i."""

from __future__ import annotations

import csv
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tests._designs import thin_j6_design

from robocal._core.measurements import MeasurementSet, write_joints_csv
from robocal.cli.main import main
from robocal.kinematics import CalibratedModel
from robocal.simulation import VirtualCell


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    cell = VirtualCell.create("fanuc_lrmate200i", "paper", seed=5)
    rng = np.random.default_rng(6)
    d = tmp_path_factory.mktemp("fitcli")
    q, p, _s, idx = cell.simulate(cell.random_joints(250, rng), rng, outlier_fraction=0.01)
    train = MeasurementSet(q, p)
    train.write_csv(d / "train.csv")
    qv, pv, sv, _ = cell.simulate(cell.random_joints(150, rng), rng)
    MeasurementSet(qv, pv, sv).write_csv(d / "val.csv")
    write_joints_csv(d / "joints.csv", qv[:10], extra={"pose_id": [f"V{i}" for i in range(10)]})
    np.save(d / "truth_val.npy", cell.reflector_position(qv[:10]))
    (d / "planted.txt").write_text("\n".join(train.pose_id[i] for i in idx))
    return {"dir": d, "train": d / "train.csv", "val": d / "val.csv",
            "joints": d / "joints.csv"}


def _fit(files, tmp_path, model, *extra):
    out = tmp_path / f"{model}.json"
    code = main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(files["train"]),
                 "--model", model, "--out", str(out), "--validate", str(files["val"]), *extra])
    return code, out


def test_fit_writes_a_model_and_prints_a_table(files, tmp_path, capsys):
    code, out = _fit(files, tmp_path, "high-order")
    assert code == 0 and out.exists()
    text = capsys.readouterr().out
    assert "% described (RMS)" in text and "baseline" in text and "reflector" in text
    assert "held fixed" in text and str(out) in text
    planted = set(files["dir"].joinpath("planted.txt").read_text().split())
    assert planted and all(p in text for p in planted)           # outliers listed by id
    cal = CalibratedModel.load(out)
    assert cal.kind == "high-order" and cal.fallback is not None
    assert cal.data["source"] == str(files["train"])
    assert cal.metrics["validation"]["percent_described_rms"] > 95


def test_fit_json_output_and_predict_round_trip(files, tmp_path, capsys):
    code, out = _fit(files, tmp_path, "constant", "--json")
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["model"] == "constant" and summary["rank"] == 27
    assert summary["validation"]["rms_mm"] > 0 and summary["out"] == str(out)
    pred = tmp_path / "pred.csv"
    assert main(["predict", "--model", str(out), "--joints", str(files["joints"]),
                 "--out", str(pred)]) == 0
    with pred.open() as f:
        rows = list(csv.DictReader(f))
    assert [r["pose_id"] for r in rows] == [f"V{i}" for i in range(10)]
    p = np.array([[float(r[k]) for k in "xyz"] for r in rows]) * 1e-3
    truth = np.load(files["dir"] / "truth_val.npy")
    assert np.max(np.linalg.norm(p - truth, axis=1)) < 0.8e-3       # constant-model accuracy
    sig = np.array([[float(r[k]) for k in ("sx", "sy", "sz")] for r in rows])
    assert np.all(sig > 0) and np.all(sig < 0.1)
    assert all(r["in_coverage"] == "1" for r in rows)


def test_predict_json_summary(files, tmp_path, capsys):
    _code, out = _fit(files, tmp_path, "constant")
    capsys.readouterr()
    pred = tmp_path / "p.csv"
    assert main(["predict", "--model", str(out), "--joints", str(files["joints"]),
                 "--out", str(pred), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["n"] == 10 and s["outside_coverage"] == 0


def _expect_error(capsys, argv, out: Path, match: str) -> None:
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and match in err
    assert not out.exists()
    assert not list(out.parent.glob(f".{out.name}*"))               # no temporary left behind


def test_bad_inputs_give_one_line_errors_and_no_file(files, tmp_path, capsys):
    d = tmp_path
    out = d / "m.json"
    base = ["fit", "--robot", "fanuc_lrmate200i", "--model", "constant", "--out", str(out)]
    text = files["train"].read_text().splitlines()
    (d / "nocol.csv").write_text("\n".join(line.rsplit(",", 1)[0] for line in text) + "\n")
    _expect_error(capsys, [*base, "--data", str(d / "nocol.csv")], out, "'z'")
    rows = list(text)
    rows[5] = ",".join([*rows[5].split(",")[:-1], "nan"])
    (d / "nan.csv").write_text("\n".join(rows) + "\n")
    _expect_error(capsys, [*base, "--data", str(d / "nan.csv")], out, "row 6")
    five = [",".join(line.split(",")[:6] + line.split(",")[7:]) for line in text]
    (d / "five.csv").write_text("\n".join(five) + "\n")
    _expect_error(capsys, [*base, "--data", str(d / "five.csv")], out, "6 joints")
    (d / "few.csv").write_text("\n".join(text[:9]) + "\n")
    _expect_error(capsys, [*base, "--data", str(d / "few.csv")], out, "too few poses")
    _expect_error(capsys, [*base, "--data", str(d / "missing.csv")], out, "not found")
    _expect_error(capsys, ["fit", "--robot", "no_such_robot", "--model", "constant",
                           "--out", str(out), "--data", str(files["train"])], out, "built-in")
    _expect_error(capsys, ["predict", "--model", str(d / "none.json"), "--joints",
                           str(files["joints"]), "--out", str(out)], out, "not found")


def test_non_convergence_is_an_error_and_writes_nothing(files, tmp_path, capsys, monkeypatch):
    from robocal.identification import _engine, _solver

    real = _solver.levenberg_marquardt

    def stuck(*a, **k):
        # stopped by max_iter, still descending, far from the minimum
        info = real(*a, **{**k, "max_iter": 1})
        return dataclasses.replace(info, status=_solver.MAX_ITERATIONS, last_decrease=0.1,
                                   remaining=0.5)

    monkeypatch.setattr(_engine, "levenberg_marquardt", stuck)
    out = tmp_path / "nc.json"
    _expect_error(capsys, ["fit", "--robot", "fanuc_lrmate200i", "--data", str(files["train"]),
                           "--model", "constant", "--out", str(out)], out, "did not converge")


def test_console_script_runs(files, tmp_path):
    out = tmp_path / "cs.json"
    r = subprocess.run([sys.executable, "-m", "robocal", "fit", "--robot", "fanuc_lrmate200i",
                        "--data", str(files["train"]), "--model", "constant", "--out",
                        str(out), "--json"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["model"] == "constant" and out.exists()


# heavy packages that the fit/predict path must not load (start-up time, issue 14)
_NOT_ON_FIT_PATH = ("scipy", "numpy.f2py", "aiohttp", "pydantic", "structlog", "asyncio")
_IMPORTED = """
import sys
from robocal.cli.main import main
code = main(sys.argv[1:])
heavy = sorted(m for m in sys.modules if m.split(".")[0] in {roots} or m in {full})
print("HEAVY=" + ",".join(heavy))
sys.exit(code)
"""


def _modules_loaded_by(*argv: str) -> tuple[int, list[str], str]:
    roots = {m for m in _NOT_ON_FIT_PATH if "." not in m}
    full = {m for m in _NOT_ON_FIT_PATH if "." in m}
    src = _IMPORTED.format(roots=sorted(roots), full=sorted(full))
    out = subprocess.run([sys.executable, "-c", src, *argv], capture_output=True, text=True,
                         timeout=120)
    line = [s for s in out.stdout.splitlines() if s.startswith("HEAVY=")]
    assert line, out.stderr
    heavy = [m for m in line[0][len("HEAVY="):].split(",") if m]
    return out.returncode, heavy, out.stderr


@pytest.mark.parametrize("model", ["constant", "high-order"])
def test_fit_and_predict_import_no_heavy_modules(files, tmp_path, model):
    out = tmp_path / "m.json"
    code, heavy, err = _modules_loaded_by(
        "fit", "--robot", "fanuc_lrmate200i", "--data", str(files["train"]), "--model", model,
        "--out", str(out))
    assert code == 0, err
    assert heavy == []
    code, heavy, err = _modules_loaded_by(
        "predict", "--model", str(out), "--joints", str(files["joints"]),
        "--out", str(tmp_path / "pred.csv"))
    assert code == 0, err
    assert heavy == []


def test_help_imports_neither_numpy_nor_subcommands() -> None:
    src = ("import sys\nfrom robocal.cli.main import main\n"
           "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
           "print('MODS=' + ','.join(sorted(m for m in sys.modules "
           "if m.split('.')[0] == 'numpy' or m.startswith('robocal.cli._'))))\n")
    out = subprocess.run([sys.executable, "-c", src], capture_output=True, text=True, timeout=60)
    mods = [s for s in out.stdout.splitlines() if s.startswith("MODS=")]
    assert mods and mods[0] == "MODS=", out.stdout + out.stderr


def test_help_lists_every_subcommand_with_its_modules_help_line(
        capsys: pytest.CaptureFixture[str]) -> None:
    """The cheap help table in main.py agrees with every module's own registration."""
    import argparse

    from robocal.cli.main import COMMANDS, build_parser

    full = build_parser()       # imports every subcommand module; an import error fails here
    sub = next(a for a in full._actions if isinstance(a, argparse._SubParsersAction))
    registered = {a.dest: a.help for a in sub._choices_actions}
    assert registered == COMMANDS
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for name, text in COMMANDS.items():
        assert name in out and text.split()[0] in out


def _rewrite(src: Path, dst: Path, *, joints: float = 1.0, xyz: float = 1.0) -> Path:
    """Copy a measurement CSV with joints and/or positions scaled (wrong units)."""
    ms = MeasurementSet.read_csv(src, dof=6)
    # read_csv converts deg -> rad and mm -> m; write_csv converts back, so scaling the SI
    # values by 180/pi writes radians into the degree columns, by 1e-3 metres into the mm ones
    MeasurementSet(ms.q * joints, ms.p * xyz, ms.sigma, ms.pose_id).write_csv(dst)
    return dst


def test_wrong_units_and_wrong_robot_get_one_line_hints(files, tmp_path, capsys):
    out = tmp_path / "m.json"
    base = ["fit", "--model", "constant", "--out", str(out)]
    rad = _rewrite(files["train"], tmp_path / "rad.csv", joints=np.pi / 180)
    _expect_error(capsys, [*base, "--robot", "fanuc_lrmate200i", "--data", str(rad)], out,
                  "look like radians")
    metres = _rewrite(files["train"], tmp_path / "m.csv", xyz=1e-3)
    _expect_error(capsys, [*base, "--robot", "fanuc_lrmate200i", "--data", str(metres)], out,
                  "look like metres")
    _expect_error(capsys, [*base, "--robot", "fanuc_lrmate200id", "--data",
                           str(files["train"])], out, "right robot/variant")
    _expect_error(capsys, [*base, "--robot", "ur10", "--data", str(files["train"])], out,
                  "right robot/variant")
    # the override fits anyway (and the absurd result is visible in the summary)
    assert main([*base, "--robot", "fanuc_lrmate200id", "--data", str(files["train"]),
                 "--no-sanity", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["train"]["baseline_rms_mm"] > 10.0


def test_max_rms_threshold_fails_the_fit(files, tmp_path, capsys):
    ok, out = _fit(files, tmp_path, "constant", "--max-rms-mm", "5")
    assert ok == 0 and out.exists()
    capsys.readouterr()
    out2 = tmp_path / "strict.json"
    code = main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(files["train"]),
                 "--model", "constant", "--out", str(out2), "--validate", str(files["val"]),
                 "--max-rms-mm", "0.01"])
    err = capsys.readouterr().err
    assert code == 1 and not out2.exists()
    assert "validation RMS" in err and "exceeds --max-rms-mm 0.01" in err


def test_reuse_keeps_the_joint_dependent_terms(files, tmp_path, capsys):
    code, first = _fit(files, tmp_path, "high-order", "--json")
    assert code == 0
    capsys.readouterr()
    prev = CalibratedModel.load(first)
    # a new session: 60 of the held-out poses, the tracker moved (new base), same robot
    val = MeasurementSet.read_csv(files["val"], dof=6)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = MeasurementSet(val.q, val.p @ R.T + np.array([0.3, -0.2, 0.05]), None, val.pose_id)
    new, rest = moved.subset(np.arange(60)), moved.subset(np.arange(60, len(moved)))
    new.write_csv(tmp_path / "new.csv")
    rest.write_csv(tmp_path / "rest.csv")
    out = tmp_path / "reused.json"
    code = main(["fit", "--reuse", str(first), "--data", str(tmp_path / "new.csv"),
                 "--validate", str(tmp_path / "rest.csv"), "--out", str(out), "--json"])
    assert code == 0
    s = json.loads(capsys.readouterr().out)
    cal = CalibratedModel.load(out)
    assert cal.kind == "refit:high-order" and cal.fit["frozen_from"] == prev.model_id
    assert cal.data["reused"] == str(first)
    joint_dep = [i for i, n in enumerate(cal.model.names)
                 if not (n.startswith(("base.", "tool.")) or n.endswith(".const"))]
    assert joint_dep and np.allclose(cal.params[joint_dep], prev.params[joint_dep])
    const = main(["fit", "--robot", "fanuc_lrmate200i", "--model", "constant", "--data",
                  str(tmp_path / "new.csv"), "--validate", str(tmp_path / "rest.csv"),
                  "--out", str(tmp_path / "c.json"), "--json"])
    assert const == 0
    c = json.loads(capsys.readouterr().out)
    # the reused maps beat a constant model fitted on the same 60 poses
    assert s["validation"]["rms_mm"] < 0.6 * c["validation"]["rms_mm"]
    _expect_error(capsys, ["fit", "--reuse", str(first), "--model", "auto", "--data",
                           str(tmp_path / "new.csv"), "--out", str(tmp_path / "x.json")],
                  tmp_path / "x.json", "--reuse")
    _expect_error(capsys, ["fit", "--robot", "fanuc_lrmate200i", "--no-fill-gaps", "--data",
                           str(tmp_path / "new.csv"), "--out", str(tmp_path / "x.json")],
                  tmp_path / "x.json", "--no-fill-gaps")
    # the link constants stay near the earlier ones (prior 0.05 mm / 0.005 deg); the joint
    # offsets move freely
    links = [i for i, n in enumerate(cal.model.names)
             if n.endswith(".const") and not n.endswith(".ez.const")]
    step = np.abs(cal.params[links] - prev.params[links])
    lin = np.array([".d" in cal.model.names[i] for i in links])
    assert step[lin].max() < 0.15e-3 and step[~lin].max() < np.radians(0.015)


def test_report_exit_code_follows_the_verdict(files, tmp_path, capsys):
    code, good = _fit(files, tmp_path, "high-order")
    assert code == 0
    assert main(["report", str(good), "--out", str(tmp_path / "ok.html")]) == 0
    # joints scrambled: the model is useless on these poses -> failed verdict, exit 1
    bad_q = MeasurementSet.read_csv(files["val"], dof=6)
    scrambled = MeasurementSet(bad_q.q[::-1], bad_q.p, None, bad_q.pose_id)
    scrambled.write_csv(tmp_path / "scrambled.csv")
    capsys.readouterr()
    code = main(["report", str(good), "--validate", str(tmp_path / "scrambled.csv"),
                 "--out", str(tmp_path / "bad.html"), "--json"])
    verdict = json.loads(capsys.readouterr().out)["verdict"]
    assert verdict["outcome"] == "failed" and code == 1


def test_fit_prints_warnings_about_extrapolated_validation_poses(tmp_path, capsys):
    """Training J6 at 0 and 2 deg only: the summary warns, the JSON and model carry it."""
    cell, rng, train = thin_j6_design()
    qv, pv, _, _ = cell.simulate(cell.random_joints(100, rng), rng)
    train.write_csv(tmp_path / "t.csv")
    MeasurementSet(qv, pv).write_csv(tmp_path / "v.csv")
    out = tmp_path / "m.json"
    argv = ["fit", "--robot", "ur10", "--model", "constant", "--data", str(tmp_path / "t.csv"),
            "--validate", str(tmp_path / "v.csv"), "--out", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    warn = [ln for ln in text.splitlines() if ln.startswith("WARNING: ")]
    assert len(warn) == 1 and "with J6 angles the training poses lack" in warn[0]
    assert CalibratedModel.load(out).fit["warnings"] == [warn[0][len("WARNING: "):]]
    assert main([*argv, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["warnings"] == [warn[0][len("WARNING: "):]]
