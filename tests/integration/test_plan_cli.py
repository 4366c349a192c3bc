"""``robocal plan``: writes a valid, deterministic PLAN.json; bad input writes nothing."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from robocal.cli.main import main
from robocal.planning import Plan


def _args(out: Path, *extra: str) -> list[str]:
    return ["plan", "--robot", "fanuc_lrmate200i", "--cell", "demo", "--model", "constant",
            "--count", "20", "--validation", "5", "--candidates", "256", "--out", str(out),
            *extra]


def test_plan_writes_a_valid_deterministic_file(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    assert main(_args(a, "--seed", "11")) == 0
    out = capsys.readouterr().out
    assert f"wrote {a}" in out and "20 calibration" in out and "observability O1" in out
    assert "needs >= 11 poses, 27 recommended" in out
    assert main(_args(b, "--seed", "11", "--json")) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["by_purpose"]["calibration"] == 20 and summary["seed"] == 11
    assert a.read_bytes() == b.read_bytes()
    plan = Plan.load(a)
    assert plan.seed == 11 and plan.count("validation") == 5 and plan.count("iso") == 5 * 30
    assert plan.model.name == "constant" and plan.robot.name == "fanuc_lrmate200i"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json"]


def test_cpa_and_high_order(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "p.json"
    assert main(["plan", "--robot", "fanuc_lrmate200i", "--cell", "demo", "--model",
                 "high-order", "--count", "70", "--candidates", "256", "--cpa",
                 "--cpa-points", "4", "--no-iso", "--out", str(out)]) == 0
    plan = Plan.load(out)
    assert plan.model.name == "high-order" and plan.count("cpa") == 24
    assert plan.count("iso") == 0
    assert any("recommended" in w for w in plan.warnings)  # 70 < 3 per parameter
    assert "warning:" in capsys.readouterr().out


@pytest.mark.parametrize(("change", "message"), [
    (["--count", "3"], "count 3 is below the 11 poses"),
    (["--robot", "no_such_robot"], "not a built-in robot"),
    (["--validation", "-2"], "validation must not be negative"),
])
def test_bad_input_is_one_error_line_and_no_file(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str],
                                                 change: list[str], message: str) -> None:
    out = tmp_path / "PLAN.json"
    args = _args(out)
    i = args.index(change[0])
    args[i + 1] = change[1]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("robocal plan: error: ") and message in err
    assert err.count("\n") == 1
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_bad_cell_names_file_and_key_and_keeps_the_old_plan(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cell = tmp_path / "cell.toml"
    cell.write_text('[tracker]\nposition_mm = [1800, 0, 400]\n[floor]\nz_mm = -600\n'
                    'height_mm = 3\n')
    out = tmp_path / "PLAN.json"
    out.write_text("previous plan\n")
    args = _args(out)
    args[args.index("--cell") + 1] = str(cell)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert str(cell) in err and "key 'floor.height_mm'" in err and "unknown key" in err
    assert out.read_text() == "previous plan\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["PLAN.json", "cell.toml"]
    assert main(_args(tmp_path / "missing" / "PLAN.json")) == 2
    assert "output directory does not exist" in capsys.readouterr().err


def test_dropped_targets_are_listed(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # the KR210 in the demo cell: with seed 1 no J4 sweep of its 64 candidates is reachable
    # (forearm folded over the shoulder; ADR 0057 prefers reachable bases, seed 0 has one);
    # its points are left out and said so
    out = tmp_path / "p.json"
    assert main(["plan", "--robot", "kuka_kr210_r3100", "--cell", "demo", "--model", "constant",
                 "--count", "12",
                 "--validation", "2", "--no-iso", "--cpa", "--cpa-points", "4",
                 "--candidates", "64", "--seed", "1",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    plan = Plan.load(out)
    assert plan.dropped
    assert f"warning: {len(plan.dropped)} target(s) dropped" in text
    for d in plan.dropped:
        q = ", ".join(f"{v:.2f}" for v in d.joints_deg)
        assert f"dropped {d.purpose} target [{q}] deg: no safe route" in text

