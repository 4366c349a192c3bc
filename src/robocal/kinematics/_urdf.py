"""URDF in and out: nominal chains to standard DH, calibrated models to URDF (numpy + stdlib).

Import (:func:`urdf_to_robot`) takes the serial chain from the root link to the tip link,
folds fixed joints, and turns the joint axes at the zero configuration into standard DH
frames with the usual common-normal construction:

* frame i-1 has z along joint i's axis (in the URDF's positive direction, so ``sign = 1``);
* skew axes: x_i along the common normal, origin where it meets axis i+1;
* intersecting axes: x_i = +-(z_{i-1} x z_i), origin at the intersection;
* parallel axes (d is not defined): the common normal through the previous origin, so
  ``d_i = 0`` -- the offsets along the axis accumulate in the next joint's d, as in UR's
  and most vendors' tables; coincident axes: x_i = x_{i-1};
* the sign of x_i is chosen so that it points along x_{i-1} (theta offsets near 0);
* frame 0: z along joint 1, origin at the point of axis 1 nearest the root origin, x the
  root's x projected onto the plane normal to z (root y when x is along the axis); the rest
  of root -> frame 0 becomes ``base_*`` of the description;
* frame n: z along joint n, origin at the point of axis n nearest the tip origin, x the
  tip's x projected (tip y likewise); the tip relative to it becomes ``flange_*``.

Nearly parallel (not exactly parallel) axes put the common normal far away: DH stays exact
in exact arithmetic but its lengths grow as 1/angle, and so does rounding (the usual reason
for Hayati's parameters); robocal imports them as they are.

Not representable (one :class:`ConfigError` naming the joint): prismatic, planar and
floating joints, ``mimic`` joints, movable joints outside one serial chain. A ``tip`` link
cuts the chain there: joints below it (a gripper's jaw, of any type) are left out, so
an arm whose URDF carries a movable gripper imports with ``tip`` = the gripper's base.
``continuous`` joints get +-360 deg limits. Links' inertials, visuals and collisions are ignored.

Export (:func:`robot_to_urdf`, :func:`calibrated_to_urdf`) writes a chain whose joint i
turns about ``(0, 0, sign_i)`` of its frame: the joint origins hold everything constant
(DH offsets, theta offsets, the constant error terms, root -> DH frame 0); the flange and the
reflector point (``tcp`` link) are fixed joints, and so is the tracker -> base transform
when the model has one. Joint-dependent error terms, joint couplings and the low-order
fallback cannot be expressed in URDF and are listed in a side table.

XML is read with :mod:`xml.etree.ElementTree` after refusing documents with a DOCTYPE
(no entity expansion, no external entities) and over 16 MB; see docs/adr/0009.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.files import read_text
from robocal.errors import ConfigError
from robocal.kinematics._calibrated import CalibratedModel
from robocal.kinematics._robot import (
    Joint,
    RobotDescription,
    default_link_radii,
    matrix_to_rpy,
    transform,
)
from robocal.kinematics._spec import ParameterLayout
from robocal.kinematics._transforms import euler_xyz_to_matrix

Array = NDArray[np.float64]
MAX_URDF_BYTES = 16 * 1024 * 1024
_PAR = 1e-9      # |sin| below which two axes count as parallel
_MEET = 1e-9     # m: distance below which two axes count as intersecting
_MOVABLE = ("revolute", "continuous")
_KNOWN = ("revolute", "continuous", "fixed", "prismatic", "planar", "floating")
SIDE_FORMAT = "robocal.urdf-side/1"


@dataclass(frozen=True)
class _UJoint:
    name: str
    kind: str
    parent: str
    child: str
    origin: Array            # (4, 4)
    axis: Array              # (3,), unit
    lower: float
    upper: float
    velocity: float | None
    problem: str | None = None   # why it cannot be represented (raised unless cut off)


def _floats(text: str | None, n: int, default: Sequence[float], where: str,
            source: str) -> list[float]:
    if text is None:
        return list(default)
    parts = text.split()
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise ConfigError(f"needs {n} finite numbers, got {text!r}", source=source, key=where)
    return vals


def _parse_xml(text: str, source: str) -> ET.Element:
    if len(text.encode("utf-8", "replace")) > MAX_URDF_BYTES:
        raise ConfigError(f"file larger than {MAX_URDF_BYTES // 2**20} MB", source=source)
    if "<!DOCTYPE" in text or "<!ENTITY" in text:
        raise ConfigError("DOCTYPE/ENTITY declarations are not accepted in URDF files",
                          source=source)
    try:
        root = ET.fromstring(text)
    except ET.ParseError as err:
        raise ConfigError(f"not well-formed XML: {err}", source=source) from None
    if root.tag != "robot":
        raise ConfigError(f"root element must be <robot>, got <{root.tag}>", source=source)
    return root


def _joints(root: ET.Element, source: str) -> list[_UJoint]:
    out = []
    for k, el in enumerate(root.findall("joint"), start=1):
        name = el.get("name") or f"joint#{k}"
        where = f"joint {name}"
        kind = el.get("type", "")
        if kind not in _KNOWN:
            raise ConfigError(f"unknown joint type {kind!r}", source=source, key=where)
        problem = None
        if kind in ("prismatic", "planar", "floating"):
            problem = (f"{kind} joints cannot be represented: robocal's robot model has "
                       "revolute joints only")
        elif el.find("mimic") is not None:
            problem = "mimic joints cannot be represented (use coupled_to in the robot TOML)"
        parent, child = el.find("parent"), el.find("child")
        if parent is None or child is None or not parent.get("link") or not child.get("link"):
            raise ConfigError("needs <parent link=...> and <child link=...>", source=source,
                              key=where)
        org = el.find("origin")
        xyz = _floats(None if org is None else org.get("xyz"), 3, (0, 0, 0),
                      f"{where}.origin.xyz", source)
        rpy = _floats(None if org is None else org.get("rpy"), 3, (0, 0, 0),
                      f"{where}.origin.rpy", source)
        ax_el = el.find("axis")
        axis = np.array(_floats(None if ax_el is None else ax_el.get("xyz"), 3, (1, 0, 0),
                                f"{where}.axis.xyz", source))
        lower, upper, vel = -2 * math.pi, 2 * math.pi, None
        if kind in _MOVABLE:
            big = float(np.abs(axis).max())
            if big < 1e-12:
                raise ConfigError("axis must not be zero", source=source, key=f"{where}.axis")
            axis = axis / big               # scaled first: no overflow for huge components
            axis = axis / float(np.linalg.norm(axis))
            lim = el.find("limit")
            if kind == "revolute":
                if lim is None:
                    raise ConfigError("revolute joint needs <limit>", source=source,
                                      key=f"{where}.limit")
                lower = _floats(lim.get("lower"), 1, (0.0,), f"{where}.limit.lower", source)[0]
                upper = _floats(lim.get("upper"), 1, (0.0,), f"{where}.limit.upper", source)[0]
                if lower >= upper:
                    raise ConfigError(f"lower ({lower}) must be below upper ({upper})",
                                      source=source, key=f"{where}.limit")
            if lim is not None and lim.get("velocity") is not None:
                vel = _floats(lim.get("velocity"), 1, (0.0,), f"{where}.limit.velocity",
                              source)[0]
                vel = vel if vel > 0 else None
        out.append(_UJoint(name, kind, str(parent.get("link")), str(child.get("link")),
                           transform((xyz[0], xyz[1], xyz[2]), (rpy[0], rpy[1], rpy[2])),
                           axis, lower, upper, vel, problem))
    return out


def _cut_below(joints: list[_UJoint], links: set[str], tip: str | None, source: str
               ) -> tuple[list[_UJoint], set[str]]:
    """The joints and links without those below the ``tip`` link (a gripper); a problem of a
    joint that stays is raised."""
    if tip is not None and tip not in links | {j.parent for j in joints} | {j.child
                                                                         for j in joints}:
        raise ConfigError(f"no link named {tip!r}", source=source, key="tip")
    below: set[str] = set()
    todo = [] if tip is None else [tip]
    while todo:
        link = todo.pop()
        for j in joints:
            if j.parent == link and j.name not in below:
                below.add(j.name)
                todo.append(j.child)
    for j in joints:
        if j.problem is not None and j.name not in below:
            raise ConfigError(j.problem, source=source, key=f"joint {j.name}")
    cut = {j.child for j in joints if j.name in below} - {tip}
    return [j for j in joints if j.name not in below], links - cut


def _by_child(joints: list[_UJoint], source: str) -> dict[str, _UJoint]:
    """Each link's parent joint; a link with two is refused."""
    by_child: dict[str, _UJoint] = {}
    for j in joints:
        if j.child in by_child:
            raise ConfigError(f"link {j.child!r} has two parent joints", source=source,
                              key=f"joint {j.name}")
        by_child[j.child] = j
    return by_child


