"""Compensation: gradient-search inverse kinematics and compensation tables."""

from robocal.compensation._table import (
    TABLE_FORMAT,
    CompensationTable,
    Frame,
    FramesPayload,
    JointCorrection,
    TargetRow,
)

__all__ = [
    "TABLE_FORMAT",
    "CompensationTable",
    "Frame",
    "FramesPayload",
    "JointCorrection",
    "TargetRow",
]
