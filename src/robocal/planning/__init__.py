"""Pose planning for calibration campaigns.

Candidates are scrambled Sobol points over the joint ranges; a cell description (TOML) decides
which are feasible (reflector facing the tracker, unobstructed beam, no collision with floor,
keep-out boxes or the robot itself, within tracker range); a D-optimal selection on the
column-scaled identification Jacobian picks the calibration poses; validation poses, CPA
sweeps and ISO 9283 cube poses are added; the result is ordered for short joint moves and
written as PLAN.json for the daemon. Every move of a plan is checked along its swept path
(:class:`MotionChecker`); targets without a safe route are dropped and listed.

Public entry points: :func:`plan_campaign`, :class:`Plan` (``load``/``save``),
:func:`load_cell`, :class:`Cell`, :class:`FeasibilityChecker`, :class:`DesignSpace`.
"""

from robocal._core.joint_ranges import targets_outside
from robocal.kinematics import default_link_radii
from robocal.planning._campaign import (
    cell_design_space,
    draw_candidates,
    plan_campaign,
    split_legs,
)
from robocal.planning._cell import Cell, builtin_cells, load_cell, pydantic_config_error
from robocal.planning._coverage import (
    excluded_families,
    joint_coverage,
    read_program_joints,
    winding_ranges,
)
from robocal.planning._cpa import CpaSweep, cpa_sweeps
from robocal.planning._design import (
    DESIGNS,
    MODELS,
    DesignSpace,
    Observability,
    identification_jacobian,
    model_spec,
    observability_indices,
)
from robocal.planning._feasibility import (
    Feasibility,
    FeasibilityChecker,
    one_revolution,
    working_ranges,
)
from robocal.planning._geometry import (
    CapsuleModel,
    link_frames,
    segment_box_distance,
    segment_distance,
)
from robocal.planning._iso import IsoCube, iso_cube, solve_ik
from robocal.planning._motion import SAMPLE_FRACTION, MotionChecker, MoveCheck, UnsafeMove
from robocal.planning._order import insert_via_points, move_times, order_poses
from robocal.planning._plan import (
    PLAN_FORMAT,
    DroppedTarget,
    ExcludedFamily,
    JointCoverage,
    Plan,
    PlannedPose,
)

__all__ = [
    "DESIGNS",
    "MODELS",
    "PLAN_FORMAT",
    "SAMPLE_FRACTION",
    "CapsuleModel",
    "Cell",
    "CpaSweep",
    "DesignSpace",
    "DroppedTarget",
    "ExcludedFamily",
    "Feasibility",
    "FeasibilityChecker",
    "IsoCube",
    "JointCoverage",
    "MotionChecker",
    "MoveCheck",
    "Observability",
    "Plan",
    "PlannedPose",
    "UnsafeMove",
    "builtin_cells",
    "cell_design_space",
    "cpa_sweeps",
    "default_link_radii",
    "draw_candidates",
    "excluded_families",
    "identification_jacobian",
    "insert_via_points",
    "iso_cube",
    "joint_coverage",
    "link_frames",
    "load_cell",
    "model_spec",
    "move_times",
    "observability_indices",
    "one_revolution",
    "order_poses",
    "plan_campaign",
    "pydantic_config_error",
    "read_program_joints",
    "segment_box_distance",
    "segment_distance",
    "solve_ik",
    "split_legs",
    "targets_outside",
    "winding_ranges",
    "working_ranges",
]
