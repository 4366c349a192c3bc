"""The ``[fleet]`` configuration (ADR 0035): off by default, checked keys, secrets in files,
warnings for a password in the URL and an unverified server; the fleet report's CLI errors."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from robocal.cli.main import main
from robocal.daemon.config import config_warnings, parse_config
from robocal.daemon.main import preflight
from robocal.errors import ConfigError

BASE: dict[str, Any] = {"robot_description": "fanuc_lrmate200i", "robot": {"kind": "mock"},
                        "tracker": {"kind": "mock"}}


def _cfg(fleet: dict[str, Any], base: Path | None = None) -> Any:
    return parse_config({**BASE, "fleet": fleet}, base=base)


def test_off_by_default() -> None:
    cfg = parse_config(dict(BASE))
    assert cfg.fleet.url is None
    assert config_warnings(cfg) == []


@pytest.mark.parametrize(("fleet", "match"), [
    ({"url": "postgresql://h/db"}, "robot_serial"),
    ({"url": "mysql://h/db", "robot_serial": "S"}, "postgresql://"),
    ({"url": "postgresql://h/db", "robot_serial": "S", "pasword_file": "p"}, "pasword_file"),
    ({"url": "postgresql://h/db", "robot_serial": "S", "batch_rows": 0}, "batch_rows"),
])
def test_bad_settings_are_refused(fleet: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        _cfg(fleet)


def test_password_in_url_and_unverified_server_warn() -> None:
    cfg = _cfg({"url": "postgresql://u:secret@db.plant/fleet", "robot_serial": "S"})
    warnings = " ".join(config_warnings(cfg))
    assert "password_file" in warnings and "verify-full" in warnings
    ok = _cfg({"url": "postgresql://u@db.plant/fleet?sslmode=verify-full&sslrootcert=ca.pem",
               "robot_serial": "S", "password_file": "/x"})
    assert config_warnings(ok) == []


def test_password_file_is_relative_to_the_config_and_private(tmp_path: Path) -> None:
    (tmp_path / "pw").write_text("s3cret\n")
    (tmp_path / "pw").chmod(0o644)
    cfg = _cfg({"url": "postgresql://u@127.0.0.1/f", "robot_serial": "S",
                "password_file": "pw"}, base=tmp_path)
    assert cfg.fleet.password_file == tmp_path / "pw"
    with pytest.raises(ConfigError, match="password file has mode 0644"):
        preflight(cfg)
    (tmp_path / "pw").chmod(0o600)
    preflight(cfg)


def test_report_needs_a_url(monkeypatch: pytest.MonkeyPatch,
                            capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.delenv("ROBOCAL_FLEET_URL", raising=False)
    assert main(["fleet", "report"]) == 2
    assert "--url" in capsys.readouterr().err


def test_report_on_an_unreachable_database_is_one_line(capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    with socket.socket() as s:  # bound, not listening: connections are refused
        s.bind(("127.0.0.1", 0))
        url = f"postgresql://robocal@127.0.0.1:{s.getsockname()[1]}/fleet"
        assert main(["fleet", "report", "--url", url]) == 2
    err = capsys.readouterr().err
    assert err.startswith("robocal fleet report: error:") and "Traceback" not in err


def test_psycopg_is_imported_only_when_used(tmp_path: Path) -> None:
    """The daemon with the fleet store off never loads the PostgreSQL client."""
    src = ("import asyncio, sys\n"
           "import robocal.daemon.main, robocal.cli._fleet\n"
           "from robocal.daemon.config import parse_config\n"
           "from robocal.daemon.fleet import start_fleet\n"
           f"cfg = parse_config({{**{BASE!r}, 'data_dir': {str(tmp_path)!r}}})\n"
           "assert start_fleet(cfg, robot='r') is None\n"
           "print('psycopg' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", src], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
