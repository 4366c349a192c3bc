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
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.files import read_toml
from robocal.errors import ConfigError

_JOINT_KEYS = {
    "a_mm", "d_mm", "alpha_deg", "theta_offset_deg", "min_deg", "max_deg", "gear_ratio",
    "mass_kg", "com_mm", "sign", "coupled_to", "coupling", "name", "max_speed_deg_s",
}
_TOP_KEYS = {"name", "manufacturer", "tool_mm", "gravity", "joints", "source", "notes"}


@dataclass(frozen=True)
class Joint:
    """One revolute joint, SI units (m, rad, kg)."""

    a: float
    d: float
    alpha: float
    theta_offset: float
    q_min: float
    q_max: float
    gear_ratio: float | None = None
    mass: float | None = None
    com: tuple[float, float, float] | None = None
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
        return {
            "name": self.name, "manufacturer": self.manufacturer,
            "tool_mm": [t * 1e3 for t in self.tool], "gravity": list(self.gravity),
            "source": self.source, "joints": joints,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "<robot>") -> RobotDescription:
        """Build a description from the public layout; raise :class:`ConfigError` on problems."""
        return _parse(data, source)


def _num(d: dict[str, Any], key: str, src: str, default: float | None = None,
         *, required: bool = True) -> float | None:
    if key not in d:
        if required and default is None:
            raise ConfigError("required key is missing", source=src, key=key)
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ConfigError(f"must be a finite number, got {v!r}", source=src, key=key)
    return float(v)


def _vec3(d: dict[str, Any], key: str, src: str) -> tuple[float, float, float] | None:
    if key not in d:
        return None
    v = d[key]
    if (not isinstance(v, list) or len(v) != 3
            or not all(isinstance(x, int | float) and not isinstance(x, bool)
                       and math.isfinite(x) for x in v)):
        raise ConfigError(f"must be a list of 3 finite numbers, got {v!r}", source=src, key=key)
    return (float(v[0]), float(v[1]), float(v[2]))


