"""Names of the built-in robot descriptions, in one place that imports nothing heavy.

The CLI checks a ``--robot`` argument with these before it imports numpy and the planner
(a typo is answered at once); :func:`robocal.kinematics.load_robot` resolves names the same
way.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from robocal.errors import ConfigError

__all__ = ["ALIASES", "builtin_robot_key", "builtin_robots", "check_robot_spec"]

#: Other spellings of built-in robots.
ALIASES = {
    "lrmate200id": "fanuc_lrmate200id", "lr-mate-200id": "fanuc_lrmate200id",
    "lrmate200i": "fanuc_lrmate200i", "lr-mate-200i": "fanuc_lrmate200i",
    "ur10-cb3": "ur10", "kr210": "kuka_kr210_r3100",
}


def builtin_robots() -> list[str]:
    """Return the names under which built-in descriptions can be loaded."""
    root = resources.files("robocal.data") / "robots"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def builtin_robot_key(spec: str) -> str | None:
    """The built-in name ``spec`` (a name or alias, any case) stands for, else None."""
    if spec.endswith((".toml", ".urdf")):
        return None
    key = ALIASES.get(spec.lower(), spec.lower())
    return key if key in builtin_robots() else None


def check_robot_spec(spec: str) -> None:
    """Refuse a robot argument that is neither a built-in name nor an existing file.

    Raises
    ------
    ConfigError
        Naming the built-in robots.
    """
    if builtin_robot_key(spec) is None and not Path(spec).exists():
        raise ConfigError(
            f"no such file, and not a built-in robot (built-in: {', '.join(builtin_robots())})",
            source=spec)