def _chain(joints: list[_UJoint], links: set[str], tip: str | None,
           source: str) -> list[_UJoint]:
    """The joints from the root link to the tip, checked to be one serial chain."""
    joints, links = _cut_below(joints, links, tip, source)
    by_child = _by_child(joints, source)
    names = links | {j.parent for j in joints} | {j.child for j in joints}
    roots = sorted(names - set(by_child))
    if len(roots) != 1:
        raise ConfigError(f"expected one root link, found {roots or 'none (a cycle)'}",
                          source=source)
    parents = {j.parent for j in joints}
    movable = {j.name for j in joints if j.kind in _MOVABLE}
    if not movable:
        raise ConfigError("no revolute or continuous joint", source=source)

    def path(link: str) -> list[_UJoint]:
        out: list[_UJoint] = []
        seen = set()
        while link in by_child:
            if link in seen:
                raise ConfigError(f"kinematic loop at link {link!r}", source=source)
            seen.add(link)
            out.append(by_child[link])
            link = by_child[link].parent
        return out[::-1]

    # the tip, else the leaves
    candidates = [tip] if tip is not None else sorted(n for n in names if n not in parents)

    def covers(link: str) -> bool:
        return {j.name for j in path(link)} >= movable

    if tip is None:
        for pref in ("tool0", "flange"):
            if pref in names and covers(pref):
                return path(pref)
    full = [c for c in candidates if covers(c)]
    if not full:
        raise ConfigError("the movable joints are not on one serial chain from the root"
                          + (f" to {tip!r}" if tip else ""), source=source)
    return path(max(full, key=lambda c: (len(path(c)), c)))


