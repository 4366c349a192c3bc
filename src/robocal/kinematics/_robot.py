"""Robot description files (TOML) and the built-in robots.

The public format, all lengths in mm and angles in degrees::

    name = "My robot"
    manufacturer = "ACME"            # optional
    tool_mm = [0.0, 0.0, 50.0]       # optional default flange -> reflector offset
    gravity = [0.0, 0.0, -9.81]      # optional gravity vector in the base frame (m/s^2)

    [[joints]]                       # one table per joint, base to flange
    a_mm = 150.0
    d_mm = 450.0
    alpha_deg = -90.0
    theta_offset_deg = 0.0           # optional, default 0
    min_deg = -170.0
    max_deg = 170.0
    gear_ratio = 121.0               # optional; enables strain-wave terms
    mass_kg = 12.0                   # optional, with com_mm = [x, y, z] in the link frame;
    com_mm = [0.0, 0.0, 100.0]       #   enables gravity torsion
    sign = -1                        # optional: chain angle turns opposite to the joint value
    coupled_to = 2                   # optional: chain angle also follows joint 2 ...
    coupling = 1.0                   #   ... with this factor (FANUC J2/J3 coupling)

The chain angle of joint i is ``theta_i = sign_i * (q_i + coupling_i * q_{coupled_to}) +
theta_offset_i`` and the link transform is ``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` (standard DH).
Joint values ``q`` (what the controller reports and accepts) are what robocal stores in files.

Optional top-level keys:

* ``base_xyz_mm``, ``base_rpy_deg``: fixed transform robot root -> DH frame 0 (default
  identity); ``flange_xyz_mm``, ``flange_rpy_deg``: DH frame n -> flange (default identity).
  ``tool_mm`` is given in the flange frame. rpy as in URDF: ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
* ``convention = "modified"``: the joint tables are Craig's modified DH, link transform
  ``Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i)``: table i holds ``a_mm = a_{i-1}`` and
  ``alpha_deg = alpha_{i-1}`` with ``d_mm = d_i`` and ``theta_offset_deg``. It is converted
  exactly on load: ``Rx(alpha_0) Tx(a_0)`` joins the base transform and the standard
  ``a_i, alpha_i`` are the next table's values (the last joint gets 0). Default
  ``"standard"``. :func:`to_modified_dict` writes the modified layout.
* ``[collision]``: the planner's capsule model of the links (ADR 0026): ``link_radii_mm``,
  one capsule radius per joint body (the link moved by that joint), and ``source``, where
  the radii come from (a published model or data sheet). Without it the planner uses
  :func:`default_link_radii`; a URDF import takes them from the links' collision geometry.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.files import read_toml
from robocal._core.robot_names import (
    builtin_robot_key,
    check_robot_spec,
)
from robocal._core.schema import fail, key, list_of, load, parse
from robocal.errors import ConfigError

_ZERO3 = (0.0, 0.0, 0.0)


def rpy_to_matrix(rpy: tuple[float, float, float] | NDArray[np.float64]) -> NDArray[np.float64]:
    """URDF roll-pitch-yaw (rad) -> rotation (3, 3): ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = (math.cos(r), math.sin(r), math.cos(p), math.sin(p),
                              math.cos(y), math.sin(y))
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def matrix_to_rpy(R: NDArray[np.float64]) -> tuple[float, float, float]:
    """Inverse of :func:`rpy_to_matrix`, accurate near pitch = +-90 deg.

    Yaw comes first from the first column; roll and pitch are then read from
    ``Rz(yaw)^T R = Ry(pitch) Rx(roll)``, whose large entries stay well conditioned even
    when yaw itself is poorly defined (gimbal lock), so the angles reproduce ``R`` to
    rounding error.
    """
    yaw = math.atan2(R[1, 0], R[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    M = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ R
    roll = math.atan2(-M[1, 2], M[1, 1])
    pitch = math.atan2(-M[2, 0], M[0, 0])
    return roll, pitch, yaw


def transform(xyz: tuple[float, float, float], rpy: tuple[float, float, float]
              ) -> NDArray[np.float64]:
    """Homogeneous transform (4, 4) from a translation (m) and URDF rpy (rad)."""
    T = np.eye(4)
    T[:3, :3] = rpy_to_matrix(rpy)
    T[:3, 3] = xyz
    return T


@dataclass(frozen=True)
class Joint:
    """One revolute joint, SI units (m, rad, kg)."""

    a: float  # DH link length, m
    d: float  # DH link offset, m
    alpha: float  # DH twist, rad
    theta_offset: float  # chain angle at joint value 0, rad
    q_min: float  # joint limits, rad
    q_max: float
    #: gear ratio (strain-wave terms), None where unknown
    gear_ratio: float | None = None
    #: link mass (kg) and centre of mass (m, link frame), for gravity torsion
    mass: float | None = None
    com: tuple[float, float, float] | None = None
    #: the chain angle turns with ``sign * (q + coupling * q[coupled_to])``
    sign: int = 1
    coupled_to: int | None = None  # 0-based index of the joint this one is coupled to
    coupling: float = 0.0
    name: str = ""
    max_speed: float = math.radians(180.0)


@dataclass(frozen=True)
class RobotDescription:
    """Nominal kinematics of a serial robot with revolute joints."""

    name: str
    joints: tuple[Joint, ...]
    manufacturer: str = ""
    tool: tuple[float, float, float] = (0.0, 0.0, 0.05)
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    source: str = ""
    base_xyz: tuple[float, float, float] = _ZERO3     # root -> DH frame 0, m
    base_rpy: tuple[float, float, float] = _ZERO3     # rad, URDF rpy
    flange_xyz: tuple[float, float, float] = _ZERO3   # DH frame n -> flange, m
    flange_rpy: tuple[float, float, float] = _ZERO3
    #: capsule radius per joint body, m (``[collision]``), None: the planner's default
    link_radii: tuple[float, ...] | None = None
    #: where ``link_radii`` come from
    collision_source: str = ""
    _coupling: NDArray[np.float64] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = len(self.joints)
        C = np.zeros((n, n))
        for i, j in enumerate(self.joints):
            C[i, i] = j.sign
            if j.coupled_to is not None:
                C[i, j.coupled_to] += j.sign * j.coupling
        C.setflags(write=False)
        object.__setattr__(self, "_coupling", C)

    @property
    def dof(self) -> int:
        """Number of joints."""
        return len(self.joints)

    @property
    def coupling_matrix(self) -> NDArray[np.float64]:
        """Matrix ``C`` (dof, dof) with ``theta = q @ C.T + theta_offset``."""
        return self._coupling

    @property
    def T_root_dh0(self) -> NDArray[np.float64]:
        """Fixed transform robot root -> DH frame 0 (4, 4), m."""
        return transform(self.base_xyz, self.base_rpy)

    @property
    def T_dhn_flange(self) -> NDArray[np.float64]:
        """Fixed transform DH frame n -> flange (4, 4), m."""
        return transform(self.flange_xyz, self.flange_rpy)

    @property
    def has_base(self) -> bool:
        """True when the root -> DH frame 0 transform is not the identity."""
        return self.base_xyz != _ZERO3 or self.base_rpy != _ZERO3

    @property
    def has_flange(self) -> bool:
        """True when the DH frame n -> flange transform is not the identity."""
        return self.flange_xyz != _ZERO3 or self.flange_rpy != _ZERO3

    @property
    def joint_limits(self) -> NDArray[np.float64]:
        """Joint limits in rad, shape (dof, 2): [min, max]."""
        return np.array([[j.q_min, j.q_max] for j in self.joints])

    joint_limits_rad = joint_limits

    @property
    def gear_ratios(self) -> tuple[float | None, ...]:
        """Gear ratio per joint, None where unknown."""
        return tuple(j.gear_ratio for j in self.joints)

    @property
    def has_masses(self) -> bool:
        """True when every joint gives a mass and centre of mass (gravity torsion possible)."""
        return all(j.mass is not None and j.com is not None for j in self.joints)

    def within_limits(self, q: NDArray[np.float64], margin: float = 0.0) -> NDArray[np.bool_]:
        """Return, per pose, whether all joints of ``q`` (n, dof) rad are inside the limits."""
        lim = self.joint_limits
        q = np.atleast_2d(q)
        return np.all((q >= lim[:, 0] + margin) & (q <= lim[:, 1] - margin), axis=1)

    def to_dict(self) -> dict[str, Any]:
        """Return the description in the public TOML layout (mm, deg)."""
        joints = []
        for j in self.joints:
            d: dict[str, Any] = {
                "a_mm": j.a * 1e3, "d_mm": j.d * 1e3, "alpha_deg": math.degrees(j.alpha),
                "theta_offset_deg": math.degrees(j.theta_offset),
                "min_deg": math.degrees(j.q_min), "max_deg": math.degrees(j.q_max),
            }
            if j.gear_ratio is not None:
                d["gear_ratio"] = j.gear_ratio
            if j.mass is not None:
                d["mass_kg"] = j.mass
            if j.com is not None:
                d["com_mm"] = [c * 1e3 for c in j.com]
            if j.sign != 1:
                d["sign"] = j.sign
            if j.coupled_to is not None:
                d["coupled_to"] = j.coupled_to + 1
                d["coupling"] = j.coupling
            if j.name:
                d["name"] = j.name
            d["max_speed_deg_s"] = math.degrees(j.max_speed)
            joints.append(d)
        out: dict[str, Any] = {
            "name": self.name, "manufacturer": self.manufacturer,
            "tool_mm": [t * 1e3 for t in self.tool], "gravity": list(self.gravity),
            "source": self.source,
        }
        if self.has_base:
            out["base_xyz_mm"] = [v * 1e3 for v in self.base_xyz]
            out["base_rpy_deg"] = [math.degrees(v) for v in self.base_rpy]
        if self.has_flange:
            out["flange_xyz_mm"] = [v * 1e3 for v in self.flange_xyz]
            out["flange_rpy_deg"] = [math.degrees(v) for v in self.flange_rpy]
        if self.link_radii is not None:
            out["collision"] = {"link_radii_mm": [r * 1e3 for r in self.link_radii],
                                "source": self.collision_source}
        out["joints"] = joints
        return out

    def to_modified_dict(self) -> dict[str, Any]:
        """Return the description in the public layout with Craig's modified DH tables.

        Exact inverse of the conversion on load: table i gets the standard ``a, alpha`` of
        joint i-1 (0 for the first), the last joint's ``a, alpha`` join the flange transform.
        """
        d = self.to_dict()
        std = d["joints"]
        last_a, last_alpha = std[-1]["a_mm"], std[-1]["alpha_deg"]
        for i in range(len(std) - 1, 0, -1):
            std[i]["a_mm"], std[i]["alpha_deg"] = std[i - 1]["a_mm"], std[i - 1]["alpha_deg"]
        std[0]["a_mm"], std[0]["alpha_deg"] = 0.0, 0.0
        T = (np.eye(4) if not self.has_flange else self.T_dhn_flange)
        T = _tx_rx(last_a * 1e-3, math.radians(last_alpha)) @ T
        d.pop("flange_xyz_mm", None)
        d.pop("flange_rpy_deg", None)
        if not np.allclose(T, np.eye(4), rtol=0.0, atol=1e-15):
            d["flange_xyz_mm"] = [float(v) * 1e3 for v in T[:3, 3]]
            d["flange_rpy_deg"] = [math.degrees(v) for v in matrix_to_rpy(T[:3, :3])]
        d["convention"] = "modified"
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "<robot>") -> RobotDescription:
        """Build a description from the public layout; raise :class:`ConfigError` on problems."""
        return _parse(data, source)


#: no length (mm), angle (deg), mass or speed of a robot description comes near this; larger
#: numbers would only overflow the kinematics later
_MAX_ABS = 1e6


def _plausible(v: float) -> bool:
    try:
        return math.isfinite(v) and abs(v) <= _MAX_ABS
    except OverflowError:  # an int too large for a float
        return False


def _number(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not _plausible(v):
        fail(f"must be a finite number within +-{_MAX_ABS:g}, got {v!r}")
    return float(v)


def _positive(v: Any) -> float:
    if _number(v) <= 0:
        fail("must be positive")
    return float(v)


def _not_negative(v: Any) -> float:
    if _number(v) < 0:
        fail("must not be negative")
    return float(v)


def _vector3(v: Any) -> tuple[float, float, float]:
    if (not isinstance(v, list | tuple) or len(v) != 3
            or not all(isinstance(x, int | float) and not isinstance(x, bool)
                       and _plausible(x) for x in v)):
        fail(f"must be a list of 3 finite numbers within +-{_MAX_ABS:g}, got {v!r}")
    return (float(v[0]), float(v[1]), float(v[2]))


def _text(v: Any) -> str:
    if not isinstance(v, str):
        fail("must be a string")
    return v


def _sign(v: Any) -> int:
    if isinstance(v, bool) or v not in (1, -1):
        fail(f"must be 1 or -1, got {v!r}")
    return int(v)


def _robot_name(v: Any) -> str:
    if not isinstance(v, str) or not v.strip():
        fail("required non-empty string")
    return v.strip()


def _convention(v: Any) -> str:
    if v not in ("standard", "modified"):
        fail(f"must be \"standard\" or \"modified\", got {v!r}")
    return str(v)


def _joint_tables(v: Any) -> list[_JointFile]:
    if not isinstance(v, list) or not v:
        fail("at least one [[joints]] table is required")
    return list_of(lambda j, i: _coupled_in(parse(_JointFile, j), i, len(v)), numbered=True)(v)


def _coupled_in(j: _JointFile, i: int, n: int) -> _JointFile:
    """``coupled_to`` of joint ``i``: another joint 1..n."""
    c = j.coupled_to
    if c is not None and (not isinstance(c, int) or isinstance(c, bool)
                          or not 1 <= c <= n or c == i):
        fail(f"must name another joint 1..{n}", key="coupled_to")
    return j


def _collision_table(v: Any) -> _CollisionFile | None:
    return None if v is None else parse(_CollisionFile, v)


@dataclass(frozen=True, kw_only=True)
class _JointFile:
    """One ``[[joints]]`` table (mm, deg)."""

    a_mm: float = key(_number)
    d_mm: float = key(_number)
    alpha_deg: float = key(_number)
    theta_offset_deg: float = key(_number, 0.0)
    min_deg: float = key(_number)
    max_deg: float = key(_number)
    gear_ratio: float | None = key(_positive, None)
    mass_kg: float | None = key(_not_negative, None)
    com_mm: tuple[float, float, float] | None = key(_vector3, None)
    sign: int = key(_sign, 1)
    coupled_to: Any = key(None, None)  # 1-based joint number, checked against the joint count
    coupling: float | None = key(_number, None)
    name: str = key(_text, "")
    max_speed_deg_s: float = key(_positive, 180.0)

    def __post_init__(self) -> None:
        if self.min_deg >= self.max_deg:
            fail(f"min_deg ({self.min_deg}) must be below max_deg ({self.max_deg})",
                 key="min_deg")
        if (self.mass_kg is None) != (self.com_mm is None):
            fail("mass_kg and com_mm must be given together",
                 key="com_mm" if self.com_mm is None else "mass_kg")

    def joint(self) -> Joint:
        """The joint in SI units (coupling 1 by default when coupled)."""
        coupled = None if self.coupled_to is None else int(self.coupled_to) - 1
        coupling = 0.0 if coupled is None else (1.0 if self.coupling is None else self.coupling)
        return Joint(
            a=self.a_mm * 1e-3, d=self.d_mm * 1e-3, alpha=math.radians(self.alpha_deg),
            theta_offset=math.radians(self.theta_offset_deg),
            q_min=math.radians(self.min_deg), q_max=math.radians(self.max_deg),
            gear_ratio=self.gear_ratio, mass=self.mass_kg,
            com=None if self.com_mm is None else _scaled(self.com_mm, 1e-3),
            sign=self.sign, coupled_to=coupled, coupling=coupling, name=self.name,
            max_speed=math.radians(self.max_speed_deg_s))


@dataclass(frozen=True, kw_only=True)
class _CollisionFile:
    """``[collision]``: capsule radius per joint body (mm), checked against the joint count."""

    link_radii_mm: Any = key(None, None)
    source: str = key(_text, "")


@dataclass(frozen=True, kw_only=True)
class _RobotFile:
    """The robot TOML (module docstring)."""

    convention: str = key(_convention, "standard")
    name: str = key(_robot_name, missing="required non-empty string")
    joints: list[_JointFile] = key(_joint_tables,
                                   missing="at least one [[joints]] table is required")
    tool_mm: tuple[float, float, float] = key(_vector3, (0.0, 0.0, 50.0))
    gravity: tuple[float, float, float] = key(_vector3, (0.0, 0.0, -9.81))
    manufacturer: str = key(_text, "")
    base_xyz_mm: tuple[float, float, float] = key(_vector3, _ZERO3)
    base_rpy_deg: tuple[float, float, float] = key(_vector3, _ZERO3)
    flange_xyz_mm: tuple[float, float, float] = key(_vector3, _ZERO3)
    flange_rpy_deg: tuple[float, float, float] = key(_vector3, _ZERO3)
    collision: _CollisionFile | None = key(_collision_table, None)
    source: str | None = key(str, None)
    notes: Any = key(None, None)

    def __post_init__(self) -> None:
        n = len(self.joints)
        radii = None if self.collision is None else self.collision.link_radii_mm
        if self.collision is not None and (
                not isinstance(radii, list) or len(radii) != n
                or not all(isinstance(r, int | float) and not isinstance(r, bool)
                           and math.isfinite(r) and r > 0 for r in radii)):
            fail(f"must be {n} positive numbers (mm), one per joint body",
                 key="collision.link_radii_mm")


def _scaled(v: tuple[float, float, float], f: float) -> tuple[float, float, float]:
    return (v[0] * f, v[1] * f, v[2] * f)


def _tx_rx(a: float, alpha: float) -> NDArray[np.float64]:
    """``Tx(a) Rx(alpha)`` (4, 4)."""
    c, s = math.cos(alpha), math.sin(alpha)
    return np.array([[1.0, 0.0, 0.0, a], [0.0, c, -s, 0.0], [0.0, s, c, 0.0],
                     [0.0, 0.0, 0.0, 1.0]])


def _split(T: NDArray[np.float64]) -> tuple[tuple[float, float, float],
                                             tuple[float, float, float]]:
    """(xyz m, rpy rad) of a transform."""
    xyz = (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]))
    return xyz, matrix_to_rpy(T[:3, :3])


