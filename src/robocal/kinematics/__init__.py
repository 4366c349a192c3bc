"""Kinematics: robot descriptions, joint-dependent error model, FK, Jacobians (numpy only)."""

from robocal._core.robot_names import builtin_robots
from robocal.kinematics._basis import evaluate_basis, gravity_torques, spline_weights
from robocal.kinematics._calibrated import MODEL_FORMAT, CalibratedModel
from robocal.kinematics._load import load_robot
from robocal.kinematics._model import ChainState, KinematicModel
from robocal.kinematics._robot import (
    Joint,
    RobotDescription,
    default_link_radii,
    link_radii,
    matrix_to_rpy,
    robot_to_toml,
    rpy_to_matrix,
)
from robocal.kinematics._spec import (
    BASE_NAMES,
    COMPONENTS,
    FAMILIES,
    TOOL_NAMES,
    ErrorModelSpec,
    ParameterLayout,
    Term,
)
from robocal.kinematics._transforms import (
    euler_xyz_to_matrix,
    kabsch,
    matrix_to_euler_xyz,
    matrix_to_rotvec,
    matrix_to_wpr,
    rigid_fit,
    rotvec_to_matrix,
    wpr_to_matrix,
)
from robocal.kinematics._urdf import (
    calibrated_to_urdf,
    constant_part,
    load_urdf,
    robot_to_urdf,
    urdf_to_robot,
)

__all__ = [
    "BASE_NAMES",
    "COMPONENTS",
    "FAMILIES",
    "MODEL_FORMAT",
    "TOOL_NAMES",
    "CalibratedModel",
    "ChainState",
    "ErrorModelSpec",
    "Joint",
    "KinematicModel",
    "ParameterLayout",
    "RobotDescription",
    "Term",
    "builtin_robots",
    "calibrated_to_urdf",
    "constant_part",
    "default_link_radii",
    "euler_xyz_to_matrix",
    "evaluate_basis",
    "gravity_torques",
    "kabsch",
    "link_radii",
    "load_robot",
    "load_urdf",
    "matrix_to_euler_xyz",
    "matrix_to_rotvec",
    "matrix_to_rpy",
    "matrix_to_wpr",
    "rigid_fit",
    "robot_to_toml",
    "robot_to_urdf",
    "rotvec_to_matrix",
    "rpy_to_matrix",
    "spline_weights",
    "urdf_to_robot",
    "wpr_to_matrix",
]