def _unit(v: Array) -> Array:
    return v / float(np.linalg.norm(v))


def _perp(v: Array, z: Array) -> Array:
    """Component of v normal to unit z."""
    return v - float(v @ z) * z


def _x_from(x: Array, y: Array, z: Array) -> Array:
    """x projected normal to z; y's projection when x is within 60 deg of z (better
    conditioned)."""
    px, py = _perp(x, z), _perp(y, z)
    if np.linalg.norm(px) >= 0.5 or np.linalg.norm(px) >= np.linalg.norm(py):
        return px
    return py


def _frames_to_dh(z: list[Array], p: list[Array], T_tip: Array
                  ) -> tuple[Array, list[tuple[float, float, float, float]], Array]:
    """DH frames for axes (points p_i, unit directions z_i) at q = 0.

    Returns T_root_dh0 (4, 4), per joint (theta, d, a, alpha), and T_dhn_tip (4, 4).
    """
    n = len(z)
    ex, ey = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    zs = [z[0]]
    Os = [p[0] + float((np.zeros(3) - p[0]) @ z[0]) * z[0]]
    xs = [_unit(_x_from(ex, ey, z[0]))]
    for i in range(1, n + 1):
        zp, Op, xp = zs[-1], Os[-1], xs[-1]
        if i == n:
            zi = zp
            Oi = Op + float((T_tip[:3, 3] - Op) @ zp) * zp
            xi = _unit(_x_from(T_tip[:3, 0], T_tip[:3, 1], zi))
        else:
            zi, pi = z[i], p[i]
            c = np.cross(zp, zi)
            if np.linalg.norm(c) > _PAR:
                w = Op - pi
                b, d_, e = float(zp @ zi), float(zp @ w), float(zi @ w)
                den = 1.0 - b * b
                t = (e - b * d_) / den
                Oi = pi + t * zi
                nv = _unit(c)
            else:
                v = _perp(pi - Op, zp)
                if np.linalg.norm(v) > _MEET:
                    Oi = Op + v
                    nv = _unit(v)
                else:
                    Oi, nv = Op, xp
            xi = nv if float(nv @ xp) >= 0.0 else -nv
            xi = _unit(_perp(xi, zi))
        zs.append(zi)
        Os.append(Oi)
        xs.append(xi)
    dh = []
    for i in range(1, n + 1):
        zp, Op, xp, zi, Oi, xi = zs[i - 1], Os[i - 1], xs[i - 1], zs[i], Os[i], xs[i]
        theta = math.atan2(float(np.cross(xp, xi) @ zp), float(xp @ xi))
        d = float((Oi - Op) @ zp)
        a = float((Oi - Op) @ xi)
        alpha = math.atan2(float(np.cross(zp, zi) @ xi), float(zp @ zi))
        dh.append((theta, d, a, alpha))

    def frame(k: int) -> Array:
        T = np.eye(4)
        T[:3, 0], T[:3, 2] = xs[k], zs[k]
        T[:3, 1] = np.cross(zs[k], xs[k])
        T[:3, 3] = Os[k]
        return T

    T_n = frame(n)
    return frame(0), dh, np.asarray(np.linalg.solve(T_n, T_tip), dtype=float)


