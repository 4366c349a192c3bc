"""``robocal daemon --config FILE``: run the calibration daemon in the foreground."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from robocal.cli._command import command


def register(sub: Any) -> None:
    """Add the ``daemon`` subcommand."""
    p = command(sub, "daemon", run)
    p.add_argument("--config", required=True, type=Path, help="TOML configuration file")


def run(args: argparse.Namespace) -> int:
    """Validate the configuration and serve until SIGTERM."""
    from robocal.errors import ConfigError

    # before the daemon's imports (aiohttp, numpy, pydantic): a wrong path is answered at once
    if not args.config.is_file():
        raise ConfigError("file not found" if not args.config.exists() else "not a file",
                          source=str(args.config))
    from robocal.daemon.config import load_config
    from robocal.daemon.main import run as run_daemon

    return run_daemon(load_config(args.config))
