"""TARGETS.csv (program targets to compensate) and JOINTS.csv (compensated commands).

TARGETS.csv, a header row, comma separated (``;`` with decimal commas is accepted too)::

    [target_id,]x,y,z,q1,...,qN[,w,p,r]

``x, y, z``
    target position of the reflector/TCP in the tracker frame, mm;
``q1..qN``
    seed joints, deg: the program's joint values for the target. They select the robot
    configuration and, without orientation columns, the orientation to keep;
``w, p, r``
    optional flange orientation in the tracker frame, deg, FANUC convention
    ``R = Rz(r) Ry(p) Rx(w)`` (all three or none);
``target_id``
    optional label.

Other columns are ignored. JOINTS.csv has ``q1..qN`` (deg, 9 decimals), ``status`` and
``model_residual_mm``, one row per target in the same order; the joint cells of a target
whose status is not ``ok`` are left empty so that they cannot be executed by mistake.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

# The one CSV table reader and its column and number checks are _core's.
from robocal._core.files import atomic_write_text
from robocal._core.measurements import joint_columns, numeric_columns, read_table, row_ids
from robocal.compensation._solve import CompensationResult
from robocal.errors import DataError
from robocal.kinematics import matrix_to_wpr, wpr_to_matrix

Array = NDArray[np.float64]
ORIENTATION_COLUMNS = ("w", "p", "r")


@dataclass(frozen=True)
class TargetSet:
    """Program targets in SI.

    ``p`` (n, 3) m tracker frame; ``q_seed`` (n, dof) rad; ``R`` (n, 3, 3) flange
    orientations in the tracker frame or None (position-only); ``labels`` n strings.
    """

    p: Array
    q_seed: Array
    R: Array | None = None
    labels: tuple[str, ...] = field(default=())
    #: the file's id column (``target_id`` or ``pose_id``), "" when it had none
    id_column: str = ""

    def __post_init__(self) -> None:
        p = np.atleast_2d(np.asarray(self.p, dtype=float))
        q = np.atleast_2d(np.asarray(self.q_seed, dtype=float))
        if p.shape[1] != 3 or q.shape[0] != p.shape[0]:
            raise DataError(f"targets {p.shape} and seeds {q.shape} do not match (n, 3)/(n, dof)")
        object.__setattr__(self, "p", p)
        object.__setattr__(self, "q_seed", q)
        if self.R is not None:
            R = np.asarray(self.R, dtype=float)
            if R.shape != (p.shape[0], 3, 3):
                raise DataError(f"orientations have shape {R.shape}, expected ({p.shape[0]}, 3, 3)")
            object.__setattr__(self, "R", R)
        object.__setattr__(self, "labels", row_ids(self.labels, p.shape[0], "T", "labels",
                                                   "targets"))

    def __len__(self) -> int:
        return int(self.p.shape[0])

    @property
    def dof(self) -> int:
        """Number of joints of the seeds."""
        return int(self.q_seed.shape[1])

    def to_csv_text(self) -> str:
        """Render as TARGETS.csv text (mm, deg; full float precision)."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        head = [self.id_column or "target_id", "x", "y", "z",
                *(f"q{i + 1}" for i in range(self.dof))]
        if self.R is not None:
            head += list(ORIENTATION_COLUMNS)
        w.writerow(head)
        pm = self.p * 1e3
        qd = np.degrees(self.q_seed)
        for i in range(len(self)):
            row = [self.labels[i], *(repr(float(v)) for v in pm[i]),
                   *(repr(float(v)) for v in qd[i])]
            if self.R is not None:
                row += [repr(math.degrees(a)) for a in matrix_to_wpr(self.R[i])]
            w.writerow(row)
        return buf.getvalue()

    def write_csv(self, path: str | Path) -> None:
        """Write TARGETS.csv atomically."""
        atomic_write_text(path, self.to_csv_text())


def read_targets_csv(path: str | Path, *, dof: int | None = None) -> TargetSet:
    """Read TARGETS.csv; raise :class:`DataError` naming the file, column and row.

    Parameters
    ----------
    path
        The file.
    dof
        Expected number of joint columns (the model's robot); None accepts any.
    """
    src = str(path)
    header, rows = read_table(path)
    for c in ("x", "y", "z"):
        if c not in header:
            raise DataError("required column is missing (x, y, z in mm)", source=src, key=c)
    qcols = joint_columns(header, src, dof)
    p = numeric_columns(rows, header, ["x", "y", "z"], src) * 1e-3
    q = numeric_columns(rows, header, qcols, src) * (math.pi / 180.0)
    present = [c for c in ORIENTATION_COLUMNS if c in header]
    R = None
    if present:
        if len(present) != 3:
            missing = next(c for c in ORIENTATION_COLUMNS if c not in present)
            raise DataError("orientation needs all of w, p, r (deg) or none", source=src,
                            key=missing)
        wpr = np.radians(numeric_columns(rows, header, list(ORIENTATION_COLUMNS), src))
        R = np.stack([wpr_to_matrix(*row) for row in wpr])
    labels: tuple[str, ...] = ()
    id_column = next((c for c in ("target_id", "pose_id") if c in header), "")
    if id_column:
        k = header.index(id_column)
        labels = tuple(r[k].strip() for r in rows)
    return TargetSet(p=p, q_seed=q, R=R, labels=labels, id_column=id_column)


def compensated_joints_csv_text(result: CompensationResult,
                                targets: TargetSet | None = None) -> str:
    """Render a compensation result as JOINTS.csv text; the targets' id column (``pose_id``
    or ``target_id``), when their file had one, comes first."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    dof = result.q.shape[1]
    ids = targets.labels if targets is not None and targets.id_column else ()
    if ids and len(ids) != len(result):
        raise DataError("targets and compensation result differ in length")
    head = [targets.id_column] if ids and targets is not None else []
    w.writerow([*head, *(f"q{i + 1}" for i in range(dof)), "status", "model_residual_mm"])
    qd = np.degrees(result.q)
    for i in range(len(result)):
        ok = result.status[i] == "ok"
        cells = [f"{v:.9f}" for v in qd[i]] if ok else [""] * dof
        w.writerow([*([ids[i]] if ids else []), *cells, str(result.status[i]),
                    f"{result.residual_m[i] * 1e3:.6f}"])
    return buf.getvalue()


def write_compensated_joints_csv(path: str | Path, result: CompensationResult,
                                 targets: TargetSet | None = None) -> None:
    """Write JOINTS.csv atomically (temporary file, then rename)."""
    atomic_write_text(path, compensated_joints_csv_text(result, targets))