def _parse(data: dict[str, Any], src: str) -> RobotDescription:
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise ConfigError(f"unknown key (allowed: {', '.join(sorted(_TOP_KEYS))})",
                          source=src, key=sorted(unknown)[0])
    name = data.get("name")
    if not isinstance(name, str) or not name.strip():
        raise ConfigError("required non-empty string", source=src, key="name")
    raw_joints = data.get("joints")
    if not isinstance(raw_joints, list) or not raw_joints:
        raise ConfigError("at least one [[joints]] table is required", source=src, key="joints")
    joints = []
    for i, jd in enumerate(raw_joints, start=1):
        where = f"joints[{i}]"
        if not isinstance(jd, dict):
            raise ConfigError("must be a table", source=src, key=where)
        bad = set(jd) - _JOINT_KEYS
        if bad:
            raise ConfigError(f"unknown key (allowed: {', '.join(sorted(_JOINT_KEYS))})",
                              source=src, key=f"{where}.{sorted(bad)[0]}")

        def num(k: str, default: float | None = None, required: bool = True,
                _jd: dict[str, Any] = jd, _w: str = where) -> float | None:
            try:
                return _num(_jd, k, src, default, required=required)
            except ConfigError as err:
                raise ConfigError(str(err).split(": ", 2)[-1], source=src,
                                  key=f"{_w}.{k}") from None

        a = num("a_mm")
        d = num("d_mm")
        alpha = num("alpha_deg")
        off = num("theta_offset_deg", 0.0)
        qmin = num("min_deg")
        qmax = num("max_deg")
        assert a is not None and d is not None and alpha is not None and off is not None
        assert qmin is not None and qmax is not None
        if qmin >= qmax:
            raise ConfigError(f"min_deg ({qmin}) must be below max_deg ({qmax})",
                              source=src, key=f"{where}.min_deg")
        gear = num("gear_ratio", required=False)
        if gear is not None and gear <= 0:
            raise ConfigError("must be positive", source=src, key=f"{where}.gear_ratio")
        mass = num("mass_kg", required=False)
        if mass is not None and mass < 0:
            raise ConfigError("must not be negative", source=src, key=f"{where}.mass_kg")
        try:
            com = _vec3(jd, "com_mm", src)
        except ConfigError as err:
            raise ConfigError(str(err).split(": ", 2)[-1], source=src,
                              key=f"{where}.com_mm") from None
        if (mass is None) != (com is None):
            raise ConfigError("mass_kg and com_mm must be given together", source=src,
                              key=f"{where}.{'com_mm' if com is None else 'mass_kg'}")
        sign = jd.get("sign", 1)
        if sign not in (1, -1) or isinstance(sign, bool):
            raise ConfigError(f"must be 1 or -1, got {sign!r}", source=src, key=f"{where}.sign")
        coupled = jd.get("coupled_to")
        if coupled is not None and (
                not isinstance(coupled, int) or isinstance(coupled, bool)
                or not 1 <= coupled <= len(raw_joints) or coupled == i):
            raise ConfigError(f"must name another joint 1..{len(raw_joints)}",
                              source=src, key=f"{where}.coupled_to")
        coupling = num("coupling", 1.0 if coupled is not None else 0.0)
        speed = num("max_speed_deg_s", 180.0)
        assert coupling is not None and speed is not None
        if speed <= 0:
            raise ConfigError("must be positive", source=src, key=f"{where}.max_speed_deg_s")
        jname = jd.get("name", "")
        if not isinstance(jname, str):
            raise ConfigError("must be a string", source=src, key=f"{where}.name")
        joints.append(Joint(
            a=a * 1e-3, d=d * 1e-3, alpha=math.radians(alpha), theta_offset=math.radians(off),
            q_min=math.radians(qmin), q_max=math.radians(qmax), gear_ratio=gear,
            mass=mass, com=None if com is None else (com[0] * 1e-3, com[1] * 1e-3, com[2] * 1e-3),
            sign=int(sign), coupled_to=None if coupled is None else coupled - 1,
            coupling=coupling if coupled is not None else 0.0, name=jname,
            max_speed=math.radians(speed),
        ))
    tool = _vec3(data, "tool_mm", src) or (0.0, 0.0, 50.0)
    gravity = _vec3(data, "gravity", src) or (0.0, 0.0, -9.81)
    manufacturer = data.get("manufacturer", "")
    if not isinstance(manufacturer, str):
        raise ConfigError("must be a string", source=src, key="manufacturer")
    return RobotDescription(
        name=name.strip(), joints=tuple(joints), manufacturer=manufacturer,
        tool=(tool[0] * 1e-3, tool[1] * 1e-3, tool[2] * 1e-3), gravity=gravity,
        source=str(data.get("source", src)),
    )


def builtin_robots() -> list[str]:
    """Return the names under which built-in descriptions can be loaded."""
    root = resources.files("robocal.data") / "robots"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


_ALIASES = {
    "lrmate200id": "fanuc_lrmate200id", "lr-mate-200id": "fanuc_lrmate200id",
    "lrmate200i": "fanuc_lrmate200i", "lr-mate-200i": "fanuc_lrmate200i",
    "ur10-cb3": "ur10", "kr210": "kuka_kr210_r3100",
}


def load_robot(spec: str | Path) -> RobotDescription:
    """Load a robot by built-in name (see :func:`builtin_robots`) or from a TOML file path.

    Raises
    ------
    ConfigError
        When the name is unknown, the file is missing or unreadable, or a key is invalid.
    """
    text_spec = str(spec)
    key = _ALIASES.get(text_spec.lower(), text_spec.lower())
    if not text_spec.endswith(".toml") and key in builtin_robots():
        res = resources.files("robocal.data") / "robots" / f"{key}.toml"
        data = tomllib.loads(res.read_text())
        return _parse(data, f"builtin:{key}")
    path = Path(text_spec)
    if not path.exists():
        raise ConfigError(
            f"no such file, and not a built-in robot (built-in: {', '.join(builtin_robots())})",
            source=text_spec)
    return _parse(read_toml(path), text_spec)
