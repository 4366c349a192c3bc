"""``robocal simulate`` writes measurement files that ``robocal fit`` accepts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.cli.main import main


def test_simulate_then_fit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    meas = tmp_path / "meas.csv"
    assert main(["simulate", "--scenario", "constant", "--poses", "120", "--validation", "30",
                 "--outliers", "0.05", "--out", str(meas)]) == 0
    out = capsys.readouterr().out
    assert "120 poses, 6 with planted glitches" in out
    cal = MeasurementSet.read_csv(meas, dof=6)
    val = MeasurementSet.read_csv(tmp_path / "meas-val.csv", dof=6)
    assert len(cal) == 120 and len(val) == 30 and cal.sigma is not None
    assert np.all(np.linalg.norm(cal.p, axis=1) > 0.5)  # metres from the tracker
    model = tmp_path / "model.json"
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(meas), "--model",
                 "constant", "--out", str(model),
                 "--validate", str(tmp_path / "meas-val.csv")]) == 0
    assert model.exists()


def test_simulate_rejects_bad_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "--poses", "0", "--out", str(tmp_path / "m.csv")]) == 2
    assert "--poses" in capsys.readouterr().err
    assert main(["simulate", "--scenario", "wobbly", "--out", str(tmp_path / "m.csv")]) == 2
    assert "unknown scenario" in capsys.readouterr().err
    assert not (tmp_path / "m.csv").exists()


@pytest.mark.parametrize("cmd", [["simulate"], ["fit", "--robot", "fanuc_lrmate200i", "--data",
                                                "meas.csv"], ["plan"], ["demo"]])
def test_a_negative_seed_is_a_usage_error(cmd: list[str], tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    # numpy's generators refused it with a traceback (simulate; fit's CV folds)
    with pytest.raises(SystemExit) as exc:
        main([*cmd, "--seed", "-1", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "argument --seed: must not be negative, got -1" in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


# --- a plan's robot, and plans with joints no robot can reach --------------------------------
@pytest.fixture(scope="module")
def ur10_plan_text() -> str:
    """A small plan rewritten to be a UR10's (the UR10's +-360 deg limits hold its poses)."""
    import json

    from robocal.kinematics import load_robot
    from robocal.planning import plan_campaign

    plan = plan_campaign("fanuc_lrmate200i", "demo", count=12, model="constant", validation=2,
                         iso=False, candidates=200, seed=1)
    data = json.loads(plan.to_json())
    data["robot"] = {"name": "ur10", "source": "builtin",
                     "description": load_robot("ur10").to_dict()}
    return json.dumps(data)


def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_simulate_a_plan_uses_the_plans_robot(tmp_path: Path, ur10_plan_text: str,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    plan = tmp_path / "ur10plan.json"
    plan.write_text(ur10_plan_text)
    out = tmp_path / "m.csv"
    assert main(["simulate", "--plan", str(plan), "--out", str(out)]) == 0
    assert "virtual UR10" in capsys.readouterr().out
    assert main(["simulate", "--plan", str(plan), "--robot", "ur10", "--out", str(out)]) == 0
    capsys.readouterr()
    other = tmp_path / "other.csv"
    assert main(["simulate", "--plan", str(plan), "--robot", "fanuc_lrmate200i",
                 "--out", str(other)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "made for 'ur10'" in line
    assert not other.exists()


@pytest.mark.parametrize("joint", ["1e300", "-1e300", "Infinity", "NaN", "7" * 5000, "400.0"])
def test_simulate_refuses_a_plan_with_an_impossible_joint(
        tmp_path: Path, ur10_plan_text: str, joint: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    import json

    data = json.loads(ur10_plan_text)
    pose = next(p for p in data["poses"] if p["purpose"] == "calibration")
    pose["joints_deg"][1] = "@JOINT@"
    plan = tmp_path / "bad.json"
    plan.write_text(json.dumps(data).replace('"@JOINT@"', joint))
    out = tmp_path / "m.csv"
    assert main(["simulate", "--plan", str(plan), "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(plan) in line
    assert not out.exists() and not (tmp_path / "m-val.csv").exists()


def test_simulate_any_joint_value_is_simulated_or_refused_in_one_line(
        tmp_path_factory: pytest.TempPathFactory, ur10_plan_text: str) -> None:
    """Property: whatever number a plan's joint holds, simulate exits 0 (within the limits)
    or 2 with one error line and no file; never a traceback."""
    import contextlib
    import io
    import json

    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    base = json.loads(ur10_plan_text)

    @settings(max_examples=15, deadline=None,
              suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(value=st.one_of(st.floats(allow_nan=False, allow_infinity=False),
                           st.integers(min_value=-10**400, max_value=10**400)))
    def check(value: float | int) -> None:
        d = tmp_path_factory.mktemp("prop")
        data = json.loads(json.dumps(base))
        next(p for p in data["poses"] if p["purpose"] == "validation")["joints_deg"][0] = value
        plan = d / "p.json"
        plan.write_text(json.dumps(data))
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(["simulate", "--plan", str(plan), "--out", str(d / "m.csv")])
        inside = abs(value) <= 360
        if inside:
            assert code == 0, err.getvalue()
        else:
            assert code == 2 and not (d / "m.csv").exists()
            _one_error_line(err.getvalue())

    check()
