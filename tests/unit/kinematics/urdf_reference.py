"""Test-side URDF forward kinematics: xml.etree plus 4x4 products, independent of robocal."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np


def _rpy(r: float, p: float, y: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    return T


def _vec(text: str | None, default: tuple[float, float, float]) -> np.ndarray:
    return np.array(default if text is None else [float(v) for v in text.split()])


def urdf_fk(text: str, values: dict[str, float], link: str) -> np.ndarray:
    """Pose (4, 4) of ``link`` in the root link's frame; ``values`` by joint name (rad)."""
    root = ET.fromstring(text)
    by_child = {j.find("child").get("link"): j for j in root.findall("joint")}
    chain = []
    while link in by_child:
        j = by_child[link]
        chain.append(j)
        link = j.find("parent").get("link")
    T = np.eye(4)
    for j in reversed(chain):
        o = j.find("origin")
        A = np.eye(4)
        if o is not None:
            A[:3, :3] = _rpy(*_vec(o.get("rpy"), (0, 0, 0)))
            A[:3, 3] = _vec(o.get("xyz"), (0, 0, 0))
        T = T @ A
        if j.get("type") in ("revolute", "continuous"):
            ax = j.find("axis")
            T = T @ _axis_angle(_vec(None if ax is None else ax.get("xyz"), (1, 0, 0)),
                                values[j.get("name")])
    return T


def movable_joints(text: str) -> list[str]:
    """Names of the revolute/continuous joints in document order."""
    return [j.get("name") for j in ET.fromstring(text).findall("joint")
            if j.get("type") in ("revolute", "continuous")]