def urdf_to_robot(text: str, *, source: str = "<urdf>", tip: str | None = None,
                  tool_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> RobotDescription:
    """Import the serial chain of a URDF document as a standard-DH robot description.

    Parameters
    ----------
    text
        URDF XML (already expanded: xacro is not processed).
    source
        Name used in error messages.
    tip
        Link ending the chain; default ``tool0``, else ``flange``, else the deepest leaf
        below the last movable joint. Joints below the tip are left out.
    tool_mm
        Default flange -> reflector point of the description (flange = the tip link), mm.

    Raises
    ------
    ConfigError
        Malformed XML, a joint that cannot be represented, or no single serial chain.
    """
    root = _parse_xml(text, source)
    links = {str(el.get("name")) for el in root.findall("link") if el.get("name")}
    chain = _chain(_joints(root, source), links, tip, source)
    T = np.eye(4)
    z: list[Array] = []
    p: list[Array] = []
    movers = []
    for j in chain:
        T = T @ j.origin
        if j.kind in _MOVABLE:
            z.append(T[:3, :3] @ j.axis)
            p.append(T[:3, 3].copy())
            movers.append(j)
    if not np.all(np.isfinite(T)) or float(np.abs(T[:3, 3]).max()) > 1e6:
        raise ConfigError("joint origins put the chain beyond 1000 km: not a robot",
                          source=source)
    T_base, dh, T_flange = _frames_to_dh(z, p, T)
    if not (np.all(np.isfinite(dh)) and np.all(np.isfinite(T_base))
            and np.all(np.isfinite(T_flange))):
        raise ConfigError("the joint axes give no finite DH parameters", source=source)
    joints = []
    for j, (theta, d, a, alpha) in zip(movers, dh, strict=True):
        lo, hi = (j.lower, j.upper) if j.kind == "revolute" else (-2 * math.pi, 2 * math.pi)
        kw: dict[str, Any] = {} if j.velocity is None else {"max_speed": j.velocity}
        joints.append(Joint(a=a, d=d, alpha=alpha, theta_offset=theta, q_min=lo, q_max=hi,
                            name=j.name, **kw))

    def parts(M: Array) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        M = M.copy()
        M[np.abs(M) < 1e-15] = 0.0
        rpy = matrix_to_rpy(M[:3, :3])
        return ((float(M[0, 3]), float(M[1, 3]), float(M[2, 3])),
                tuple(0.0 if abs(v) < 1e-15 else v for v in rpy))  # type: ignore[return-value]

    bxyz, brpy = parts(T_base)
    fxyz, frpy = parts(T_flange)
    name = (root.get("name") or Path(source).stem or "robot").strip() or "robot"
    robot = RobotDescription(
        name=name, joints=tuple(joints),
        tool=(tool_mm[0] * 1e-3, tool_mm[1] * 1e-3, tool_mm[2] * 1e-3),
        source=f"urdf:{source}", base_xyz=bxyz, base_rpy=brpy, flange_xyz=fxyz,
        flange_rpy=frpy,
    )
    return _with_collision_radii(robot, root, chain, source)


def _collision_radius(link: ET.Element, source: str) -> float | None:
    """Radius (m) of the capsule that encloses a link's primitive collision shapes about
    their long axis: a cylinder's or sphere's radius, a box's half cross-section diagonal
    (the two smaller sides); the largest over the link's shapes. None without primitives
    (meshes only, or no <collision>)."""
    best: float | None = None
    where = f"link {link.get('name')!r} collision"
    for geo in link.findall("collision/geometry"):
        r: float | None = None
        for kind in ("cylinder", "sphere", "capsule"):
            el = geo.find(kind)
            if el is not None:
                r = _floats(el.get("radius"), 1, (math.nan,), where, source)[0]
        box = geo.find("box")
        if box is not None:
            size = sorted(abs(v) for v in _floats(box.get("size"), 3, (math.nan,) * 3, where,
                                                  source))
            r = 0.5 * math.hypot(size[0], size[1])
        if r is not None and math.isfinite(r) and r > 0:
            best = r if best is None else max(best, r)
    return best


def _with_collision_radii(robot: RobotDescription, root: ET.Element, chain: list[_UJoint],
                          source: str) -> RobotDescription:
    """Capsule radii per joint body from the collision geometry of the links that body
    carries (the child link of its joint and links fixed to it); bodies without primitive
    shapes get the default (:func:`default_link_radii`). Unchanged when no body has any."""
    shapes = {str(el.get("name")): _collision_radius(el, source) for el in root.findall("link")}
    radii: list[float | None] = []
    for j in chain:
        if j.kind in _MOVABLE:
            radii.append(None)
        if radii:
            r = shapes.get(j.child)
            if r is not None:
                radii[-1] = r if radii[-1] is None else max(radii[-1], r)
    if all(r is None for r in radii):
        return robot
    default = default_link_radii(robot)
    from_urdf = [i + 1 for i, r in enumerate(radii) if r is not None]
    missing = [i + 1 for i, r in enumerate(radii) if r is None]
    note = "URDF collision geometry (bodies " + ", ".join(map(str, from_urdf)) + ")"
    if missing:
        note += "; default radii for bodies " + ", ".join(map(str, missing))
    return replace(robot, link_radii=tuple(d if r is None else r
                                           for r, d in zip(radii, default, strict=True)),
                   collision_source=note)


def load_urdf(path: str | Path, *, tip: str | None = None) -> RobotDescription:
    """Read a URDF file and import it with :func:`urdf_to_robot`."""
    return urdf_to_robot(read_text(path), source=str(path), tip=tip)


# -- export ---------------------------------------------------------------------------------
def _tz_tx_rx(d: float, a: float, alpha: float) -> Array:
    c, s = math.cos(alpha), math.sin(alpha)
    return np.array([[1.0, 0.0, 0.0, a], [0.0, c, -s, 0.0], [0.0, s, c, d],
                     [0.0, 0.0, 0.0, 1.0]])


def _rz(t: float) -> Array:
    T = np.eye(4)
    c, s = math.cos(t), math.sin(t)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _error_T(e: Array) -> Array:
    """``Tx Ty Tz Rx Ry Rz`` (4, 4) of error components e (6,)."""
    T = np.eye(4)
    T[:3, :3] = euler_xyz_to_matrix(float(e[3]), float(e[4]), float(e[5]))
    T[:3, 3] = e[:3]
    return T


def _fmt(v: float) -> str:
    return repr(float(v) + 0.0)


def _origin(T: Array) -> str:
    r, p, y = matrix_to_rpy(T[:3, :3])
    xyz = " ".join(_fmt(v) for v in T[:3, 3])
    return f'<origin xyz="{xyz}" rpy="{_fmt(r)} {_fmt(p)} {_fmt(y)}"/>'


def _esc(s: str) -> str:
    return (s.replace("&", "&amp;").replace('"', "&quot;").replace("<", "&lt;")
            .replace(">", "&gt;"))


def robot_to_urdf(robot: RobotDescription, *, joint_errors: Array | None = None,
                  tool: Sequence[float] | Array | None = None, T_tracker_base: Array | None = None,
                  comment: str = "") -> str:
    """URDF text of the robot's chain with constant joint errors folded into joint origins.

    Parameters
    ----------
    joint_errors
        Constant error components per joint (dof, 6): dx, dy, dz (m), ex, ey, ez (rad),
        applied right after the joint rotation as in the kinematic model; default zeros.
    tool
        Flange -> reflector point (3,) m for the ``tcp`` link; default the robot's.
    T_tracker_base
        When given (4, 4, m), a root link ``tracker`` and a fixed joint to ``base_link``.

    The URDF value of joint i is ``q_i + coupling_i * q_{coupled_to}`` (the controller's
    value when the joint is not coupled); it turns about ``(0, 0, sign_i)``.
    """
    dof = robot.dof
    E = np.zeros((dof, 6)) if joint_errors is None else np.asarray(joint_errors, dtype=float)
    tcp = np.asarray(robot.tool if tool is None else tool, dtype=float)
    lines = ['<?xml version="1.0"?>']
    if comment:
        lines.append(f"<!-- {comment.replace('--', '- -')} -->")
    lines.append(f'<robot name="{_esc(robot.name)}">')
    link_names = ["base_link", *[f"link_{i + 1}" for i in range(dof)], "flange", "tcp"]
    if T_tracker_base is not None:
        link_names.insert(0, "tracker")
    lines += [f'  <link name="{n}"/>' for n in link_names]
    if T_tracker_base is not None:
        lines += ['  <joint name="tracker_to_base" type="fixed">',
                  '    <parent link="tracker"/>', '    <child link="base_link"/>',
                  f"    {_origin(np.asarray(T_tracker_base, dtype=float))}", "  </joint>"]
    before = robot.T_root_dh0
    for i, j in enumerate(robot.joints):
        name = j.name or f"joint_{i + 1}"
        parent = "base_link" if i == 0 else f"link_{i}"
        lines += [f'  <joint name="{_esc(name)}" type="revolute">',
                  f'    <parent link="{parent}"/>', f'    <child link="link_{i + 1}"/>',
                  f"    {_origin(before @ _rz(j.theta_offset))}",
                  f'    <axis xyz="0 0 {j.sign}"/>',
                  f'    <limit lower="{_fmt(j.q_min)}" upper="{_fmt(j.q_max)}" effort="0" '
                  f'velocity="{_fmt(j.max_speed)}"/>', "  </joint>"]
        before = _error_T(E[i]) @ _tz_tx_rx(j.d, j.a, j.alpha)
    lines += ['  <joint name="flange_fixed" type="fixed">', f'    <parent link="link_{dof}"/>',
              '    <child link="flange"/>', f"    {_origin(before @ robot.T_dhn_flange)}",
              "  </joint>",
              '  <joint name="tcp_fixed" type="fixed">', '    <parent link="flange"/>',
              '    <child link="tcp"/>',
              f'    <origin xyz="{" ".join(_fmt(v) for v in tcp)}" rpy="0.0 0.0 0.0"/>',
              "  </joint>", "</robot>", ""]
    return "\n".join(lines)


def constant_part(cal: CalibratedModel) -> tuple[Array, Array]:
    """Parameters (P,) of the model with every joint-dependent term set to zero, and the
    constant error components per joint (dof, 6)."""
    model = cal.model
    x = cal.params.copy()
    E = np.zeros((model.robot.dof, 6))
    comps = ("dx", "dy", "dz", "ex", "ey", "ez")
    for k, t in enumerate(model.spec.terms):
        if t.family == "const":
            E[t.joint, comps.index(t.component)] += x[ParameterLayout.OFFSET + k]
        else:
            x[ParameterLayout.OFFSET + k] = 0.0
    return x, E


def calibrated_to_urdf(cal: CalibratedModel) -> tuple[str, dict[str, Any]]:
    """URDF of a calibrated model's constant part, and the side table of what URDF cannot hold.

    The URDF's ``tcp`` link, for URDF joint values v (see :func:`robot_to_urdf`), sits where
    the model with its joint-dependent terms zeroed (:func:`constant_part`) puts the
    reflector, in the tracker frame (root link ``tracker``).
    """
    model = cal.model
    x, E = constant_part(cal)
    text = robot_to_urdf(
        model.robot, joint_errors=E, tool=x[ParameterLayout.TOOL],
        T_tracker_base=model.base_transform(x),
        comment=f"robocal calibrated model {cal.model_id} ({cal.kind}): constant part only; "
                "joint-dependent terms are in the side table")
    sig = cal.sigma
    rows = []
    for k, t in enumerate(model.spec.terms):
        if t.family == "const":
            continue
        unit = t.unit
        f, u = {"m": (1e3, "mm"), "rad": (180.0 / math.pi, "deg"),
                "rad/(N m)": (180.0 / math.pi, "deg/(N m)")}[unit]
        rows.append({"name": t.name, "joint": t.joint + 1, "component": t.component,
                     "family": t.family, "index": t.index,
                     "value": float(cal.params[ParameterLayout.OFFSET + k] * f), "unit": u,
                     "sigma": None if sig is None else float(sig[ParameterLayout.OFFSET + k] * f)})
    couplings = [
        {"joint": i + 1, "coupled_to": j.coupled_to + 1, "coupling": j.coupling,
         "urdf_value": f"q{i + 1} + {j.coupling!r} * q{j.coupled_to + 1}"}
        for i, j in enumerate(model.robot.joints) if j.coupled_to is not None]
    side = {
        "format": SIDE_FORMAT,
        "model_id": cal.model_id,
        "kind": cal.kind,
        "robot": model.robot.name,
        "error_model": model.spec.to_dict(),
        "not_representable": {
            "why": "URDF joint origins are constant; these terms change with the joint "
                   "angle (polynomials, harmonics, strain-wave ripple, angle maps, gravity "
                   "compliance) and are evaluated as in the robocal model "
                   "(docs: kinematics/_spec.py). Use robocal predict/compensate or a "
                   "compensation table for them.",
            "terms": rows,
            "joint_couplings": couplings,
            "fallback_model": cal.fallback is not None,
        },
        "urdf_joint_values": "URDF joint i = q_i (+ coupling * q_j for coupled joints), rad",
    }
    return text, side