def _parse(data: dict[str, Any], src: str) -> RobotDescription:
    f = load(_RobotFile, data, src)
    joints = [j.joint() for j in f.joints]
    fixed = {part: (_scaled(getattr(f, f"{part}_xyz_mm"), 1e-3),
                    _scaled(getattr(f, f"{part}_rpy_deg"), math.pi / 180.0))
             for part in ("base", "flange")}
    if f.convention == "modified":
        # Craig: Rx(al0) Tx(a0) [Rz Tz Tx(a1) Rx(al1)] ... [Rz Tz]: regroup into standard DH
        T_base = transform(*fixed["base"]) @ _tx_rx(joints[0].a, joints[0].alpha)
        if not np.allclose(T_base, np.eye(4), rtol=0.0, atol=0.0):
            fixed["base"] = _split(T_base)
        nxt = [(j.a, j.alpha) for j in joints[1:]] + [(0.0, 0.0)]
        joints = [replace(j, a=a, alpha=al) for j, (a, al) in zip(joints, nxt, strict=True)]
    radii = None if f.collision is None else tuple(
        float(r) * 1e-3 for r in f.collision.link_radii_mm)
    return RobotDescription(
        name=f.name, joints=tuple(joints), manufacturer=f.manufacturer,
        tool=_scaled(f.tool_mm, 1e-3), gravity=f.gravity,
        source=src if f.source is None else f.source, link_radii=radii,
        collision_source="" if f.collision is None else f.collision.source,
        base_xyz=fixed["base"][0], base_rpy=fixed["base"][1],
        flange_xyz=fixed["flange"][0], flange_rpy=fixed["flange"][1],
    )


