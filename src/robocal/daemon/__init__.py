"""The calibration daemon: campaigns, store, executor, fits, compensation pushes and the API.

Public entry points: :class:`AppConfig` / :func:`load_config` (configuration),
:class:`CalibrationService` (the async facade, also used in-process by ``robocal demo``),
:class:`CampaignState` and :data:`TRANSITIONS` (the state machine), :func:`serve` (the
long-running service). Heavy modules are imported lazily.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from robocal.daemon.campaign import TRANSITIONS, CampaignState, check_transition
from robocal.daemon.config import AppConfig, config_errors, load_config, parse_config

if TYPE_CHECKING:
    from robocal.daemon._plan import PlanDoc, parse_plan, plan_from_poses
    from robocal.daemon.main import serve
    from robocal.daemon.service import CalibrationService

__all__ = [
    "TRANSITIONS",
    "AppConfig",
    "CalibrationService",
    "CampaignState",
    "PlanDoc",
    "check_transition",
    "config_errors",
    "load_config",
    "parse_config",
    "parse_plan",
    "plan_from_poses",
    "serve",
]


def __getattr__(name: str) -> Any:
    if name == "CalibrationService":
        from robocal.daemon.service import CalibrationService

        return CalibrationService
    if name in ("PlanDoc", "parse_plan", "plan_from_poses"):
        from robocal.daemon import _plan

        return getattr(_plan, name)
    if name == "serve":
        from robocal.daemon.main import serve

        return serve
    raise AttributeError(f"module 'robocal.daemon' has no attribute {name!r}")
