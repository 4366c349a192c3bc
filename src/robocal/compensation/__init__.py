"""Compensation: gradient-search inverse kinematics and compensation tables.

Public API
----------
``compensate(cal, targets_p, seeds_q, R_targets=None, ...)`` -> :class:`CompensationResult`
    joint commands whose pose under the calibrated model equals each target (batched).
``nominal_ik(robot, T_base_flange, seed)`` -> :class:`IKResult`
    closed form for ortho-parallel arms with a spherical wrist (all 8 solutions, the one
    closest to the seed chosen), damped least squares for other robots.
``build_table(cal, kind, ...)`` -> :class:`CompensationTable`
    ``targets`` / ``joint`` / ``frames`` tables, sealed with a checksum.
``diff_tables(a, b)`` -> :class:`TableDiff`
    what changes between two tables.
``read_targets_csv`` / ``write_compensated_joints_csv``
    TARGETS.csv and JOINTS.csv.
"""

from robocal.compensation._build import (
    FrameFit,
    build_table,
    fit_frames,
    ideal_positions,
    joint_corrections,
    nominal_residual_mm,
    sample_poses,
    targets_table,
    valid_range,
)
from robocal.compensation._diff import TableDiff, diff_tables
from robocal.compensation._dls import rotation_error
from robocal.compensation._ik import (
    IKResult,
    has_closed_form,
    ik_solutions,
    nominal_fk,
    nominal_ik,
)
from robocal.compensation._solve import (
    STATUSES,
    CompensationResult,
    compensate,
)
from robocal.compensation._summary import (
    PURPOSE,
    describe_table,
    improvement_refusal,
    summary_line,
)
from robocal.compensation._table import (
    TABLE_FORMAT,
    CompensationTable,
    Frame,
    FramesPayload,
    JointCorrection,
    TargetRow,
)
from robocal.compensation._targets import (
    TargetSet,
    compensated_joints_csv_text,
    read_targets_csv,
    write_compensated_joints_csv,
)
from robocal.compensation._vendor import write_vendor_export

__all__ = [
    "PURPOSE",
    "STATUSES",
    "TABLE_FORMAT",
    "CompensationResult",
    "CompensationTable",
    "Frame",
    "FrameFit",
    "FramesPayload",
    "IKResult",
    "JointCorrection",
    "TableDiff",
    "TargetRow",
    "TargetSet",
    "build_table",
    "compensate",
    "compensated_joints_csv_text",
    "describe_table",
    "diff_tables",
    "fit_frames",
    "has_closed_form",
    "ideal_positions",
    "ik_solutions",
    "improvement_refusal",
    "joint_corrections",
    "nominal_fk",
    "nominal_ik",
    "nominal_residual_mm",
    "read_targets_csv",
    "rotation_error",
    "sample_poses",
    "summary_line",
    "targets_table",
    "valid_range",
    "write_compensated_joints_csv",
    "write_vendor_export",
]
