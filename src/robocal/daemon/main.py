"""The daemon's entry point: ``robocal daemon --config FILE`` or ``python -m robocal.daemon``.

Start-up: validate the configuration, take the data directory's lock (one daemon per store),
open the store, connect the drivers, resume interrupted campaigns, serve the API, then tell
systemd ``READY=1``. SIGTERM/SIGINT: ``STOPPING=1``, stop the robot at once, stop serving,
stop fits (campaign states stay, to resume on the next start), close the drivers.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import fcntl
import os
import resource
import signal
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

import structlog

from robocal import __version__
from robocal._core.files import private_dir
from robocal.daemon import systemd
from robocal.daemon.api import ApiServer
from robocal.daemon.config import AppConfig, config_warnings, load_config
from robocal.daemon.fleet import read_password, start_fleet
from robocal.daemon.logging import configure_logging
from robocal.daemon.service import CalibrationService
from robocal.errors import ConfigError, RobocalError

__all__ = ["main", "preflight", "serve"]

_log = structlog.get_logger(__name__)


@contextlib.contextmanager
def data_dir_lock(data_dir: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``data_dir/robocal.lock`` (released by the kernel on exit)."""
    private_dir(data_dir)
    fd = os.open(data_dir / "robocal.lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as err:
            raise ConfigError("another daemon uses this data directory",
                              source=str(data_dir)) from err
        # the pid is for people; a full disk must not stop the daemon from starting (it then
        # serves health and status with the storage fault instead of restarting in a loop)
        try:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
        except OSError as err:
            _log.warning("pid not written to the lock file", error=str(err))
        yield
    finally:
        os.close(fd)


def preflight(config: AppConfig) -> None:
    """Every start-up check that needs no device: robot description, driver kinds and
    options, fit options, the token file. ``robocal config check --drivers`` runs the same.

    Raises
    ------
    ConfigError
        The first problem found (other robocal errors for a driver that cannot be built).
    """
    from robocal.daemon.fitting import fit_options
    from robocal.daemon.hub import DriverHub
    from robocal.kinematics import load_robot

    robot = load_robot(config.robot_description)
    DriverHub(config, robot).validate()
    try:
        fit_options(config.fit.options)
    except (TypeError, ValueError) as err:
        raise ConfigError(str(err), source="fit.options") from err
    config.read_token()
    if config.fleet.password_file is not None:
        read_password(config.fleet.password_file)


async def serve(config: AppConfig, *, stop: asyncio.Event | None = None) -> None:
    """Run the daemon until ``stop`` is set or SIGTERM/SIGINT arrives."""
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    with data_dir_lock(config.data_dir):
        service = CalibrationService(config)
        api = ApiServer(service, config)
        watchdog: asyncio.Task[None] | None = None
        fleet = None
        try:
            systemd.notify("STATUS=starting")
            await service.start()
            fleet = start_fleet(config, robot=service.robot.name)
            await api.start()
            watchdog = asyncio.create_task(systemd.watchdog(), name="watchdog")
            systemd.notify(f"READY=1\nSTATUS=serving ({service.robot.name})")
            _log.info("daemon ready", version=__version__, robot=service.robot.name,
                      data_dir=str(config.data_dir), pid=os.getpid())
            await stop.wait()
        finally:
            systemd.notify("STOPPING=1")
            _log.info("daemon stopping")
            if watchdog is not None:
                watchdog.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await watchdog
            # The robot stops before anything else winds down (the API may take a while).
            await stop_robot_for_shutdown(service)
            # A push or rollback being written finishes (read back, journaled) before the
            # API, whose requests it runs in, is torn down.
            await service.drain()
            service.events.close()
            await api.stop()
            if fleet is not None:
                await fleet.stop()
            await service.stop()
            for sig in (signal.SIGTERM, signal.SIGINT):
                with contextlib.suppress(Exception):
                    loop.remove_signal_handler(sig)
            _log.info("daemon stopped")


async def stop_robot_for_shutdown(service: CalibrationService) -> bool:
    """Stop the robot as the daemon shuts down; a stop that fails or is not confirmed is
    logged as an error (shutdown goes on). Returns True when the halt was confirmed."""
    try:
        ok = await service.stop_motion(trigger="shutdown", reason="daemon stopping")
    except Exception as err:
        _log.error("motion stop at shutdown failed; the robot may still be moving",
                   error=repr(err))
        return False
    if not ok:
        _log.error("motion stop at shutdown not confirmed by the controller")
    return ok


def raise_fd_limit(wanted: int = 65536) -> int:
    """Raise the soft ``RLIMIT_NOFILE`` towards ``wanted`` (not above the hard limit).

    systemd's unit sets ``LimitNOFILE``; outside systemd the soft limit is often 1024. Return
    the soft limit now in force.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if soft != resource.RLIM_INFINITY and soft < target:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


def run(config: AppConfig) -> int:
    """Configure logging and run :func:`serve` (the one ``asyncio.run``); return exit code."""
    try:
        preflight(config)
    except RobocalError as err:
        sys.stderr.write(f"robocal daemon: error: {err}\n")
        return 2
    configure_logging(config.logging.level, config.logging.format)
    fds = raise_fd_limit()
    # Both listeners at their limits plus drivers, store and fit workers must fit.
    if fds < 2 * config.api.max_connections + 64:
        _log.warning("few file descriptors for the API connection limits", nofile=fds,
                     max_connections=config.api.max_connections)
    for warning in config_warnings(config):
        _log.warning("insecure setting", warning=warning)
        sys.stderr.write(f"robocal daemon: WARNING: {warning}\n")
    # Files the daemon creates (reports, models, the socket before its chmod) are not for
    # everybody, whatever umask the caller had; the state directory is 0750 and the
    # database 0600 (see private_dir and Store.open).
    os.umask(0o027)
    try:
        asyncio.run(serve(config))
    except (RobocalError, OSError) as err:
        _log.error("daemon failed", error=str(err))
        systemd.notify(f"STATUS=failed: {err}")
        sys.stderr.write(f"robocal daemon: error: {err}\n")
        return 2
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m robocal.daemon --config FILE``."""
    p = argparse.ArgumentParser(prog="robocal-daemon", description="robocal calibration daemon")
    p.add_argument("--config", required=True, type=Path, help="TOML configuration file")
    args = p.parse_args(argv)
    try:
        config = load_config(args.config)
    except ConfigError as err:
        sys.stderr.write(f"robocal daemon: error: {err}\n")
        return 2
    return run(config)
