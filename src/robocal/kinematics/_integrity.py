"""MODEL.json integrity: the content hash (optionally keyed with a site secret) and the
physical plausibility of the robot description a model carries.

The hash covers every section that changes predictions or limits (:data:`HASHED`): the robot
description (joint geometry, limits, names, base, flange, tool), the error-model structure,
the tracker <- base reference, the parameters with their sigmas, the covariance, the covered
joint range and the fallback model; since scheme 3 also the thermal term (``fit.thermal``).
It is computed over the canonical JSON of those sections as the file holds them (mm, deg), so
a file hashes the same before and after loading.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
from typing import Any, Final, NoReturn

import numpy as np

from robocal._core.files import json_default
from robocal._core.robot_names import builtin_robots
from robocal.errors import ConfigError
from robocal.kinematics._robot import Joint, RobotDescription, load_toml_robot

#: Sections of MODEL.json the hash covers (free-form ``metrics``, ``fit``, ``data``,
#: ``kind`` and ``created`` describe the model and change no prediction).
HASHED: Final = ("format", "robot", "error_model", "T_tracker_base_ref_mm", "parameters",
                 "covariance", "coverage_deg", "fallback")

#: What the ``integrity`` record of a file written by this version says it covers: the
#: :data:`HASHED` sections and the thermal term (``fit.thermal``, ADR 0042), which changes
#: the predictions at given joint temperatures.
SCHEME: Final = "robocal.model-hash/3"

#: Schemes a file may carry, and what each covers. Version 2 (before the thermal term was
#: covered) is read when its file has no thermal term.
COVERS: Final = {"robocal.model-hash/2": HASHED, SCHEME: (*HASHED, "fit.thermal")}

#: Largest difference of a model's robot description from its nominal one: DH lengths and
#: base/flange offsets (mm), DH angles and base/flange rotations (deg). Joint limits may be
#: narrower than the nominal ones, never wider (beyond rounding).
ROBOT_TOLERANCE: Final = {"mm": 10.0, "deg": 1.0, "limit_deg": 1e-6}

#: Without a nominal description: longest DH length or base offset (mm), widest joint limit
#: (deg), longest tool offset (mm).
ROBOT_ABSOLUTE: Final = {"mm": 10_000.0, "limit_deg": 540.0, "tool_mm": 2_000.0}


def canonical(sections: dict[str, Any]) -> bytes:
    """Canonical JSON bytes of ``sections`` (sorted keys, no spaces)."""
    return json.dumps(sections, sort_keys=True, separators=(",", ":"), allow_nan=True,
                      default=json_default).encode()


def hashed(d: dict[str, Any], scheme: str = SCHEME) -> dict[str, Any]:
    """What ``scheme`` covers of the MODEL.json mapping ``d``: its :data:`HASHED` sections,
    and under version 3 the thermal term (``fit.thermal``; null when there is none)."""
    out = {k: d.get(k) for k in HASHED}
    if "fit.thermal" in COVERS[scheme]:
        fit = d.get("fit")
        out["fit.thermal"] = fit.get("thermal") if isinstance(fit, dict) else None
    return out


def digests(sections: dict[str, Any], key: bytes | None = None, scheme: str = SCHEME
            ) -> tuple[str, str | None]:
    """(sha256 hex, HMAC-SHA256 hex with ``key`` or None) of what ``scheme`` covers of the
    MODEL.json mapping ``sections`` (:func:`hashed`)."""
    text = canonical(hashed(sections, scheme))
    mac = None if key is None else hmac.new(key, text, hashlib.sha256).hexdigest()
    return hashlib.sha256(text).hexdigest(), mac


def check_seal(d: dict[str, Any], source: str, key: bytes | None) -> None:
    """Check a MODEL.json mapping against its ``model_id`` and ``integrity`` record.

    Raises
    ------
    ConfigError
        One error: an earlier file format without a hash of the whole model (refit), a
        content that does not hash to its ``model_id``, or (with ``key``) a missing or
        wrong site signature.
    """
    seal = d.get("integrity")
    scheme = seal.get("scheme") if isinstance(seal, dict) else None
    if not isinstance(seal, dict) or scheme not in COVERS:
        raise ConfigError(
            "written by an earlier robocal whose model_id does not cover the robot "
            "description, covariance and covered range: refit the model (robocal fit, or "
            "the daemon's campaign) to get a verifiable file", source=source, key="integrity")
    if "fit.thermal" not in COVERS[scheme] and hashed(d)["fit.thermal"] is not None:
        raise ConfigError(
            f"the thermal term (fit.thermal) is not covered by this file's {scheme} hash: "
            "refit the model to get a verifiable file", source=source, key="fit.thermal")
    sha, mac = digests(d, key, scheme)
    if d.get("model_id") != sha[:16] or seal.get("sha256") != sha:
        raise ConfigError(
            f"the content does not match its model_id {d.get('model_id')!r} (it hashes to "
            f"{sha[:16]!r}): the file was edited or damaged after it was written; refit or "
            "restore the original", source=source, key="model_id")
    if mac is not None and not hmac.compare_digest(str(seal.get("hmac_sha256", "")), mac):
        what = ("is not signed" if not seal.get("hmac_sha256")
                else "has a signature that does not match this site's secret")
        raise ConfigError(
            f"the model {what} (site secret configured): it was not written by this site's "
            "daemon, or was edited; refit it here", source=source, key="integrity")


def builtin_nominal(robot: RobotDescription) -> RobotDescription | None:
    """The built-in description a model's robot was made from (by source or name), if any."""
    if robot.source.startswith("builtin:"):
        name = robot.source.removeprefix("builtin:")
        if name in builtin_robots():
            return load_toml_robot(name)
    for name in builtin_robots():
        nominal = load_toml_robot(name)
        if nominal.name == robot.name:
            return nominal
    return None


