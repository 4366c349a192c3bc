"""What is checked before a campaign is created: the plan and the devices.

:func:`checked_plan` parses a plan and checks it against the daemon's robot (name, joint
limits with the configured margin) and cell (the swept path of every move), off the event
loop; :func:`preflight` connects robot and tracker, so a campaign that cannot run is never
stored.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import structlog

from robocal.daemon._plan import CampaignPlan, parse_plan, unsafe_moves
from robocal.daemon.config import AppConfig
from robocal.daemon.engine import limits_with_margin
from robocal.daemon.hub import DriverHub
from robocal.drivers import check_joint_target
from robocal.errors import ConfigError, ConnectFailed, DriverError, LimitViolation, ProtocolError
from robocal.kinematics import RobotDescription
from robocal.planning import load_cell

__all__ = ["check_plan", "checked_plan", "preflight"]

_log = structlog.get_logger(__name__)


def check_plan(plan: CampaignPlan, robot: RobotDescription, config: AppConfig) -> None:
    """Refuse (ConfigError, naming the pose) a plan for another robot, with a pose outside
    the joint limits less the margin, or with an unsafe move in the cell."""
    if plan.robot and plan.robot not in (robot.name, config.robot_description):
        names = {robot.name, Path(config.robot_description).stem}
        if plan.robot not in names:
            raise ConfigError(f"plan is for robot {plan.robot!r}, the daemon drives "
                              f"{robot.name!r}", source="plan", key="robot")
    limits = limits_with_margin(robot, config.limits.joint_margin_deg)
    for p in plan.poses:
        try:
            check_joint_target([math.radians(v) for v in p.q_deg], limits, kind="plan")
        except LimitViolation as err:
            raise ConfigError(f"pose {p.idx}: {err} (joint margin "
                              f"{config.limits.joint_margin_deg} deg)",
                              source="plan", key=f"poses[{p.idx}]") from err
    # Motion safety is recomputed for every move (swept path: floor, keep-out boxes,
    # self-collision) in the daemon's cell, else the plan's; the plan's flags are ignored.
    cell = load_cell(config.cell) if config.cell else plan.cell
    if cell is None:
        return
    unsafe = unsafe_moves(plan, robot, cell, limits)
    if unsafe:
        _log.warning("plan refused: unsafe moves", count=len(unsafe), cell=cell.name,
                     poses=[u.index for u in unsafe])
        raise ConfigError(
            f"{len(unsafe)} unsafe move(s) in cell {cell.name!r}, nothing started: "
            + "; ".join(u.describe() for u in unsafe), source="plan",
            key=f"poses[{unsafe[0].index}]")


async def checked_plan(plan: Mapping[str, Any] | str | CampaignPlan, robot: RobotDescription,
                       config: AppConfig) -> CampaignPlan:
    """:func:`parse_plan` and :func:`check_plan`, off the event loop (which keeps serving)."""
    doc = plan if isinstance(plan, CampaignPlan) else await asyncio.to_thread(parse_plan, plan)
    # the swept-path check takes a while on long plans: off the event loop, in a thread
    # that ends with it
    with ThreadPoolExecutor(1, thread_name_prefix="plan-check") as pool:
        await asyncio.get_running_loop().run_in_executor(pool, check_plan, doc, robot, config)
    return doc


async def preflight(hub: DriverHub, config: AppConfig) -> dict[str, str]:
    """Connect to the robot and the tracker before anything is stored or moved; return
    their driver kinds.

    Raises
    ------
    ConnectFailed
        Naming the device that does not answer and why; nothing was created.
    """
    out: dict[str, str] = {}
    for what, cfg, connect in (("robot", config.robot, hub.robot),
                               ("tracker", config.tracker, hub.tracker)):
        try:
            await connect()
        except (DriverError, ProtocolError, OSError, TimeoutError) as err:
            await hub.reset(f"pre-flight: {what} unreachable")
            raise ConnectFailed(
                f"the {what} ({cfg.kind}) does not answer: {err}. Nothing was started; "
                f"check that it is on and reachable, then try again") from err
        out[what] = cfg.kind
    return out
