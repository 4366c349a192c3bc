"""The calibration daemon: campaigns, store, executor, fits, compensation pushes and the API.

Public entry points: :class:`AppConfig` / :func:`load_config` (configuration),
:class:`CalibrationService` (the async facade, also used in-process by ``robocal demo``),
:class:`CampaignState` and :data:`TRANSITIONS` (the state machine), :func:`serve` (the
long-running service). Heavy modules are imported lazily.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from robocal.daemon.campaign import TRANSITIONS, CampaignState, check_transition
from robocal.daemon.config import AppConfig, config_errors, load_config, parse_config

if TYPE_CHECKING:
    from robocal.daemon._plan import CampaignPlan, parse_plan, plan_from_poses
    from robocal.daemon.main import serve
    from robocal.daemon.service import CalibrationService

__all__ = [
    "TRANSITIONS",
    "AppConfig",
    "CalibrationService",
    "CampaignPlan",
    "CampaignState",
    "check_transition",
    "config_errors",
    "load_config",
    "parse_config",
    "parse_plan",
    "plan_from_poses",
    "serve",
]


# Lazy attributes, kept on purpose: the client commands (``robocal campaign``, ``robocal
# compensation``, ``robocal config check``) import this package for its light modules, and
# importing the service and the daemon's main (aiohttp, numpy, ...) or the plan reader
# (robocal.planning, scipy) up front would add 1.2-1.5 s to each of them (python -X
# importtime: robocal.daemon.client 0.25 s alone, 1.5 s with service and main; _plan 1.3 s).
def __getattr__(name: str) -> object:
    found: dict[str, object]
    if name in ("CampaignPlan", "parse_plan", "plan_from_poses"):
        from robocal.daemon._plan import CampaignPlan, parse_plan, plan_from_poses

        found = {"CampaignPlan": CampaignPlan, "parse_plan": parse_plan,
                 "plan_from_poses": plan_from_poses}
    elif name in ("CalibrationService", "serve"):
        from robocal.daemon.main import serve
        from robocal.daemon.service import CalibrationService

        found = {"CalibrationService": CalibrationService, "serve": serve}
    else:
        raise AttributeError(f"module 'robocal.daemon' has no attribute {name!r}")
    globals().update(found)  # each module is looked up once
    return found[name]