def check_robot(robot: RobotDescription, nominal: RobotDescription | None, source: str
                ) -> None:
    """Refuse a robot description that is not physically this robot.

    With a ``nominal`` description (the daemon's, else the built-in one the model names) the
    geometry must match it within :data:`ROBOT_TOLERANCE` and no joint limit may be wider;
    without one, only the absolute bounds of :data:`ROBOT_ABSOLUTE` apply.

    Raises
    ------
    ConfigError
        Naming the robot key and how far it is off.
    """
    src = f"{source}#robot"
    tool_mm = 1e3 * math.dist(robot.tool, (0.0, 0.0, 0.0))
    if tool_mm > ROBOT_ABSOLUTE["tool_mm"]:
        _refuse(src, "tool_mm",
                f"tool offset {tool_mm:.0f} mm beyond {ROBOT_ABSOLUTE['tool_mm']:g} mm")
    if nominal is None:
        _check_absolute(robot, src)
    else:
        _check_nominal(robot, nominal, src)


def _refuse(src: str, key: str, what: str) -> NoReturn:
    raise ConfigError(f"{what}: not a plausible description of this robot (refit with "
                      "the right robot description)", source=src, key=key)


def _check_absolute(robot: RobotDescription, src: str) -> None:
    """Without a nominal robot: lengths and joint limits within :data:`ROBOT_ABSOLUTE`."""
    lengths = [("base_xyz_mm", 1e3 * math.dist(robot.base_xyz, (0.0, 0.0, 0.0))),
               ("flange_xyz_mm", 1e3 * math.dist(robot.flange_xyz, (0.0, 0.0, 0.0)))]
    for i, j in enumerate(robot.joints):
        lengths += [(f"joints[{i + 1}].a_mm", abs(j.a) * 1e3),
                    (f"joints[{i + 1}].d_mm", abs(j.d) * 1e3)]
    for key, v in lengths:
        if v > ROBOT_ABSOLUTE["mm"]:
            _refuse(src, key, f"{v:.0f} mm beyond {ROBOT_ABSOLUTE['mm']:g} mm")
    for i, j in enumerate(robot.joints):
        widest = max(abs(math.degrees(j.q_min)), abs(math.degrees(j.q_max)))
        if widest > ROBOT_ABSOLUTE["limit_deg"]:
            _refuse(src, f"joints[{i + 1}]", f"joint limit {widest:.1f} deg beyond "
                    f"{ROBOT_ABSOLUTE['limit_deg']:g} deg")


def _check_nominal(robot: RobotDescription, nominal: RobotDescription, src: str) -> None:
    """Against a nominal robot: same name and joints, geometry within :data:`ROBOT_TOLERANCE`,
    no wider joint limits."""
    if robot.name != nominal.name:
        _refuse(src, "name",
                f"robot {robot.name!r}, the nominal description is {nominal.name!r}")
    if robot.dof != nominal.dof:
        _refuse(src, "joints", f"{robot.dof} joints, {nominal.name!r} has {nominal.dof}")
    mm, deg = ROBOT_TOLERANCE["mm"], ROBOT_TOLERANCE["deg"]
    pairs: list[tuple[str, float, float, float, str]] = []
    for part in ("base", "flange"):
        xyz, rpy = getattr(robot, f"{part}_xyz"), getattr(robot, f"{part}_rpy")
        nxyz, nrpy = getattr(nominal, f"{part}_xyz"), getattr(nominal, f"{part}_rpy")
        pairs.append((f"{part}_xyz_mm", 1e3 * math.dist(xyz, nxyz), 0.0, mm, "mm"))
        rot = np.degrees(np.abs(np.angle(np.exp(1j * (np.subtract(rpy, nrpy))))))
        pairs.append((f"{part}_rpy_deg", float(rot.max()), 0.0, deg, "deg"))
    for i, (j, n) in enumerate(zip(robot.joints, nominal.joints, strict=True)):
        k = f"joints[{i + 1}]"
        pairs += [(f"{k}.a_mm", j.a * 1e3, n.a * 1e3, mm, "mm"),
                  (f"{k}.d_mm", j.d * 1e3, n.d * 1e3, mm, "mm"),
                  (f"{k}.alpha_deg", math.degrees(j.alpha), math.degrees(n.alpha), deg, "deg"),
                  (f"{k}.theta_offset_deg", math.degrees(j.theta_offset),
                   math.degrees(n.theta_offset), deg, "deg")]
        _check_joint_vs_nominal(j, n, k, src)
    for key, v, nv, tol, unit in pairs:
        if not abs(v - nv) <= tol:
            _refuse(src, key,
                    f"{v:.6g} {unit}, nominal {nv:.6g} {unit} (tolerance {tol:g} {unit})")


def _check_joint_vs_nominal(j: Joint, n: Joint, k: str, src: str) -> None:
    """Same sign and coupling as the nominal joint, limits no wider."""
    if (j.sign, j.coupled_to, j.coupling) != (n.sign, n.coupled_to, n.coupling):
        _refuse(src, k, "joint sign or coupling differs from the nominal description")
    eps = ROBOT_TOLERANCE["limit_deg"]
    if (math.degrees(j.q_min) < math.degrees(n.q_min) - eps
            or math.degrees(j.q_max) > math.degrees(n.q_max) + eps):
        _refuse(src, f"{k}.min_deg", f"joint limits [{math.degrees(j.q_min):.2f}, "
                f"{math.degrees(j.q_max):.2f}] deg wider than the nominal "
                f"[{math.degrees(n.q_min):.2f}, {math.degrees(n.q_max):.2f}] deg")