def load_toml_robot(spec: str | Path) -> RobotDescription:
    """Load a robot by built-in name (see :func:`builtin_robots`) or a TOML file path.

    :func:`robocal.kinematics.load_robot` takes URDF paths too (ADR 0038).

    Raises
    ------
    ConfigError
        When the name is unknown, the file is missing or unreadable, or a key is invalid.
    """
    text_spec = str(spec)
    key = builtin_robot_key(text_spec)
    if key is not None:
        res = resources.files("robocal.data") / "robots" / f"{key}.toml"
        return _parse(read_toml(res), f"builtin:{key}")
    check_robot_spec(text_spec)
    return _parse(read_toml(Path(text_spec)), text_spec)


def default_link_radii(robot: RobotDescription) -> list[float]:
    """Default capsule radius per body, m: 4 % of the summed link lengths for bodies 1-3, 2.5 %
    for the wrist bodies (a rough, deliberately generous fit to industrial arms from 5 kg to
    200 kg payload), for robots whose description carries no ``[collision]`` radii.

    The last body (the flange) is capped at 60 % of the robot file's tool offset: the reflector
    sits on the flange, so a flange capsule reaching past it would contradict the robot file
    (the KR210's 2.5 % is 101 mm against a 100 mm tool offset).
    """
    reach = sum(abs(j.a) + abs(j.d) for j in robot.joints)
    radii = [(0.04 if i < 3 else 0.025) * reach for i in range(robot.dof)]
    tool = math.hypot(*robot.tool)
    if tool > 0.0:
        radii[-1] = min(radii[-1], 0.6 * tool)
    return radii


