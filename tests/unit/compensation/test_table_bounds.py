"""Compensation tables are verified on load: numbers beyond physical bounds are refused
(one ConfigError naming the key), and a first frames push is bounded by the limits."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from robocal.compensation import CompensationTable
from robocal.daemon.config import LimitsConfig
from robocal.daemon.pushing import check_bounds
from robocal.errors import CompensationError, ConfigError
from robocal.kinematics import load_robot


def _frames(base: dict[str, float], tool: dict[str, float] | None = None) -> dict[str, Any]:
    zero = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0, "p": 0.0, "r": 0.0}
    return {"kind": "frames", "model_id": "0123456789abcdef", "robot": "fanuc_lrmate200i",
            "valid_range_deg": [[-90.0, 90.0]] * 6, "predicted_residual_mm": 0.1,
            "frames": {"base": {**zero, **base}, "tool": {**zero, **(tool or {})}}}


@pytest.mark.parametrize(("base", "key"), [({"x": -1e308}, "frames.base.x"),
                                           ({"r": 1e6}, "frames.base.r")])
def test_absurd_frames_are_refused_on_load(tmp_path: Path, base: dict[str, float],
                                           key: str) -> None:
    p = tmp_path / "table.json"
    p.write_text(json.dumps(_frames(base)))
    with pytest.raises(ConfigError) as info:
        CompensationTable.read(p)
    assert key in str(info.value)


def test_a_first_frames_push_is_bounded() -> None:
    robot = load_robot("fanuc_lrmate200i")
    t = [v * 1e3 for v in robot.tool]
    tool = {"x": float(t[0]), "y": float(t[1]), "z": float(t[2])}
    limits = LimitsConfig(max_base_distance_mm=20_000.0)
    near = CompensationTable.model_validate(_frames({"x": 3000.0, "y": -500.0}, tool)).sealed()
    check_bounds(near, limits, robot, previous=None)
    far = CompensationTable.model_validate(_frames({"x": 90_000.0}, tool)).sealed()
    with pytest.raises(CompensationError, match="from the tracker"):
        check_bounds(far, limits, robot, previous=None)
