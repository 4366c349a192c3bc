"""Protocol simulators on loopback, all driven by one shared :class:`SimWorld`.

In-process (tests, benchmarks)::

    async with SimCell(seed=1, ltp_pty=True) as cell:
        robot = load_robot_driver("fanuc_rmi", cell.robot_options("fanuc_rmi"))
        tracker = load_tracker_driver("ltp", cell.tracker_options("tcp"))

As a process (``robocal sim ...`` calls :func:`main`; also ``python -m robocal.drivers.sim``)::

    robocal sim all --seed 3 --pty --fault-rate 0.1 --ports-file ports.json

prints the bound ports as one JSON line (and writes them to ``--ports-file``), then serves
until SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import structlog

from robocal.drivers.sim._server import publish_ports, until_signalled
from robocal.drivers.sim.abb_rws import AbbRwsSimulator, AbbSimOptions
from robocal.drivers.sim.emscon import EmsconSimOptions, EmsconTrackerSimulator
from robocal.drivers.sim.fanuc_rmi import FanucRmiSimulator, FanucSimOptions
from robocal.drivers.sim.faults import FaultConfig, FaultInjector
from robocal.drivers.sim.kuka_kvp import KukaKvpSimulator, KukaSimOptions
from robocal.drivers.sim.ltp_tracker import LtpSimOptions, LtpTrackerSimulator
from robocal.drivers.sim.modbus_plc import ModbusPlcSimulator, ModbusSimOptions
from robocal.drivers.sim.universal_robots import UrSimOptions, UrSimulator
from robocal.drivers.sim.world import DEFAULT_ROBOT, SimWorld
from robocal.simulation import SCENARIOS

__all__ = [
    "DEFAULT_ROBOT",
    "AbbRwsSimulator",
    "AbbSimOptions",
    "EmsconSimOptions",
    "EmsconTrackerSimulator",
    "FanucRmiSimulator",
    "FanucSimOptions",
    "FaultConfig",
    "FaultInjector",
    "KukaKvpSimulator",
    "KukaSimOptions",
    "LtpSimOptions",
    "LtpTrackerSimulator",
    "ModbusPlcSimulator",
    "ModbusSimOptions",
    "SimCell",
    "SimWorld",
    "UrSimOptions",
    "UrSimulator",
    "main",
]

_log = structlog.get_logger(__name__)


class SimCell:
    """Start any of the three simulators around one world; an async context manager.

    Parameters
    ----------
    robot, scenario, seed
        Virtual cell (``VirtualCell.create``); ignored when ``world`` is given.
    world : SimWorld, optional
        An existing world to serve.
    fanuc, modbus, ltp : bool or options
        Which simulators to run (True: default options; False: not at all).
    ltp_tcp, ltp_pty : bool
        Serve the tracker on TCP and/or on a pty pair.
    emscon : bool or options
        Run the emScon tracker simulator (off by default).
    kuka : bool or options
        Run the KUKA KUKAVARPROXY simulator (off by default).
    abb : bool or options
        Run the ABB Robot Web Services simulator (off by default).
    ur : bool or options
        Run the Universal Robots simulator (off by default).
    faults : FaultConfig, optional
        Injected faults, shared by all simulators (each draws with its own generator).
    host : str
        Listening address (loopback).
    ports : dict, optional
        Fixed ports: ``fanuc_connect``, ``fanuc_main``, ``modbus``, ``ltp``, ``emscon``,
        ``kuka``, ``abb``, ``ur_dashboard``, ``ur_primary``, ``ur_secondary``,
        ``ur_realtime``, ``ur_rtde`` (0: free port).
    ur_host : str, optional
        Listening address of the UR simulator (default ``host``); ur-rtde reaches RTDE on
        port 30004 only, so tests give it a loopback address of its own.

    Attributes
    ----------
    fanuc_sim, modbus_sim, ltp_sim, emscon_sim, kuka_sim, abb_sim, ur_sim
        The running simulators (None when not requested).
    """

    def __init__(
        self,
        *,
        robot: str = DEFAULT_ROBOT,
        scenario: str = "paper",
        seed: int = 1,
        world: SimWorld | None = None,
        fanuc: bool | FanucSimOptions = True,
        modbus: bool | ModbusSimOptions = True,
        ltp: bool | LtpSimOptions = True,
        ltp_tcp: bool = True,
        ltp_pty: bool = False,
        emscon: bool | EmsconSimOptions = False,
        kuka: bool | KukaSimOptions = False,
        abb: bool | AbbSimOptions = False,
        ur: bool | UrSimOptions = False,
        ur_host: str | None = None,
        faults: FaultConfig | None = None,
        host: str = "127.0.0.1",
        ports: dict[str, int] | None = None,
    ) -> None:
        self.robot, self.scenario, self.seed = robot, scenario, seed
        self._world = world
        self._fanuc, self._modbus, self._ltp = fanuc, modbus, ltp
        self.ltp_tcp, self.ltp_pty = ltp_tcp, ltp_pty
        self._emscon = emscon
        self._kuka = kuka
        self._abb = abb
        self.abb_sim: AbbRwsSimulator | None = None
        self._ur = ur
        self.ur_host = ur_host or host
        self.faults = faults
        self.host = host
        self._fixed = dict(ports or {})
        self.fanuc_sim: FanucRmiSimulator | None = None
        self.modbus_sim: ModbusPlcSimulator | None = None
        self.ltp_sim: LtpTrackerSimulator | None = None
        self.emscon_sim: EmsconTrackerSimulator | None = None
        self.kuka_sim: KukaKvpSimulator | None = None
        self.ur_sim: UrSimulator | None = None

    @property
    def world(self) -> SimWorld:
        """The shared world (created on first use)."""
        if self._world is None:
            self._world = SimWorld.create(self.robot, self.scenario, self.seed)
        return self._world

    async def start(self) -> SimCell:
        """Start the requested simulators."""
        world, p = self.world, self._fixed
        try:
            if self._fanuc is not False:
                opts = self._fanuc if isinstance(self._fanuc, FanucSimOptions) else None
                self.fanuc_sim = FanucRmiSimulator(world, opts, self.faults)
                await self.fanuc_sim.start(
                    self.host, p.get("fanuc_connect", 0), p.get("fanuc_main", 0)
                )
            if self._modbus is not False:
                mopts = self._modbus if isinstance(self._modbus, ModbusSimOptions) else None
                self.modbus_sim = ModbusPlcSimulator(world, mopts, self.faults)
                await self.modbus_sim.start(self.host, p.get("modbus", 0))
            if self._ltp is not False:
                lopts = self._ltp if isinstance(self._ltp, LtpSimOptions) else None
                self.ltp_sim = LtpTrackerSimulator(world, lopts, self.faults)
                if self.ltp_tcp:
                    await self.ltp_sim.start_tcp(self.host, p.get("ltp", 0))
                if self.ltp_pty:
                    await self.ltp_sim.start_pty()
            if self._emscon is not False:
                eopts = self._emscon if isinstance(self._emscon, EmsconSimOptions) else None
                self.emscon_sim = EmsconTrackerSimulator(world, eopts, self.faults)
                await self.emscon_sim.start(self.host, p.get("emscon", 0))
            if self._kuka is not False:
                kopts = self._kuka if isinstance(self._kuka, KukaSimOptions) else None
                self.kuka_sim = KukaKvpSimulator(world, kopts, self.faults)
                await self.kuka_sim.start(self.host, p.get("kuka", 0))
            if self._abb is not False:
                aopts = self._abb if isinstance(self._abb, AbbSimOptions) else None
                self.abb_sim = AbbRwsSimulator(world, aopts, self.faults)
                await self.abb_sim.start(self.host, p.get("abb", 0))
            if self._ur is not False:
                uopts = self._ur if isinstance(self._ur, UrSimOptions) else None
                self.ur_sim = UrSimulator(world, uopts, self.faults)
                await self.ur_sim.start(
                    self.ur_host, dashboard=p.get("ur_dashboard", 0),
                    primary=p.get("ur_primary", 0), secondary=p.get("ur_secondary", 0),
                    rtde_port=p.get("ur_rtde", 0), realtime=p.get("ur_realtime", 0),
                )
        except BaseException:
            await self.stop()
            raise
        return self

    async def stop(self) -> None:
        """Stop every simulator; idempotent."""
        for sim in (self.ur_sim, self.abb_sim, self.kuka_sim, self.emscon_sim, self.ltp_sim,
                    self.modbus_sim, self.fanuc_sim):
            if sim is not None:
                await sim.stop()

    async def __aenter__(self) -> SimCell:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    @property
    def ports(self) -> dict[str, Any]:
        """Bound endpoints as JSON-ready data."""
        out: dict[str, Any] = {"host": self.host, "robot": self.world.robot_name}
        if self.fanuc_sim is not None:
            out["fanuc_rmi"] = {
                "connect_port": self.fanuc_sim.connect_port,
                "main_port": self.fanuc_sim.main_port,
            }
        if self.modbus_sim is not None:
            out["modbus_plc"] = {"port": self.modbus_sim.port}
        if self.ltp_sim is not None:
            out["ltp_tracker"] = {
                "port": self.ltp_sim.port or None,
                "pty": self.ltp_sim.pty_path,
            }
        if self.emscon_sim is not None:
            out["emscon_tracker"] = {"port": self.emscon_sim.port}
        if self.kuka_sim is not None:
            out["kuka_kvp"] = {"port": self.kuka_sim.port}
        if self.abb_sim is not None:
            out["abb_rws"] = {"port": self.abb_sim.port,
                              "robotware": self.abb_sim.options.robotware}
        if self.ur_sim is not None:
            out["universal_robots"] = {"host": self.ur_host, **self.ur_sim.ports}
        return out

    def robot_options(
        self,
        kind: Literal["fanuc_rmi", "modbus_plc", "kuka_kvp", "abb_rws", "universal_robots",
                      "mock"],
    ) -> dict[str, Any]:
        """Options for ``load_robot_driver(kind, ...)`` pointing at this cell's simulator."""
        limits = [list(lim) for lim in self.world.joint_limits_deg]
        if kind == "kuka_kvp":
            if self.kuka_sim is None:
                raise RuntimeError("the KUKA KVP simulator is not running")
            return {"host": self.host, "port": self.kuka_sim.port, "joint_limits_deg": limits,
                    "poll_interval_s": 0.001, "comp_size": self.kuka_sim.options.comp_size}
        if kind == "fanuc_rmi":
            if self.fanuc_sim is None:
                raise RuntimeError("the FANUC RMI simulator is not running")
            return {
                "host": self.host,
                "connect_port": self.fanuc_sim.connect_port,
                "joint_limits_deg": limits,
            }
        if kind == "abb_rws":
            if self.abb_sim is None:
                raise RuntimeError("the ABB RWS simulator is not running")
            # the simulator serves plain HTTP on loopback, also for RobotWare 7
            return {"host": self.host, "port": self.abb_sim.port, "scheme": "http",
                    "robotware": self.abb_sim.options.robotware, "joint_limits_deg": limits,
                    "poll_interval_s": 0.002}
        if kind == "modbus_plc":
            if self.modbus_sim is None:
                raise RuntimeError("the Modbus PLC simulator is not running")
            return {
                "host": self.host,
                "port": self.modbus_sim.port,
                "joint_limits_deg": limits,
                "register_map": self.modbus_sim.map.model_dump(),
                "poll_interval_s": 0.001,
            }
        if kind == "universal_robots":
            if self.ur_sim is None:
                raise RuntimeError("the Universal Robots simulator is not running")
            ports = self.ur_sim.ports
            return {
                "host": self.ur_host,
                "dashboard_port": ports["dashboard"],
                "primary_port": ports["primary"],
                "rtde_port": ports["rtde"],
                "rtde_frequency_hz": 500.0,  # the simulator reports an e-Series controller
                "joint_limits_deg": limits,
            }
        return {"robot": self.robot, "scenario": self.scenario, "seed": self.seed}

    def tracker_options(self, via: Literal["tcp", "socket", "pty"] = "tcp") -> dict[str, Any]:
        """Options for ``load_tracker_driver("ltp", ...)`` over TCP, pyserial ``socket://`` or
        the pty."""
        sim = self.ltp_sim
        if sim is None:
            raise RuntimeError("the LTP tracker simulator is not running")
        if via == "pty":
            if sim.pty_path is None:
                raise RuntimeError("the tracker simulator has no pty (ltp_pty=False)")
            return {"url": f"serial://{sim.pty_path}?baudrate=115200"}
        if not sim.port:
            raise RuntimeError("the tracker simulator has no TCP port (ltp_tcp=False)")
        scheme = "tcp" if via == "tcp" else "socket"
        return {"url": f"{scheme}://{self.host}:{sim.port}"}

    def emscon_options(self) -> dict[str, Any]:
        """Options for ``load_tracker_driver("emscon", ...)`` pointing at the emScon simulator."""
        if self.emscon_sim is None:
            raise RuntimeError("the emScon tracker simulator is not running")
        return {"host": self.host, "port": self.emscon_sim.port}


