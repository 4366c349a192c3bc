"""``robocal config check FILE`` and ``robocal config schema``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from robocal.cli._command import command


def register(sub: Any) -> None:
    """Add the ``config`` subcommand."""
    p = command(sub, "config", None)
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    c = command(verbs, "check", check, parent="config")
    c.add_argument("files", nargs="*", type=Path, metavar="FILE")
    c.add_argument("--config", action="append", type=Path, default=[], metavar="FILE",
                   help="a configuration file (like the other commands; repeatable)")
    c.add_argument("--drivers", action="store_true",
                   help="also build (not connect) the drivers to validate their options")
    c.add_argument("--connect", action="store_true",
                   help="also connect to the robot and the tracker (pre-flight check of the "
                        "cell); implies --drivers")
    command(verbs, "schema", schema, parent="config")


def check(args: argparse.Namespace) -> int:
    """Print every problem; exit 0 when all files are valid, 1 otherwise.

    The token file is always checked as the daemon checks it (readable, mode 0600, long
    enough). With ``--drivers`` the daemon's other start-up checks run too
    (:func:`preflight`: driver options, fit options), so a file that passes is one the
    daemon accepts.
    Risky settings (a non-loopback TCP bind) are printed as warnings and do not fail.
    """
    from robocal.daemon.config import config_errors, config_warnings, load_config
    from robocal.errors import ConfigError, RobocalError

    files = [*args.files, *args.config]
    if not files:
        raise ConfigError("name a configuration file: robocal config check --config FILE")
    bad = 0
    for path in files:
        errors = config_errors(path)
        warnings: list[str] = []
        if not errors:
            try:
                cfg = load_config(path)
                warnings = config_warnings(cfg)
                # the token file is the daemon's own start-up check and needs no device:
                # a file the daemon refuses (mode 0644, too short) is an error here too
                cfg.read_token()
                if args.drivers or args.connect:
                    from robocal.daemon.main import preflight

                    preflight(cfg)
                if args.connect:
                    for line in _connect(cfg):
                        sys.stdout.write(f"{path}: {line}\n")
            except RobocalError as err:
                errors = [f"{path}: {err}"]
        for w in warnings:
            sys.stdout.write(f"{path}: warning: {w}\n")
        if errors:
            bad += 1
            for e in errors:
                sys.stdout.write(f"{e}\n")
        else:
            sys.stdout.write(f"{path}: ok\n")
    return 1 if bad else 0


def _connect(cfg: Any) -> list[str]:
    """Connect to each configured device once; raise ConnectFailed naming the one down."""
    import asyncio

    from robocal.daemon.service import CalibrationService

    async def run() -> dict[str, str]:
        svc = CalibrationService(cfg)
        try:
            return await svc.preflight()
        finally:
            await svc.hub.close()

    return [f"{what} ({kind}) answers" for what, kind in asyncio.run(run()).items()]


def schema(args: argparse.Namespace) -> int:
    """Print the JSON schema of the configuration."""
    from robocal.daemon.config import AppConfig

    sys.stdout.write(json.dumps(AppConfig.model_json_schema(), indent=1) + "\n")
    return 0