def link_radii(robot: RobotDescription) -> tuple[list[float], str]:
    """Capsule radius per body (dof,) m and where it comes from: the description's
    ``[collision]`` radii, else :func:`default_link_radii`."""
    if robot.link_radii is not None:
        return list(robot.link_radii), (robot.collision_source or "robot description")
    return default_link_radii(robot), ("default: 4 % of the summed link lengths (bodies "
                                       "1-3), 2.5 % (wrist), flange at most 60 % of the tool "
                                       "offset")


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v + 0.0)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ConfigError(f"cannot write {v!r} to TOML")


def robot_to_toml(robot: RobotDescription, *, header: str = "") -> str:
    """The description as robot TOML text (the layout of :meth:`RobotDescription.to_dict`).

    Floats are written with ``repr`` so that reading the text back gives the same numbers.
    """
    d = robot.to_dict()
    lines = [f"# {h}" for h in header.splitlines()]
    for k, v in d.items():
        if k not in ("joints", "collision") and v != "":
            lines.append(f"{k} = {_toml_value(v)}")
    if "collision" in d:
        lines += ["", "[collision]"] + [f"{k} = {_toml_value(v)}"
                                        for k, v in d["collision"].items()]
    for j in d["joints"]:
        lines += ["", "[[joints]]"] + [f"{k} = {_toml_value(v)}" for k, v in j.items()]
    return "\n".join(lines) + "\n"
