"""Secure defaults: private state directory and database, token-file permissions, a loud
warning on a non-loopback TCP bind, and ``config check --drivers`` agreeing with the daemon."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from robocal.cli.main import main
from robocal.daemon.config import config_warnings, is_loopback, parse_config
from robocal.daemon.main import data_dir_lock
from robocal.daemon.service import CalibrationService
from robocal.errors import ConfigError
from tests.unit.daemon.conftest import base_config

TOKEN = "0123456789abcdef-token"


@pytest.fixture
def loose_umask() -> Iterator[None]:
    old = os.umask(0o022)
    yield
    os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


async def test_state_directory_and_database_are_private(make_config, tmp_path, loose_umask):
    state = tmp_path / "state"
    state.mkdir(mode=0o777)
    os.chmod(state, 0o777)  # as if created by hand by a careless operator
    svc = CalibrationService(make_config())
    await svc.start()
    try:
        svc.store.audit(actor="test", action="probe")  # forces the WAL file to exist
        assert _mode(state) & 0o027 == 0
        db = svc.config.db_path
        for f in (db, Path(f"{db}-wal"), Path(f"{db}-shm")):
            assert f.exists() and _mode(f) == 0o600, f
    finally:
        await svc.stop()


async def test_an_existing_world_readable_database_is_tightened(make_config, tmp_path,
                                                                loose_umask):
    cfg = make_config()
    cfg.data_dir.mkdir(mode=0o755)
    cfg.db_path.write_bytes(b"")
    os.chmod(cfg.db_path, 0o644)
    svc = CalibrationService(cfg)
    await svc.start()
    await svc.stop()
    assert _mode(cfg.db_path) == 0o600 and _mode(cfg.data_dir) == 0o750


def test_new_data_dir_from_the_lock_is_private(tmp_path, loose_umask):
    d = tmp_path / "fresh" / "state"
    with data_dir_lock(d):
        assert _mode(d) == 0o750 and _mode(d / "robocal.lock") == 0o600


@pytest.mark.parametrize(("mode", "ok"), [(0o600, True), (0o400, True), (0o640, False),
                                          (0o644, False), (0o604, False), (0o620, False)])
def test_token_file_must_be_the_owners_alone(tmp_path, mode, ok):
    tok = tmp_path / "tok"
    tok.write_text(TOKEN + "\n")
    tok.chmod(mode)
    cfg = parse_config(base_config(tmp_path, api={"tcp_port": 0, "token_file": str(tok)}))
    if ok:
        assert cfg.read_token() == TOKEN
    else:
        with pytest.raises(ConfigError, match=r"chmod 600") as info:
            cfg.read_token()
        assert f"{mode:04o}" in str(info.value)


@pytest.mark.parametrize(("host", "loop"), [("127.0.0.1", True), ("127.8.9.1", True),
                                            ("::1", True), ("localhost", True),
                                            ("0.0.0.0", False), ("::", False),
                                            ("192.168.1.5", False), ("robot-cell.lan", False)])
def test_loopback_detection(host, loop):
    assert is_loopback(host) is loop


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "robocal.toml"
    p.write_text('robot_description = "fanuc_lrmate200i"\n'
                 '[robot]\nkind = "mock"\noptions = { robot = "fanuc_lrmate200i" }\n'
                 '[tracker]\nkind = "mock"\noptions = { robot = "fanuc_lrmate200i" }\n' + text)
    return p


def test_non_loopback_bind_is_a_loud_warning(tmp_path, capsys):
    tok = tmp_path / "tok"
    tok.write_text(TOKEN)
    tok.chmod(0o600)
    p = _write(tmp_path, f'[api]\ntcp_host = "0.0.0.0"\ntcp_port = 0\ntoken_file = "{tok}"\n')
    assert main(["config", "check", "--drivers", str(p)]) == 0
    out = capsys.readouterr().out
    assert "warning" in out and "0.0.0.0" in out and out.rstrip().endswith(": ok")
    cfg = parse_config(base_config(tmp_path, api={"tcp_host": "127.0.0.1", "tcp_port": 0,
                                                   "token_file": str(tok)}))
    assert config_warnings(cfg) == []


@pytest.mark.parametrize(("extra", "needle"), [
    ('[api]\ntcp_port = 0\ntoken_file = "missing-token"\n', "cannot read token file"),
    ('[api]\ntcp_port = 0\ntoken_file = "loose-token"\n', "chmod 600"),
    ('[fit]\noptions = { no_such_option = 1 }\n', "no_such_option"),
])
def test_config_check_drivers_agrees_with_the_daemon(tmp_path, capsys, extra, needle):
    loose = tmp_path / "loose-token"
    loose.write_text(TOKEN)
    loose.chmod(0o644)
    p = _write(tmp_path, extra)
    assert main(["config", "check", "--drivers", str(p)]) == 1
    out = capsys.readouterr().out
    assert needle in out and out.count("\n") == 1
    # ... and the daemon refuses the same file with one line and exit 2, before serving
    assert main(["daemon", "--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err


def test_non_utf8_configuration_is_one_line(tmp_path, capsys):
    p = tmp_path / "latin1.toml"
    p.write_bytes('robot_description = "Roboter für Zelle 3"\n'.encode("latin-1"))
    assert main(["config", "check", str(p)]) == 1
    out = capsys.readouterr().out
    assert "not UTF-8" in out and out.count("\n") == 1
    assert main(["daemon", "--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert "not UTF-8" in err and err.count("\n") == 1


def test_deeply_nested_toml_is_one_line(tmp_path, capsys):
    p = tmp_path / "deep.toml"
    p.write_text("x = " + "[" * 100_000 + "]" * 100_000 + "\n")
    assert main(["daemon", "--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert "not valid TOML" in err and err.count("\n") == 1


@pytest.mark.parametrize(("mode", "needle"), [(0o644, "mode 0644"), (0o600, None)])
def test_plain_config_check_refuses_a_token_file_the_daemon_refuses(tmp_path, capsys, mode,
                                                                    needle):
    """Without --drivers too: ``config check`` (the unit's ExecStartPre) says what the
    daemon would say about the token file."""
    tok = tmp_path / "tok"
    tok.write_text(TOKEN)
    tok.chmod(mode)
    p = _write(tmp_path, f'[api]\ntcp_port = 0\ntoken_file = "{tok}"\n')
    rc = main(["config", "check", str(p)])
    out = capsys.readouterr().out
    if needle is None:
        assert rc == 0 and out.rstrip().endswith(": ok"), out
    else:
        assert rc == 1 and needle in out and "chmod 600" in out, out
        assert not out.rstrip().endswith(": ok")
