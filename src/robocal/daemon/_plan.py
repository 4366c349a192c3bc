"""Reading PLAN.json documents into the ordered pose list a campaign executes.

The plan format belongs to :mod:`robocal.planning` (``Plan``, ``"robocal.plan/1"``), which
validates the document. The daemon itself needs only the robot name
and, per pose in order, the joint target (degrees) and its purpose (``calibration``,
``validation``, ``cpa-jK``, ``iso-Pk``, ...).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from robocal.daemon.store import PoseRow
from robocal.errors import ConfigError
from robocal.planning import Plan

__all__ = ["PlanDoc", "parse_plan", "plan_from_poses"]

_Q_KEYS = ("q_deg", "joints_deg", "target_deg", "joint_targets_deg")


@dataclass(frozen=True)
class PlanDoc:
    """A validated plan reduced to what the daemon executes."""

    robot: str | None
    poses: tuple[PoseRow, ...]
    document: dict[str, Any]
    digest: str

    @property
    def text(self) -> str:
        """Canonical JSON of the document (stored with the campaign)."""
        return json.dumps(self.document, sort_keys=True, separators=(",", ":"))


def _pose_q(p: Any, i: int, source: str) -> tuple[tuple[float, ...], str, bool]:
    if isinstance(p, Mapping):
        q = next((p[k] for k in _Q_KEYS if k in p), None)
        purpose = p.get("purpose", "calibration")
        measure = p.get("measure", purpose != "via")
    else:
        q = next((getattr(p, k) for k in _Q_KEYS if hasattr(p, k)), None)
        purpose = getattr(p, "purpose", "calibration")
        measure = getattr(p, "measure", purpose != "via")
    if q is None:
        raise ConfigError(f"pose has no joint target ({' / '.join(_Q_KEYS)})", source=source,
                          key=f"poses[{i}]")
    try:
        qt = tuple(float(v) for v in q)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"joint target is not a list of numbers: {err}", source=source,
                          key=f"poses[{i}]") from err
    if not qt or not all(math.isfinite(v) for v in qt):
        raise ConfigError("joint target must be finite numbers", source=source,
                          key=f"poses[{i}]")
    if not isinstance(purpose, str) or not purpose:
        raise ConfigError("purpose must be a non-empty string", source=source,
                          key=f"poses[{i}].purpose")
    if not isinstance(measure, bool):
        raise ConfigError("measure must be true or false", source=source,
                          key=f"poses[{i}].measure")
    return qt, purpose, measure


def _validate_with_planning(doc: dict[str, Any], source: str) -> Plan:
    """Validate with :class:`robocal.planning.Plan`; raise ConfigError naming the key."""
    try:
        return Plan.model_validate(doc)
    except ValidationError as err:
        first = err.errors()[0]
        key = ".".join(str(p) for p in first["loc"]) or None
        raise ConfigError(f"{first['msg']} ({err.error_count()} error(s))", source=source,
                          key=key) from err


def parse_plan(data: Mapping[str, Any] | str | bytes, *, source: str = "plan",
               strict: bool = True) -> PlanDoc:
    """Validate a PLAN.json document (mapping or JSON text) and list its poses.

    With ``strict`` (the default) the document must be a complete ``robocal.plan/1`` plan
    (validated by :class:`robocal.planning.Plan`); otherwise a bare ``{"poses": [{"q_deg":
    [...], "purpose": ...}]}`` suffices (verification runs built in-process).

    Raises
    ------
    ConfigError
        If the document is not a JSON object with a non-empty ``poses`` list of joint targets;
        the message names the source and the offending key.
    """
    if isinstance(data, str | bytes):
        try:
            data = json.loads(data)
        except json.JSONDecodeError as err:
            raise ConfigError(f"not valid JSON: {err}", source=source) from err
    if not isinstance(data, Mapping):
        raise ConfigError("a plan must be a JSON object", source=source)
    doc = dict(data)
    fmt = doc.get("format")
    if fmt is not None and fmt != "robocal.plan/1":
        raise ConfigError(f"unsupported plan format {fmt!r} (expected 'robocal.plan/1')",
                          source=source, key="format")
    plan = _validate_with_planning(doc, source) if strict else None
    raw_poses: Any = getattr(plan, "poses", None) if plan is not None else doc.get("poses")
    if not isinstance(raw_poses, Sequence) or isinstance(raw_poses, str) or not raw_poses:
        raise ConfigError("a plan needs a non-empty 'poses' list", source=source, key="poses")
    poses = []
    dof = None
    for i, p in enumerate(raw_poses):
        q, purpose, measure = _pose_q(p, i, source)
        if dof is None:
            dof = len(q)
        elif len(q) != dof:
            raise ConfigError(f"{len(q)} joints, earlier poses have {dof}", source=source,
                              key=f"poses[{i}]")
        poses.append(PoseRow(i, purpose, q, measure))
    if not any(p.measure for p in poses):
        raise ConfigError("the plan has no pose to measure", source=source, key="poses")
    robot = getattr(plan, "robot", None) if plan is not None else doc.get("robot")
    if isinstance(robot, Mapping):
        robot = robot.get("name")
    elif robot is not None and not isinstance(robot, str):
        robot = getattr(robot, "name", None)
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    return PlanDoc(robot if isinstance(robot, str) else None, tuple(poses), doc, digest)


def plan_from_poses(q_deg: Sequence[Sequence[float]], *, purpose: str = "calibration",
                    robot: str | None = None, purposes: Sequence[str] | None = None
                    ) -> dict[str, Any]:
    """A minimal plan document listing joint targets (degrees), for verification runs.

    Parse it with ``parse_plan(doc, strict=False)``.
    """
    poses = [{"q_deg": [float(v) for v in q],
              "purpose": purposes[i] if purposes is not None else purpose}
             for i, q in enumerate(q_deg)]
    return {"format": "robocal.plan/1", "robot": robot, "poses": poses}
