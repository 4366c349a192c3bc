"""Configuration: validation with file and key path, both deploy configs, ``config check``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from robocal.cli.main import main
from robocal.daemon.config import config_errors, load_config, parse_config
from robocal.errors import ConfigError

REPO = Path(__file__).resolve().parents[3]
DEPLOY = REPO / "deploy" / "config"


@pytest.mark.parametrize("name", ["robocal.example.toml", "sim.toml"])
def test_deploy_configs_validate(name):
    path = DEPLOY / name
    assert config_errors(path) == []
    cfg = load_config(path)
    assert cfg.robot.kind == "fanuc_rmi" and cfg.tracker.kind == "ltp"


def test_deploy_configs_build_their_drivers(capsys):
    files = [str(DEPLOY / n) for n in ("robocal.example.toml", "sim.toml")]
    assert main(["config", "check", "--drivers", *files]) == 0
    assert capsys.readouterr().out.count(": ok") == 2


def test_unknown_key_names_file_and_path(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('robot_description = "fanuc_lrmate200i"\n'
                 '[robot]\nkind = "mock"\n[tracker]\nkind = "mock"\n'
                 '[measurement]\nsampels = 3\n')
    errors = config_errors(p)
    assert len(errors) == 1
    assert str(p) in errors[0] and "measurement.sampels" in errors[0]
    assert "Extra inputs are not permitted" in errors[0]
    with pytest.raises(ConfigError, match=r"measurement\.sampels"):
        load_config(p)


def test_config_check_cli_lists_every_error(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text('robot_description = "x"\n[robot]\nkind = "mock"\nbogus = 1\n'
                 '[api]\ntcp_port = 8000\n')
    assert main(["config", "check", str(p)]) == 1
    out = capsys.readouterr().out
    assert "robot.bogus" in out and "tracker" in out and "token_file" in out


def test_tcp_requires_a_token_file(tmp_path):
    with pytest.raises(ConfigError, match="token"):
        parse_config({"robot_description": "r", "robot": {"kind": "mock"},
                      "tracker": {"kind": "mock"}, "api": {"tcp_port": 0}})


def test_relative_paths_resolve_against_the_file(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('data_dir = "state"\nrobot_description = "fanuc_lrmate200i"\n'
                 '[robot]\nkind = "mock"\n[tracker]\nkind = "mock"\n'
                 '[api]\ntcp_port = 0\ntoken_file = "tok"\n')
    cfg = load_config(p)
    assert cfg.data_dir == tmp_path / "state"
    assert cfg.api.token_file == tmp_path / "tok"
    assert cfg.socket_path == tmp_path / "state" / "robocal.sock"


def test_short_token_is_refused(tmp_path):
    tok = tmp_path / "tok"
    tok.write_text("short\n")
    tok.chmod(0o600)
    cfg = parse_config({"robot_description": "r", "robot": {"kind": "mock"},
                        "tracker": {"kind": "mock"},
                        "api": {"tcp_port": 0, "token_file": str(tok)}})
    with pytest.raises(ConfigError, match="16 characters"):
        cfg.read_token()


def test_not_toml_and_missing_file(tmp_path):
    p = tmp_path / "x.toml"
    p.write_text("this is = = not toml")
    assert "not valid TOML" in config_errors(p)[0]
    assert "file not found" in config_errors(tmp_path / "none.toml")[0]


async def test_bad_fit_options_fail_at_start(make_config):
    from robocal.daemon.service import CalibrationService

    svc = CalibrationService(make_config(fit={"options": {"no_such_option": 1}}))
    with pytest.raises(ConfigError, match=r"fit\.options"):
        await svc.start(connect=False)
    svc.store.close()


def test_systemd_unit_is_notify_and_hardened():
    unit = (REPO / "deploy" / "systemd" / "robocal.service").read_text()
    lines = {ln.split("=", 1)[0]: ln.split("=", 1)[1] for ln in unit.splitlines()
             if "=" in ln and not ln.startswith("#")}
    assert lines["Type"] == "notify" and lines["NotifyAccess"] == "main"
    assert "robocal daemon --config" in lines["ExecStart"]
    assert lines["User"] == "robocal" and lines["StateDirectory"] == "robocal"
    assert lines["ProtectSystem"] == "strict" and lines["NoNewPrivileges"] == "yes"
    assert lines["DevicePolicy"] == "closed"
    allowed = [ln for ln in unit.splitlines() if ln.startswith("DeviceAllow=")]
    assert allowed == ["DeviceAllow=/dev/robocal-tracker rw"]
    assert int(lines["WatchdogSec"]) > 0
    rule = (REPO / "deploy" / "udev" / "99-robocal-tracker.rules").read_text()
    assert 'SYMLINK+="robocal-tracker"' in rule and 'MODE="0660"' in rule


def test_fit_acceptance_is_checked_at_load(tmp_path):
    from robocal.daemon.config import parse_config
    from robocal.errors import ConfigError

    from .conftest import base_config

    cfg = parse_config(base_config(tmp_path, fit={"acceptance": {"max_rms_mm": 0.3}}),
                       source="t")
    assert cfg.fit.acceptance == {"max_rms_mm": 0.3}
    with pytest.raises(ConfigError, match="max_rms"):
        parse_config(base_config(tmp_path, fit={"acceptance": {"max_rms": 0.3}}), source="t")


def test_config_check_connect_is_a_preflight_of_the_cell(tmp_path, capsys):
    import socket

    from .conftest import base_config

    def write(cfg: dict, name: str) -> Path:
        lines = [f'data_dir = "{cfg["data_dir"]}"',
                 f'robot_description = "{cfg["robot_description"]}"']
        for sec in ("robot", "tracker"):
            opts = ", ".join(f"{k} = {json.dumps(v)}" for k, v in cfg[sec]["options"].items())
            lines += [f"[{sec}]", f'kind = "{cfg[sec]["kind"]}"', "connect_timeout_s = 2.0",
                      f"options = {{ {opts} }}"]
        path = tmp_path / name
        path.write_text("\n".join(lines) + "\n")
        return path

    cfg = base_config(tmp_path)
    ok = write(cfg, "ok.toml")
    assert main(["config", "check", "--config", str(ok), "--connect"]) == 0
    out = capsys.readouterr().out
    assert "robot (mock) answers" in out and "tracker (mock) answers" in out
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg["robot"] = {"kind": "fanuc_rmi", "options": {"host": "127.0.0.1", "connect_port": port}}
    down = write(cfg, "down.toml")
    assert main(["config", "check", "--config", str(down), "--connect"]) == 1
    out = capsys.readouterr().out
    assert "the robot (fanuc_rmi) does not answer" in out
    assert main(["config", "check"]) == 2
    assert "--config FILE" in capsys.readouterr().err


def test_the_simulated_cell_keeps_per_user_state_and_logs_json(monkeypatch, tmp_path):
    """sim.toml: state in the running user's home (not a shared directory under /tmp),
    JSON log lines as the README says; ``~`` in data_dir is the user's home."""
    monkeypatch.setenv("HOME", str(tmp_path))
    cfg = load_config(DEPLOY / "sim.toml")
    assert cfg.data_dir == tmp_path / ".local" / "state" / "robocal-sim"
    assert cfg.logging.format == "json"
    gitignore = (REPO / ".gitignore").read_text().splitlines()
    assert "/try/" in gitignore and "/cell/" in gitignore  # the README's scratch directories
