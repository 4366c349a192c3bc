"""CLI wiring of the daemon-side commands (no daemon needed)."""

from __future__ import annotations

import json

import pytest

from robocal.cli.main import main


def test_commands_are_registered(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for name in ("daemon", "campaign", "compensation", "demo", "sim", "config"):
        assert name in out


def test_sim_forwards_its_arguments(capsys):
    with pytest.raises(SystemExit) as info:
        main(["sim", "--help"])
    assert info.value.code == 0
    assert "--ports-file" in capsys.readouterr().out


def test_config_schema_is_json(capsys):
    assert main(["config", "schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert "robot" in schema["properties"] and schema["additionalProperties"] is False


def test_client_without_daemon_is_a_one_line_error(tmp_path, capsys):
    rc = main(["campaign", "list", "--socket", str(tmp_path / "none.sock")])
    err = capsys.readouterr().err
    assert rc == 2 and "cannot reach the daemon" in err and err.count("\n") == 1


def test_campaign_start_with_a_missing_plan(tmp_path, capsys):
    rc = main(["campaign", "start", "--plan", str(tmp_path / "nope.json"), "--socket",
               str(tmp_path / "s")])
    assert rc == 2 and "file not found" in capsys.readouterr().err


def test_demo_refuses_too_few_poses(capsys):
    assert main(["demo", "--poses", "5"]) == 2
    assert "--poses" in capsys.readouterr().err


def test_daemon_errors_read_as_sentences(tmp_path, capsys):
    from robocal.daemon.client import ApiError

    err = ApiError(409, "ApprovalRequired", "campaign abc is fitted; approve it first")
    assert str(err) == "campaign abc is fitted; approve it first"
    assert err.status == 409 and err.kind == "ApprovalRequired"
    assert "token" in str(ApiError(401, "Unauthorized", ""))
    rc = main(["campaign", "status", "x", "--socket", str(tmp_path / "none.sock")])
    out = capsys.readouterr().err
    assert rc == 2 and "robocal daemon --config" in out and "Error" not in out.split(":")[0]


def test_report_of_a_campaign_without_a_config_says_how(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("ROBOCAL_CONFIG", str(tmp_path / "none.toml"))
    rc = main(["report", "0123abcd", "--out", str(tmp_path / "r.html")])
    err = capsys.readouterr().err
    assert rc == 2 and "ROBOCAL_CONFIG=" in err and "--config FILE" in err
    assert not (tmp_path / "r.html").exists()
