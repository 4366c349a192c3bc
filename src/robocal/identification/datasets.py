"""Loaders for public robot-accuracy data sets.

Only the Fraunhofer IPA UR10 / Leica laser-tracker data set is supported (GitHub
``christianlandgraf/ipa-robot-accuracy``; see ``shared/datasets/ipa-ur10-lasertracker``).
Its CSV files use ``;`` as separator and ``,`` as decimal mark; joint values are in rad (UR
order and zero convention, not wrapped), measured T-Mac positions in mm in the tracker frame,
optional tracker standard deviations in mm; on request the T-Mac orientation (``rx, ry, rz``
deg, intrinsic x-y-z as the upstream loader reads it) and its standard deviations.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from robocal._core.files import read_text
from robocal._core.measurements import MeasurementSet, numeric_columns, parse_table
from robocal.errors import DataError

IPA_JOINT_COLUMNS = (
    "shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
    "wrist_1_joint", "wrist_2_joint", "wrist_3_joint",
)
IPA_POINT_COLUMNS = ("measurement_x", "measurement_y", "measurement_z")
IPA_STD_COLUMNS = ("measurement_std_x", "measurement_std_y", "measurement_std_z")
IPA_ROT_COLUMNS = ("measurement_rx", "measurement_ry", "measurement_rz")
IPA_ROT_STD_COLUMNS = ("measurement_std_rx", "measurement_std_ry", "measurement_std_rz")
IPA_SERIES_FILES = {
    "A": "Series_A/measurements_grid.csv",
    "B": "Series_B/measurements_joint_configurations.csv",
    "C": "Series_C/measurements_random_poses.csv",
    "D": "Series_D/measurements_iso_cubes.csv",
}


def _resolve(path: str | Path) -> tuple[Path, str]:
    """Return the CSV file and a pose-id prefix for a series directory or file."""
    p = Path(path)
    if p.is_dir():
        found = sorted(p.glob("measurements_*.csv"))
        if len(found) != 1:
            raise DataError("expected exactly one measurements_*.csv in the directory",
                            source=str(p))
        p = found[0]
    folder = p.parent.name
    prefix = folder[len("Series_"):] if folder.startswith("Series_") else "R"
    return p, prefix


def parse_ipa_csv(text: str, *, source: str = "<ipa>", with_sigma: bool = False,
                  prefix: str = "R", with_orientation: bool = False) -> MeasurementSet:
    """Parse the text of one IPA measurement file.

    Parameters
    ----------
    text
        File content: ``;``-separated, decimal comma, one header row.
    source
        Name used in error messages.
    with_sigma
        Use the ``measurement_std_x/y/z`` columns (mm) as per-axis standard deviations when
        present. Off by default: the residuals of a robot model are far above the tracker's
        own scatter, so per-point tracker weights mostly add noise to the weighting.
    prefix
        Pose ids are ``f"{prefix}{row:05d}"`` with ``row`` the 0-based data row.
    with_orientation
        Also read the T-Mac orientation ``measurement_rx/ry/rz`` (deg, ``R = Rx Ry Rz``) and,
        when present, its standard deviations ``measurement_std_rx/ry/rz`` (deg).

    Returns
    -------
    MeasurementSet
        ``q`` (n, 6) rad, ``p`` (n, 3) m, ``sigma`` (n, 3) m or None.

    Raises
    ------
    DataError
        Missing columns, short rows, or cells that are not finite numbers (naming the row
        and column).
    """
    header, body = parse_table(text, source, delimiter=";")
    for col in (*IPA_JOINT_COLUMNS, *IPA_POINT_COLUMNS):
        if col not in header:
            raise DataError("required column is missing", source=source, key=col)
    cols = list(IPA_JOINT_COLUMNS) + list(IPA_POINT_COLUMNS)
    use_std = with_sigma and all(c in header for c in IPA_STD_COLUMNS)
    if use_std:
        cols += list(IPA_STD_COLUMNS)
    out = numeric_columns(body, header, cols, source)
    q = out[:, :6]
    p = out[:, 6:9] * 1e-3
    sigma = None
    if use_std:
        sigma = out[:, 9:12] * 1e-3
        if np.any(sigma <= 0):
            r = int(np.argwhere(sigma <= 0)[0, 0])
            raise DataError(f"row {r + 2}: standard deviations must be positive", source=source,
                            key=IPA_STD_COLUMNS[int(np.argwhere(sigma[r] <= 0)[0, 0])])
    ids = tuple(f"{prefix}{i:05d}" for i in range(len(body)))
    rot = rot_sigma = None
    if with_orientation:
        for col in IPA_ROT_COLUMNS:
            if col not in header:
                raise DataError("required column is missing", source=source, key=col)
        rot = np.radians(numeric_columns(body, header, list(IPA_ROT_COLUMNS), source))
        if all(c in header for c in IPA_ROT_STD_COLUMNS):
            rot_sigma = np.radians(numeric_columns(body, header, list(IPA_ROT_STD_COLUMNS),
                                                   source))
            if np.any(rot_sigma <= 0):
                r = int(np.argwhere(rot_sigma <= 0)[0, 0])
                raise DataError(f"row {r + 2}: standard deviations must be positive",
                                source=source, key=IPA_ROT_STD_COLUMNS[0])
    return MeasurementSet(q=q, p=p, sigma=sigma, pose_id=ids, rot=rot, rot_sigma=rot_sigma)


def load_ipa_series(path: str | Path, *, with_sigma: bool = False,
                    max_poses: int | None = None, seed: int = 0,
                    with_orientation: bool = False) -> MeasurementSet:
    """Load one series of the IPA UR10 data set.

    Parameters
    ----------
    path
        A ``Series_X`` directory or its ``measurements_*.csv`` file. Pose ids are
        ``X00000, X00001, ...`` (X from the directory name, row order of the file).
    with_sigma
        See :func:`parse_ipa_csv`.
    max_poses
        If given, return a random subset of at most this many poses (file order kept).
    seed
        Seed of that subset.
    with_orientation
        See :func:`parse_ipa_csv`.

    Returns
    -------
    MeasurementSet
        Joint values (n, 6) rad for the ``ur10`` robot and T-Mac positions (n, 3) m.
    """
    file, prefix = _resolve(path)
    data = parse_ipa_csv(read_text(file, error=DataError), source=str(file),
                         with_sigma=with_sigma, prefix=prefix, with_orientation=with_orientation)
    if max_poses is not None and len(data) > max_poses:
        rng = np.random.default_rng(seed)
        data = data.subset(np.sort(rng.choice(len(data), size=max_poses, replace=False)))
    return data


def ipa_series_path(root: str | Path, series: str) -> Path:
    """Path of series ``A``-``D`` under the data-set root directory."""
    try:
        return Path(root) / IPA_SERIES_FILES[series.upper()]
    except KeyError as err:
        raise DataError(f"unknown series {series!r} (A, B, C or D)") from err
