"""Loading a robot description by name, TOML or URDF path.

Apart from :mod:`robocal.kinematics._robot` because the URDF importer builds on the robot
description: with :func:`load_robot` here, neither imports the other lazily (ADR 0038).
"""

from __future__ import annotations

from pathlib import Path

from robocal.kinematics._robot import RobotDescription, load_toml_robot
from robocal.kinematics._urdf import load_urdf

__all__ = ["load_robot"]


def load_robot(spec: str | Path) -> RobotDescription:
    """Load a robot by built-in name (see :func:`builtin_robots`), a TOML or a URDF file path.

    A path ending in ``.urdf`` is imported with :func:`robocal.kinematics.load_urdf`.

    Raises
    ------
    ConfigError
        When the name is unknown, the file is missing or unreadable, or a key is invalid.
    """
    text_spec = str(spec)
    if text_spec.lower().endswith(".urdf"):
        return load_urdf(text_spec)
    return load_toml_robot(text_spec)