# --- process entry point -----------------------------------------------------------------------
class _DefaultsShown(argparse.HelpFormatter):
    """Every option's default in its help, unless it has none (None, a flag, "")."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if (not action.option_strings or action.default in (None, "", argparse.SUPPRESS)
                or isinstance(action.default, bool)):
            return text
        return f"{text} (default: %(default)s)"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="robocal sim",
        description="Run protocol simulators on loopback until SIGTERM/SIGINT. The robot is "
                    "the virtual robot of 'robocal simulate' and 'robocal demo' (same "
                    "scenarios, same seed default).",
        formatter_class=_DefaultsShown,
    )
    p.add_argument(
        "which",
        choices=["fanuc-rmi", "modbus-plc", "ltp-tracker", "emscon-tracker", "ur", "kuka", "abb",
                 "all", "relay"],
    )
    p.add_argument("--robot", default=DEFAULT_ROBOT, help="built-in robot name")
    p.add_argument("--scenario", default="paper", choices=SCENARIOS,
                   help="planted errors of the virtual robot (see robocal simulate --help)")
    p.add_argument("--seed", type=int, default=1,
                   help="seed of the planted errors, noise and faults (as plan, simulate, demo)")
    p.add_argument("--warmup-drift-mm", type=float, default=0.0,
                   help="plant a warm-up drift: the links grow by this much (mm, in all) over "
                        "30 min of motion from cold; joint temperatures follow (ADR 0042)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on")
    p.add_argument(
        "--port",
        type=int,
        default=0,
        help="first port (0: free ports). all: fanuc P, P+1; modbus P+2; ltp P+3; emscon P+4; "
        "ur P+5, P+7, P+8, P+10, P+11; kuka P+6; abb P+9. ur: dashboard P, primary P+2, "
        "secondary P+3, real-time P+4, RTDE P+5 (P=29999 gives the real ports)",
    )
    p.add_argument("--pty", action="store_true", help="also serve the tracker on a pty")
    p.add_argument("--fault-rate", type=float, default=0.0,
                   help="probability per tracker reading of a beam break or an unstable "
                        "reading (0..1)")
    p.add_argument("--time-scale", type=float, default=0.001,
                   help="factor on the real duration of moves and waits: 1 = real time, "
                        "0.001 = 1000x faster than real time, 0 = instantaneous")
    p.add_argument("--ports-file", type=Path, help="write the bound ports as JSON here")
    p.add_argument("--drift-deg-per-day", type=_rates, metavar="R1,R2,...",
                   help="plant a drift: joint zero offsets growing by these rates (deg/day, "
                        "per joint from J1) on a simulated clock (robocal check, ADR 0041)")
    p.add_argument("--days-per-minute", type=float, default=1.0,
                   help="the drift's simulated clock: days passing per real minute")
    p.add_argument("--robotware", type=int, choices=[6, 7], default=6,
                   help="abb: RobotWare 6 (RWS 1.0, digest) or 7 (RWS 2.0, basic)")
    p.add_argument("--replay", type=Path, help="emscon-tracker: answer from this recording")
    p.add_argument("--listen", default="127.0.0.1:0", help="relay: HOST:PORT to listen on")
    p.add_argument("--target", help="relay: the tracker's HOST:PORT (e.g. 192.168.0.1:700)")
    p.add_argument("--record", type=Path, help="relay: JSON-lines capture file to write")
    return p


def _rates(text: str) -> tuple[float, ...]:
    try:
        rates = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not comma-separated numbers: {text!r}") from None
    if not all(math.isfinite(r) for r in rates):
        raise argparse.ArgumentTypeError(f"rates must be finite: {text!r}")
    return rates


async def drift_clock(world: SimWorld, days_per_minute: float, *, period_s: float = 1.0
                      ) -> None:
    """Advance the virtual robot's drift clock (``sim_days``) with real time until cancelled:
    ``days_per_minute`` simulated days per real minute, updated every ``period_s``."""
    t0 = time.monotonic()
    while True:
        world.cell.sim_days = (time.monotonic() - t0) / 60.0 * days_per_minute
        await asyncio.sleep(period_s)


def _fixed_ports(which: str, port: int) -> dict[str, int]:
    if port == 0:
        return {}
    if which == "fanuc-rmi":
        return {"fanuc_connect": port, "fanuc_main": port + 1}
    if which == "modbus-plc":
        return {"modbus": port}
    if which == "ltp-tracker":
        return {"ltp": port}
    if which == "emscon-tracker":
        return {"emscon": port}
    if which == "kuka":
        return {"kuka": port}
    if which == "abb":
        return {"abb": port}
    if which == "ur":
        return _ur_ports(port)
    return {
        **_ur_ports(port + 5),
        "ur_realtime": port + 11,  # port + 9 (the real spacing) is ABB's
        "fanuc_connect": port,
        "fanuc_main": port + 1,
        "modbus": port + 2,
        "ltp": port + 3,
        "emscon": port + 4,
        "kuka": port + 6,
        "abb": port + 9,
    }


def _ur_ports(port: int) -> dict[str, int]:
    """The UR ports from the dashboard's, with the real controller's spacing."""
    return {"ur_dashboard": port, "ur_primary": port + 2, "ur_secondary": port + 3,
            "ur_realtime": port + 4, "ur_rtde": port + 5}


async def _serve(args: argparse.Namespace) -> int:
    which = args.which
    if which == "relay" or (which == "emscon-tracker" and args.replay is not None):
        from robocal.drivers.sim.relay import serve_cli

        return await serve_cli(args)
    scale = args.time_scale
    cell = SimCell(
        robot=args.robot,
        scenario=args.scenario,
        seed=args.seed,
        world=SimWorld.create(args.robot, args.scenario, args.seed,
                              warmup_drift_mm=args.warmup_drift_mm),
        fanuc=FanucSimOptions(time_scale=scale) if which in ("fanuc-rmi", "all") else False,
        modbus=ModbusSimOptions(time_scale=scale) if which in ("modbus-plc", "all") else False,
        ltp=LtpSimOptions(time_scale=scale) if which in ("ltp-tracker", "all") else False,
        ltp_pty=args.pty,
        emscon=(
            EmsconSimOptions(time_scale=scale) if which in ("emscon-tracker", "all") else False
        ),
        kuka=KukaSimOptions(time_scale=scale) if which in ("kuka", "all") else False,
        abb=(
            AbbSimOptions(time_scale=scale, robotware=args.robotware)
            if which in ("abb", "all") else False
        ),
        ur=UrSimOptions(time_scale=scale) if which in ("ur", "all") else False,
        faults=FaultConfig.uniform(args.fault_rate, seed=args.seed),
        host=args.host,
        ports=_fixed_ports(which, args.port),
    )
    async with until_signalled() as stop, cell:
        publish_ports(cell.ports, args.ports_file)
        clock = None
        if args.drift_deg_per_day:
            cell.world.cell.drift_deg_per_day = args.drift_deg_per_day
            clock = asyncio.create_task(drift_clock(cell.world, args.days_per_minute))
        await stop.wait()
        if clock is not None:
            clock.cancel()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``robocal sim fanuc-rmi|modbus-plc|ltp-tracker|emscon-tracker|ur|kuka|abb|all|relay
    [options]``."""
    args = _parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    if not structlog.is_configured():
        # stdout carries the ports JSON; keep log lines off it.
        structlog.configure(logger_factory=structlog.PrintLoggerFactory(file=sys.stderr))
    if not 0.0 <= args.fault_rate <= 1.0:
        sys.stderr.write("robocal sim: --fault-rate must be within [0, 1]\n")
        return 2
    if not args.warmup_drift_mm >= 0.0:
        sys.stderr.write("robocal sim: --warmup-drift-mm must not be negative\n")
        return 2
    try:
        return asyncio.run(_serve(args))
    except OSError as err:
        sys.stderr.write(f"robocal sim: {err}\n")
        return 1
