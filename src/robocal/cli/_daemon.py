"""``robocal daemon --config FILE``: run the calibration daemon in the foreground."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(sub: Any) -> None:
    """Add the ``daemon`` subcommand."""
    p = sub.add_parser("daemon", help="run the calibration daemon (systemd Type=notify)",
                       description="Run the long-running calibration service: drivers, "
                                   "campaigns, fits, compensation, local HTTP API. Logs JSON "
                                   "lines to stdout.")
    p.add_argument("--config", required=True, type=Path, help="TOML configuration file")
    p.set_defaults(handler=run)


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
