"""Fixtures for daemon unit tests: configurations over mock drivers, small plans."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from robocal.daemon._plan import CampaignPlan, parse_plan, plan_from_poses
from robocal.daemon.config import AppConfig, parse_config
from robocal.daemon.service import CalibrationService
from robocal.kinematics import load_robot

ROBOT = "fanuc_lrmate200i"


def base_config(tmp_path: Path, **sections: Any) -> dict[str, Any]:
    """A configuration mapping over the mock drivers (thread fits, constant model only)."""
    cfg: dict[str, Any] = {
        "data_dir": str(tmp_path / "state"),
        "robot_description": ROBOT,
        "robot": {"kind": "mock", "options": {"robot": ROBOT}},
        "tracker": {"kind": "mock", "options": {"robot": ROBOT}},
        "measurement": {"settle_s": 0.0, "backoff_s": 0.001, "max_backoff_s": 0.01},
        "fit": {"models": ["constant"], "select": "constant", "executor": "thread",
                "report": False, "cpa": False},
    }
    for key, value in sections.items():
        if isinstance(value, dict) and isinstance(cfg.get(key), dict):
            merged = dict(cfg[key])
            for k, v in value.items():
                if isinstance(v, dict) and isinstance(merged.get(k), dict):
                    merged[k] = {**merged[k], **v}
                else:
                    merged[k] = v
            cfg[key] = merged
        else:
            cfg[key] = value
    return cfg


@pytest.fixture
def make_config(tmp_path: Path) -> Callable[..., AppConfig]:
    def make(**sections: Any) -> AppConfig:
        return parse_config(base_config(tmp_path, **sections), source="test")

    return make


@pytest.fixture
async def service(make_config: Callable[..., AppConfig]) -> AsyncIterator[
        Callable[..., Awaitable[CalibrationService]]]:
    """A factory of started services on ``make_config(**sections)``; all are stopped after
    the test."""
    made: list[CalibrationService] = []

    async def make(**sections: Any) -> CalibrationService:
        svc = CalibrationService(make_config(**sections))
        await svc.start()
        made.append(svc)
        return svc

    yield make
    for svc in made:
        await svc.stop()


@pytest.fixture
async def svc(service: Callable[..., Awaitable[CalibrationService]]) -> CalibrationService:
    """A started service on the default test configuration."""
    return await service()


def random_plan(n: int, *, seed: int = 0, validation: int = 0, via_every: int = 0) -> CampaignPlan:
    """A bare plan of ``n`` random poses well inside the limits (last ``validation`` held out)."""
    robot = load_robot(ROBOT)
    rng = np.random.default_rng(seed)
    lim = np.degrees(robot.joint_limits)
    q = rng.uniform(lim[:, 0] + 10, lim[:, 1] - 10, (n, robot.dof))
    purposes = ["calibration" if i < n - validation else "validation" for i in range(n)]
    doc = plan_from_poses(q.tolist(), robot=ROBOT, purposes=purposes)
    if via_every:
        poses = []
        for i, p in enumerate(doc["poses"]):
            if i and i % via_every == 0:
                poses.append({"q_deg": p["q_deg"], "purpose": "via", "measure": False})
            poses.append(p)
        doc["poses"] = poses
    return parse_plan(doc, source="test", strict=False)


@pytest.fixture(scope="session")
def real_plan() -> dict[str, Any]:
    """A small, complete robocal.plan/1 document from the planner (demo cell)."""
    from robocal.planning import plan_campaign

    plan = plan_campaign(ROBOT, "demo", count=20, model="constant", validation=5, cpa=False,
                         iso=False, seed=3, candidates=256)
    return json.loads(plan.to_json())
