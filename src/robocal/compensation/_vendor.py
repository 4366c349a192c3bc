"""The identified *constant* kinematic errors in a controller's own calibration terms.

Robocal's per-joint error transform sits right after the joint rotation,
``Rz(theta_i) E_i Tz(d_i) Tx(a_i) Rx(alpha_i)`` with
``E_i = Tx(dx) Ty(dy) Tz(dz) Rx(ex) Ry(ey) Rz(ez)``. To first order its constant part maps
onto the standard DH parameters of joint i:

* ``ez`` -> ``delta_theta`` (the joint's zero offset; as a joint *command* offset it is
  ``-C^-1 ez`` for a robot whose chain angles are ``theta = C q``, e.g. FANUC J2/J3);
* ``dz`` -> ``delta_d``, ``dx`` -> ``delta_a``, ``ex`` -> ``delta_alpha``.

What DH cannot carry is listed, not dropped silently: ``dy`` and ``ey`` (no DH parameter;
``ey`` is Hayati's beta for parallel axes), the offset ``-d_i ex`` along y that ``ex``
implies because it acts before ``Tz(d_i)``, the base/tool (frames) and every joint-dependent
term (harmonics, strain-wave ripple, joint maps, compliance): those stay in a ``targets``
table. :func:`vendor_export` states the predicted residual when only the zero offsets are
applied, so the operator sees how much of the model a controller's zero offsets carry.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np

from robocal._core.files import atomic_write_text
from robocal.compensation._build import ideal_positions, nominal_residual_mm, sample_poses
from robocal.errors import ConfigError
from robocal.kinematics import CalibratedModel

__all__ = ["VENDOR_FORMAT", "VendorStyle", "vendor_export", "write_vendor_export"]

VENDOR_FORMAT: Final = "robocal.vendor-export/1"
VendorStyle = Literal["generic", "ur"]


def _const(cal: CalibratedModel, joint: int, comp: str) -> float:
    """The constant coefficient of ``j<joint>.<comp>`` (m or rad; 0 when not in the model)."""
    name = f"j{joint}.{comp}.const"
    names = list(cal.model.names)
    return float(cal.params[names.index(name)]) if name in names else 0.0


def vendor_export(cal: CalibratedModel, *, samples: int = 2000, seed: int = 0
                  ) -> dict[str, Any]:
    """Zero offsets and DH deltas (mm, deg) of ``cal``'s constant errors, with what they
    leave out and the predicted residual (mm) when only the zero offsets are applied."""
    robot = cal.robot
    dof = robot.dof
    ez = np.array([_const(cal, j + 1, "ez") for j in range(dof)])
    C = np.asarray(robot.coupling_matrix, dtype=float)
    dq_cmd = -np.linalg.solve(C, ez)
    Q = sample_poses(cal, samples, seed)
    p_ideal = ideal_positions(cal, Q)
    d = np.linalg.norm(cal.predict(Q + dq_cmd) - p_ideal, axis=1)
    zero_only_mm = float(np.sqrt(np.mean(d**2)) * 1e3)
    nominal = nominal_residual_mm(cal, Q)
    joints = []
    for j in range(dof):
        n = j + 1
        dy, ey, ex = _const(cal, n, "dy"), _const(cal, n, "ey"), _const(cal, n, "ex")
        joints.append({
            "joint": n,
            "zero_offset_deg": round(math.degrees(float(dq_cmd[j])), 6),
            "delta_theta_deg": round(math.degrees(float(ez[j])), 6),
            "delta_d_mm": round(_const(cal, n, "dz") * 1e3, 6),
            "delta_a_mm": round(_const(cal, n, "dx") * 1e3, 6),
            "delta_alpha_deg": round(math.degrees(ex), 6),
            "not_carried": {"dy_mm": round((dy - robot.joints[j].d * ex) * 1e3, 6),
                            "ey_deg": round(math.degrees(ey), 6)},
        })
    dependent = sorted(t.name for t in cal.model.spec.terms if t.family != "const")
    return {
        "format": VENDOR_FORMAT,
        "robot": robot.name,
        "model_id": cal.model_id,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "units": {"length": "mm", "angle": "deg"},
        "convention": ("zero_offset_deg: add to each joint's command (motor-side joint "
                       "value, coupling included); delta_*: standard DH deltas of each joint"),
        "joints": joints,
        "not_carried": [
            "dy and ey of every joint, and the y offset ex implies (listed per joint)",
            "the tracker/base and tool frames (a frames table aligns them)",
            "every joint-dependent error term (keep a targets table for those)",
        ],
        "joint_dependent_terms": len(dependent),
        "predicted_residual_zero_offsets_only_mm": round(zero_only_mm, 6),
        "nominal_residual_mm": round(nominal, 6),
        "warnings": [] if zero_only_mm < nominal else [
            f"zero offsets alone predict {zero_only_mm:.4f} mm, no better than "
            f"{nominal:.4f} mm uncompensated: the constant errors only help together with "
            "the terms a controller's zero offsets cannot carry"],
    }


def _ur_conf(doc: dict[str, Any]) -> str:
    """The DH deltas as ``[mounting]`` arrays in SI units (m, rad), the layout of a UR
    ``calibration.conf``; compare with your controller's own file before installing it."""
    js = doc["joints"]

    def arr(key: str, scale: float) -> str:
        return "[" + ", ".join(f"{j[key] * scale:.9g}" for j in js) + "]"

    rad = math.pi / 180.0
    return ("# robocal vendor export, model " + doc["model_id"] + "; DH deltas only (see "
            "docs/compensation-tables.md for what this cannot carry)\n[mounting]\n"
            f"delta_theta = {arr('delta_theta_deg', rad)}\n"
            f"delta_a = {arr('delta_a_mm', 1e-3)}\n"
            f"delta_d = {arr('delta_d_mm', 1e-3)}\n"
            f"delta_alpha = {arr('delta_alpha_deg', rad)}\n")


def write_vendor_export(cal: CalibratedModel, path: str | Path, *,
                        style: VendorStyle = "generic") -> dict[str, Any]:
    """Write the export (JSON, or ``style="ur"`` the ``[mounting]`` DH-delta file); return it.

    Raises
    ------
    ConfigError
        Unknown style, or a robot other than 6 joints for the ``ur`` style.
    """
    doc = vendor_export(cal)
    if style == "generic":
        atomic_write_text(path, json.dumps(doc, indent=1) + "\n")
    elif style == "ur":
        if cal.robot.dof != 6:
            raise ConfigError(f"the ur style needs 6 joints, {cal.robot.name} has "
                              f"{cal.robot.dof}")
        atomic_write_text(path, _ur_conf(doc))
    else:
        raise ConfigError(f"unknown vendor style {style!r} (generic, ur)")
    return doc
