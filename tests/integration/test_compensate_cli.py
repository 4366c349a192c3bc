"""``robocal compensate`` and ``robocal table`` end to end on a fitted virtual LR Mate 200i."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tests.unit.compensation._helpers import fitted_model

from robocal.cli.main import main
from robocal.compensation import CompensationTable, TargetSet, read_targets_csv


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    cell, cal = fitted_model("fanuc_lrmate200i", "paper", 7)
    d = tmp_path_factory.mktemp("cli")
    cal.save(d / "model.json")
    rng = np.random.default_rng(21)
    assert cal.coverage is not None
    q = rng.uniform(cal.coverage[:, 0] + 0.1, cal.coverage[:, 1] - 0.1, (12, 6))
    p = cell.reflector_position(q)
    TargetSet(p=p, q_seed=q).write_csv(d / "targets.csv")
    far = p.copy()
    far[4] = [6.0, 0.0, 0.0]
    TargetSet(p=far, q_seed=q).write_csv(d / "targets_far.csv")
    _, R, _ = cal.model.flange_poses(q, cal.params)
    TargetSet(p=p, q_seed=q, R=R).write_csv(d / "targets_wpr.csv")
    return {"dir": d, "model": d / "model.json", "targets": d / "targets.csv",
            "far": d / "targets_far.csv", "wpr": d / "targets_wpr.csv"}


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def test_compensate_writes_joints(files: dict[str, Path], capsys: pytest.CaptureFixture[str]
                                  ) -> None:
    out = files["dir"] / "joints.csv"
    rc = main(["compensate", "--model", str(files["model"]), "--targets", str(files["targets"]),
               "--out", str(out), "--table", str(files["dir"] / "t.json")])
    assert rc == 0
    text = capsys.readouterr().out
    assert "12 ok" in text
    rows = _rows(out)
    # the targets' label column comes first, so each row says which target it solves
    assert list(rows[0]) == ["target_id", "q1", "q2", "q3", "q4", "q5", "q6", "status",
                             "model_residual_mm"]
    assert [r["target_id"] for r in rows] == [f"T{i:04d}" for i in range(12)]
    assert len(rows) == 12 and all(r["status"] == "ok" for r in rows)
    assert max(float(r["model_residual_mm"]) for r in rows) < 1e-3
    # the commands put the model's reflector on the targets
    _, cal = fitted_model("fanuc_lrmate200i", "paper", 7)
    q = np.radians([[float(r[f"q{j}"]) for j in range(1, 7)] for r in rows])
    ts = read_targets_csv(files["targets"])
    np.testing.assert_allclose(cal.predict(q), ts.p, atol=1e-6)
    table = CompensationTable.read(files["dir"] / "t.json")
    assert table.kind == "targets" and len(table.targets or []) == 12
    assert (f"targets table {table.checksum[:16]}" in text
            and f"nominal residual {table.stats['nominal_residual_mm']:.4f} mm" in text)
    np.testing.assert_allclose([r.q_deg for r in table.targets or []], np.degrees(q),
                               atol=1e-8)


def test_orientation_columns(files: dict[str, Path]) -> None:
    out = files["dir"] / "joints_wpr.csv"
    rc = main(["compensate", "--model", str(files["model"]), "--targets", str(files["wpr"]),
               "--out", str(out), "--json"])
    assert rc == 0
    assert all(r["status"] == "ok" for r in _rows(out))


def test_failed_targets_exit_1_with_empty_joints(files: dict[str, Path],
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    out = files["dir"] / "joints_far.csv"
    rc = main(["compensate", "--model", str(files["model"]), "--targets", str(files["far"]),
               "--out", str(out), "--json"])
    assert rc == 1
    summary = json.loads(capsys.readouterr().out)
    assert summary["ok"] == 11 and summary["unreachable"] == 1
    row = _rows(out)[4]
    assert row["status"] == "unreachable" and row["q1"] == "" and row["q6"] == ""


@pytest.mark.parametrize(("args", "message"), [
    (["--targets", "{model}"], "required column is missing"),
    (["--targets", "{dir}/missing.csv"], "file not found"),
    (["--model", "{targets}"], "not valid JSON"),
    (["--out", "{dir}/nodir/j.csv"], "does not exist"),
    (["--tol-um", "0"], "--tol-um"),
])
def test_bad_input_is_one_error_and_nothing_written(
        files: dict[str, Path], capsys: pytest.CaptureFixture[str], args: list[str],
        message: str) -> None:
    out = files["dir"] / "never.csv"
    base = {"--model": str(files["model"]), "--targets": str(files["targets"]),
            "--out": str(out)}
    fmt = {k: str(v) for k, v in files.items()}
    for flag, value in zip(args[::2], args[1::2], strict=True):
        base[flag] = value.format(**fmt)
    argv = ["compensate", *[x for kv in base.items() for x in kv]]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("robocal compensate: error:")
    assert message in err[0]
    assert not out.exists()
    assert not [p for p in files["dir"].iterdir() if p.name.startswith(".never")]


def test_seed_count_must_match_the_robot(files: dict[str, Path],
                                         capsys: pytest.CaptureFixture[str]) -> None:
    bad = files["dir"] / "five.csv"
    bad.write_text("x,y,z,q1,q2,q3,q4,q5\n500,0,300,0,0,0,0,0\n")
    out = files["dir"] / "never5.csv"
    assert main(["compensate", "--model", str(files["model"]), "--targets", str(bad),
                 "--out", str(out)]) == 2
    assert "robot has 6 joints" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("kind", ["targets", "joint", "frames"])
def test_table_kinds(files: dict[str, Path], capsys: pytest.CaptureFixture[str],
                     kind: str) -> None:
    out = files["dir"] / f"{kind}.json"
    argv = ["table", "--model", str(files["model"]), "--kind", kind, "--out", str(out),
            "--samples", "300"]
    if kind == "targets":
        argv += ["--targets", str(files["targets"])]
    assert main(argv) == 0
    text = capsys.readouterr().out
    table = CompensationTable.read(out)
    assert f"wrote {out}: {kind} table" in text and table.checksum[:16] in text
    nominal = table.stats["nominal_residual_mm"]
    assert (f"predicted residual {table.predicted_residual_mm:.4f} mm; nominal "
            f"{nominal:.4f} mm") in text
    if kind == "frames":
        assert "base/tool alignment, not compensation" in text
        assert "warning: a frames table aligns base and tool only" in text
    assert table.kind == kind and table.robot == "FANUC LR Mate 200i"
    assert len(table.valid_range_deg) == 6
    assert main(["table", "--check", str(out), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["kind"] == kind and s["nominal_residual_mm"] == pytest.approx(nominal, abs=1e-6)


def test_vendor_export_states_what_zero_offsets_carry(files: dict[str, Path],
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    from robocal.kinematics import CalibratedModel

    cal = CalibratedModel.load(files["model"])
    out = files["dir"] / "vendor.json"
    assert main(["table", "--model", str(files["model"]), "--kind", "vendor", "--out",
                 str(out)]) == 0
    text = capsys.readouterr().out
    assert "zero offsets alone predict" in text
    doc = json.loads(out.read_text())
    names = list(cal.model.names)
    for j in doc["joints"]:
        ez = f"j{j['joint']}.ez.const"
        want = math.degrees(float(cal.params[names.index(ez)])) if ez in names else 0.0
        assert j["delta_theta_deg"] == pytest.approx(want, abs=1e-6)
    # zero offsets without the other constant terms may even do harm: then it says so
    worse = doc["predicted_residual_zero_offsets_only_mm"] >= doc["nominal_residual_mm"]
    assert bool(doc["warnings"]) == worse
    assert ("warning: zero offsets alone" in text) == worse
    conf = files["dir"] / "calibration.conf"
    assert main(["table", "--model", str(files["model"]), "--kind", "vendor",
                 "--vendor-style", "ur", "--out", str(conf)]) == 0
    text = conf.read_text()
    assert "[mounting]" in text and text.count("delta_") == 4


def test_table_errors_and_diff(files: dict[str, Path], capsys: pytest.CaptureFixture[str]
                               ) -> None:
    out = files["dir"] / "never_table.json"
    assert main(["table", "--model", str(files["model"]), "--kind", "targets",
                 "--out", str(out)]) == 2
    assert "--targets" in capsys.readouterr().err
    assert not out.exists()
    a = files["dir"] / "fa.json"
    b = files["dir"] / "fb.json"
    for path, extra in ((a, []), (b, ["--with-joint-table"])):
        assert main(["table", "--model", str(files["model"]), "--kind", "frames", "--out",
                     str(path), "--samples", "300", *extra]) == 0
    capsys.readouterr()
    assert main(["table", "--diff", str(a), str(a)]) == 0
    assert "tables agree" in capsys.readouterr().out
    assert main(["table", "--diff", str(a), str(b)]) == 1
    assert "base frame" in capsys.readouterr().out
    tampered = json.loads(a.read_text())
    tampered["frames"]["tool"]["z"] += 0.5
    bad = files["dir"] / "tampered.json"
    bad.write_text(json.dumps(tampered))
    assert main(["table", "--check", str(bad)]) == 2
    assert "checksum mismatch" in capsys.readouterr().err


def test_console_entry_point(files: dict[str, Path]) -> None:
    out = files["dir"] / "joints_sub.csv"
    proc = subprocess.run(
        [sys.executable, "-m", "robocal", "compensate", "--model", str(files["model"]),
         "--targets", str(files["targets"]), "--out", str(out)],
        capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert len(_rows(out)) == 12


def test_temps_on_a_model_without_thermal_term_is_a_note(files: dict[str, Path],
                                                          capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    out = files["dir"] / "joints_temps.csv"
    rc = main(["compensate", "--model", str(files["model"]), "--targets", str(files["targets"]),
               "--out", str(out), "--temps", "30,30,30,30,30,30", "--json"])
    captured = capsys.readouterr()
    assert rc == 0 and "the model has no thermal term; --temps changes nothing" in captured.err
    assert json.loads(captured.out)["temperatures_c"] is None
    for bad in ("30,30,30,30,30,nan", "warm", "30,30,30,30,30,300"):
        rc = main(["compensate", "--model", str(files["model"]), "--targets",
                   str(files["targets"]), "--out", str(out), "--temps", bad])
        assert rc == 2 and "--temps must be 6" in capsys.readouterr().err
