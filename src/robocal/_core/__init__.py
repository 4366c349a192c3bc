"""Value types shared by every layer (no device I/O)."""

from robocal._core.measurements import (
    MeasurementSet,
    read_joints_csv,
    write_joints_csv,
    write_points_csv,
)

__all__ = ["MeasurementSet", "read_joints_csv", "write_joints_csv", "write_points_csv"]
