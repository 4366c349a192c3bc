"""Measurement sets and their CSV files.

CSV layout (a header row; comma separated; mm and degrees)::

    pose_id,q1,q2,...,qN,x,y,z[,sx,sy,sz][,rx,ry,rz[,srx,sry,srz]][,temp1,...,tempN]

``q1..qN`` are joint values (deg), ``x, y, z`` the reflector position in the tracker frame
(mm), ``sx, sy, sz`` optional per-point standard deviations (mm), ``pose_id`` optional.
``rx, ry, rz`` (deg, optional, 6-DoF probes): the probe orientation in the tracker frame as
intrinsic x-y-z Euler angles, ``R = Rx(rx) Ry(ry) Rz(rz)`` (Leica T-Mac's convention);
``srx, sry, srz`` their standard deviations (deg). ``temp1..tempN`` (°C, optional, all or
none): the joint temperatures at the measurement (ADR 0042). Other columns are ignored.
Inside robocal everything is SI (rad, m; temperatures stay °C).
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from robocal._core.files import atomic_write_text, read_text
from robocal.errors import DataError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MeasurementSet:
    """Joint values and measured reflector positions of n poses.

    ``q``: (n, dof) rad. ``p``: (n, 3) m, tracker frame. ``sigma``: (n, 3) m per-axis standard
    deviations or None. ``pose_id``: n labels. ``rot``: (n, 3) rad probe orientation
    (intrinsic x-y-z Euler angles, ``R = Rx Ry Rz``, tracker frame) or None; ``rot_sigma``:
    (n, 3) rad their standard deviations or None. ``temps``: (n, dof) joint temperatures, °C,
    or None.
    """

    q: Array
    p: Array
    sigma: Array | None = None
    pose_id: tuple[str, ...] = field(default=())
    rot: Array | None = None
    rot_sigma: Array | None = None
    temps: Array | None = None

    def __post_init__(self) -> None:
        q = np.atleast_2d(np.asarray(self.q, dtype=float))
        p = np.atleast_2d(np.asarray(self.p, dtype=float))
        if q.shape[0] != p.shape[0] or p.shape[1] != 3:
            raise DataError(f"q has {q.shape[0]} rows and p has shape {p.shape}; need (n, 3)")
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "p", p)
        if self.sigma is not None:
            s = np.atleast_2d(np.asarray(self.sigma, dtype=float))
            if s.shape != p.shape:
                raise DataError(f"sigma has shape {s.shape}, expected {p.shape}")
            object.__setattr__(self, "sigma", s)
        for name in ("rot", "rot_sigma"):
            v = getattr(self, name)
            if v is not None:
                v = np.atleast_2d(np.asarray(v, dtype=float))
                if v.shape != p.shape:
                    raise DataError(f"{name} has shape {v.shape}, expected {p.shape}")
                object.__setattr__(self, name, v)
        if self.temps is not None:
            t = np.atleast_2d(np.asarray(self.temps, dtype=float))
            if t.shape != q.shape:
                raise DataError(f"temps has shape {t.shape}, expected {q.shape}")
            if not np.all(np.isfinite(t)):
                raise DataError("temps must be finite")
            object.__setattr__(self, "temps", t)
        if self.rot_sigma is not None and self.rot is None:
            raise DataError("rot_sigma given without rot")
        object.__setattr__(self, "pose_id", row_ids(self.pose_id, len(q), "P", "pose_id",
                                                    "poses"))

    def __len__(self) -> int:
        return len(self.q)

    @property
    def dof(self) -> int:
        """Number of joints."""
        return int(self.q.shape[1])

    def subset(self, idx: Sequence[int] | NDArray[np.intp] | NDArray[np.bool_]) -> MeasurementSet:
        """Return the poses selected by an index array or boolean mask."""
        idx = np.asarray(idx)
        if idx.dtype == bool:
            idx = np.flatnonzero(idx)
        return MeasurementSet(
            q=self.q[idx], p=self.p[idx],
            sigma=None if self.sigma is None else self.sigma[idx],
            pose_id=tuple(self.pose_id[i] for i in idx),
            rot=None if self.rot is None else self.rot[idx],
            rot_sigma=None if self.rot_sigma is None else self.rot_sigma[idx],
            temps=None if self.temps is None else self.temps[idx],
        )

    def split(self, fraction: float, seed: int = 0) -> tuple[MeasurementSet, MeasurementSet]:
        """Random split into (first, rest) with ``fraction`` of the poses in the first."""
        rng = np.random.default_rng(seed)
        perm = rng.permutation(len(self))
        k = round(fraction * len(self))
        return self.subset(np.sort(perm[:k])), self.subset(np.sort(perm[k:]))

    def concat(self, other: MeasurementSet) -> MeasurementSet:
        """Append another set with the same joint count."""
        if self.sigma is None or other.sigma is None:
            sig = None
        else:
            sig = np.vstack([self.sigma, other.sigma])
        rot = rsig = None
        if self.rot is not None and other.rot is not None:
            rot = np.vstack([self.rot, other.rot])
            if self.rot_sigma is not None and other.rot_sigma is not None:
                rsig = np.vstack([self.rot_sigma, other.rot_sigma])
        temps = None
        if self.temps is not None and other.temps is not None:
            temps = np.vstack([self.temps, other.temps])
        return MeasurementSet(np.vstack([self.q, other.q]), np.vstack([self.p, other.p]), sig,
                              self.pose_id + other.pose_id, rot=rot, rot_sigma=rsig,
                              temps=temps)

    def without_orientation(self) -> MeasurementSet:
        """The same poses with positions only."""
        return MeasurementSet(self.q, self.p, self.sigma, self.pose_id, temps=self.temps)

    def digest(self, *, sigma: bool = True, orientation: bool = True) -> str:
        """SHA-256 (hex) of the numerical content: joint values, points, and the per-point
        sigmas (``sigma``) and probe orientations with their sigmas (``orientation``) where
        present. Each optional block is tagged, so a set without it (the digest of joints and
        points alone, as before these columns counted) never collides with one with it.
        """
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.q).tobytes())
        h.update(np.ascontiguousarray(self.p).tobytes())
        blocks = []
        if sigma:
            blocks.append((b"sigma", self.sigma))
        if orientation:
            blocks += [(b"rot", self.rot), (b"rot_sigma", self.rot_sigma)]
        blocks.append((b"temps", self.temps))
        for tag, v in blocks:
            if v is not None:
                h.update(b"\0" + tag + b"\0")
                h.update(np.ascontiguousarray(v, dtype=float).tobytes())
        return h.hexdigest()

    # -- files --------------------------------------------------------------------------------
    def to_csv_text(self) -> str:
        """Render as CSV text (mm, deg)."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        head = ["pose_id", *(f"q{i + 1}" for i in range(self.dof)), "x", "y", "z"]
        if self.sigma is not None:
            head += ["sx", "sy", "sz"]
        if self.rot is not None:
            head += ["rx", "ry", "rz"]
            if self.rot_sigma is not None:
                head += ["srx", "sry", "srz"]
        if self.temps is not None:
            head += [f"temp{i + 1}" for i in range(self.dof)]
        w.writerow(head)
        qd = np.degrees(self.q)
        pm = self.p * 1e3
        sm = None if self.sigma is None else self.sigma * 1e3
        for i in range(len(self)):
            row = [self.pose_id[i], *(f"{v:.9f}" for v in qd[i]), *(f"{v:.6f}" for v in pm[i])]
            if sm is not None:
                row += [f"{v:.6f}" for v in sm[i]]
            if self.rot is not None:
                row += [f"{v:.9f}" for v in np.degrees(self.rot[i])]
                if self.rot_sigma is not None:
                    row += [f"{v:.9f}" for v in np.degrees(self.rot_sigma[i])]
            if self.temps is not None:
                row += [f"{v:.6f}" for v in self.temps[i]]
            w.writerow(row)
        return buf.getvalue()

    def write_csv(self, path: str | Path) -> None:
        """Write atomically (temporary file, then rename)."""
        atomic_write_text(Path(path), self.to_csv_text())

    @classmethod
    def read_csv(cls, path: str | Path, *, dof: int | None = None) -> MeasurementSet:
        """Read a measurement CSV; raise :class:`DataError` naming the file, column and row."""
        src = str(path)
        header, rows = read_table(path)
        qcols = joint_columns(header, src, dof)
        for c in ("x", "y", "z"):
            if c not in header:
                raise DataError(f"required column is missing; {found_columns(header)}",
                                source=src, key=c)
        q = numeric_columns(rows, header, qcols, src) * (math.pi / 180.0)
        p = numeric_columns(rows, header, ["x", "y", "z"], src) * 1e-3
        sigma = None
        scols = [c for c in ("sx", "sy", "sz") if c in header]
        if scols:
            if len(scols) != 3:
                missing = sorted({"sx", "sy", "sz"} - set(scols))[0]
                raise DataError("sx, sy, sz must be given together", source=src, key=missing)
            sigma = numeric_columns(rows, header, ["sx", "sy", "sz"], src) * 1e-3
            if np.any(sigma <= 0):
                r = int(np.argwhere(sigma <= 0)[0, 0])
                raise DataError(f"row {r + 2}: standard deviations must be positive",
                                source=src, key="sx")
        ids: tuple[str, ...] = ()
        if "pose_id" in header:
            k = header.index("pose_id")
            ids = tuple(r[k].strip() for r in rows)
        rot, rsig = _orientation_columns(header, rows, src)
        return cls(q=q, p=p, sigma=sigma, pose_id=ids, rot=rot, rot_sigma=rsig,
                   temps=_temperature_columns(header, rows, src, len(qcols)))


def _temperature_columns(header: list[str], rows: list[list[str]], src: str, dof: int
                         ) -> Array | None:
    """Optional ``temp1..tempN`` joint temperatures (°C), all N or none."""
    cols = [f"temp{i + 1}" for i in range(dof)]
    have = [c for c in cols if c in header]
    if not have:
        return None
    if len(have) != dof:
        missing = next(c for c in cols if c not in header)
        raise DataError(f"temp1..temp{dof} must be given together", source=src, key=missing)
    return numeric_columns(rows, header, cols, src)


def _orientation_columns(header: list[str], rows: list[list[str]], src: str
                         ) -> tuple[Array | None, Array | None]:
    """Optional ``rx, ry, rz`` (deg) and ``srx, sry, srz`` (deg) columns, in rad."""
    out: list[Array | None] = []
    for cols in (("rx", "ry", "rz"), ("srx", "sry", "srz")):
        have = [c for c in cols if c in header]
        if not have:
            out.append(None)
            continue
        if len(have) != 3:
            missing = sorted(set(cols) - set(have))[0]
            raise DataError(f"{', '.join(cols)} must be given together", source=src,
                            key=missing)
        out.append(numeric_columns(rows, header, list(cols), src) * (math.pi / 180.0))
    rot, rsig = out
    if rsig is not None:
        if rot is None:
            raise DataError("srx, sry, srz need rx, ry, rz", source=src, key="rx")
        if np.any(rsig <= 0):
            r = int(np.argwhere(rsig <= 0)[0, 0])
            raise DataError(f"row {r + 2}: standard deviations must be positive",
                            source=src, key="srx")
    return rot, rsig


def row_ids(ids: Sequence[str], n: int, prefix: str, name: str, rows: str) -> tuple[str, ...]:
    """``ids`` of ``n`` rows, or ``prefix0000``, ``prefix0001``... when there are none; a
    count that differs is a :class:`DataError` naming ``name`` and what the ``rows`` are."""
    if not ids:
        return tuple(f"{prefix}{i:04d}" for i in range(n))
    if len(ids) != n:
        raise DataError(f"{name} length differs from the number of {rows}")
    return tuple(ids)


def read_table(path: str | Path) -> tuple[list[str], list[list[str]]]:
    """Read one of robocal's CSV files into a lower-case header and data rows (see
    :func:`parse_table`); a column named twice is a :class:`DataError`."""
    src = str(path)
    header, rows = parse_table(read_text(path, error=DataError, encoding="utf-8-sig"), src)
    seen: set[str] = set()
    for h in header:
        if h and h in seen:
            raise DataError("column appears twice", source=src, key=h)
        seen.add(h)
    return header, rows


def parse_table(text: str, src: str, *, delimiter: str | None = None
                ) -> tuple[list[str], list[list[str]]]:
    """Split CSV text into a stripped header and data rows (at least as long as the header).

    The delimiter is ``;`` or ``,``, whichever the header uses more, unless given or named by
    a leading ``sep=X`` line (as spreadsheet programs write); with ``;`` decimal commas in
    numbers are turned into points (other cells are kept as written, for error messages).
    Header names are case-insensitive (returned lower-case). Raises :class:`DataError`.
    """
    text = text.lstrip("\ufeff")
    first, _, rest = text.partition("\n")
    if first.strip().lower().startswith("sep=") and len(first.strip()) == 5:
        delimiter = delimiter or first.strip()[4]
        text = rest
        first = text.split("\n", 1)[0]
    # The header decides: European files separate with ';' and may use decimal commas.
    delim = delimiter or (";" if first.count(";") > first.count(",") else ",")
    reader = csv.reader(io.StringIO(text), delimiter=delim)
    try:
        rows = [r for r in reader if r and any(c.strip() for c in r)]
    except csv.Error as err:
        raise DataError(f"not a valid CSV file: {err}", source=src) from err
    if not rows:
        raise DataError("file is empty (a header row is required)", source=src)
    header = [h.strip().lower() for h in rows[0]]
    body = rows[1:]
    if delim == ";":  # European CSV: decimal comma
        body = [[_decimal_point(c) for c in r] for r in body]
    if not body:
        raise DataError("no data rows after the header", source=src)
    for i, r in enumerate(body):
        if len(r) < len(header):
            raise DataError(f"row {i + 2} has {len(r)} fields, the header has {len(header)}",
                            source=src)
    return header, body


def _decimal_point(cell: str) -> str:
    """``'1,5'`` -> ``'1.5'``; a cell that is no number either way stays as written."""
    if "," not in cell:
        return cell
    dotted = cell.replace(",", ".")
    try:
        float(dotted)
    except ValueError:
        return cell
    return dotted


def found_columns(header: Sequence[str]) -> str:
    """``'columns found: a, b, c'`` for error messages about a missing column."""
    return "columns found: " + (", ".join(h for h in header if h) or "none")


def joint_columns(header: list[str], src: str, dof: int | None) -> list[str]:
    """Names ``q1..qN`` present in ``header`` (checked against ``dof`` when given)."""
    present = []
    i = 1
    while f"q{i}" in header:
        present.append(f"q{i}")
        i += 1
    if not present:
        raise DataError(f"no joint columns (q1..qN) found; {found_columns(header)}",
                        source=src, key="q1")
    if dof is not None and len(present) != dof:
        key = f"q{len(present) + 1}" if len(present) < dof else f"q{len(present)}"
        raise DataError(f"found {len(present)} joint columns (q1..q{len(present)}), the robot "
                        f"has {dof} joints", source=src, key=key)
    return present


#: Largest plausible magnitude in a measurement or joint file, by unit: ten turns, and 100 m
#: (beyond any tracker's range). Larger values are typos or unit mix-ups that would only
#: surface later as overflow warnings and nonsense fits.
_MAX_ABS = {"deg": 3600.0, "mm": 1e5, "degC": 1000.0}


def _unit_of(column: str) -> str:
    if column in ("x", "y", "z", "sx", "sy", "sz"):
        return "mm"
    if column in ("rx", "ry", "rz", "srx", "sry", "srz") or (
            column[:1] == "q" and column[1:].isdigit()):
        return "deg"
    if column.startswith("temp") and column[4:].isdigit():
        return "degC"
    return ""


def numeric_columns(rows: list[list[str]], header: list[str], cols: Sequence[str],
                    src: str) -> Array:
    """The named columns as an (n, len(cols)) float array; a bad cell is quoted as written."""
    idx = [header.index(c) for c in cols]
    units = [_unit_of(c) for c in cols]
    bounds = [_MAX_ABS.get(u, math.inf) for u in units]
    out = np.empty((len(rows), len(cols)))
    for r, row in enumerate(rows):
        for k, i in enumerate(idx):
            cell = row[i].strip()
            try:
                v = float(cell)
            except ValueError:
                raise DataError(f"row {r + 2}: {cell!r} is not a number", source=src,
                                key=cols[k]) from None
            if not math.isfinite(v):
                raise DataError(f"row {r + 2}: value is {cell!r} (must be finite)", source=src,
                                key=cols[k])
            if abs(v) > bounds[k]:
                raise DataError(f"row {r + 2}: {cell!r} is not a plausible value (|v| <= "
                                f"{bounds[k]:g} {units[k]})", source=src, key=cols[k])
            out[r, k] = v
    return out


def read_joints_csv(path: str | Path, *, dof: int | None = None) -> Array:
    """Read ``q1..qN`` (deg) from a CSV; return (n, dof) rad."""
    header, rows = read_table(path)
    cols = joint_columns(header, str(path), dof)
    return numeric_columns(rows, header, cols, str(path)) * (math.pi / 180.0)


def write_joints_csv(path: str | Path, q: Array, extra: dict[str, Sequence[object]] | None = None
                     ) -> None:
    """Write joint values (n, dof) rad as ``q1..qN`` in degrees, plus optional extra columns."""
    q = np.atleast_2d(q)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    extra = extra or {}
    w.writerow([*(f"q{i + 1}" for i in range(q.shape[1])), *extra])
    qd = np.degrees(q)
    for i in range(q.shape[0]):
        w.writerow([*(f"{v:.9f}" for v in qd[i]), *(_fmt(col[i]) for col in extra.values())])
    atomic_write_text(Path(path), buf.getvalue())


def write_points_csv(path: str | Path, p: Array,
                     extra: Mapping[str, Sequence[object]] | None = None) -> None:
    """Write points (n, 3) m as ``x, y, z`` in mm, plus optional extra columns."""
    p = np.atleast_2d(p)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    extra = extra or {}
    w.writerow(["x", "y", "z", *extra])
    for i in range(p.shape[0]):
        w.writerow([*(f"{v * 1e3:.6f}" for v in p[i]), *(_fmt(col[i]) for col in extra.values())])
    atomic_write_text(Path(path), buf.getvalue())


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.6f}"
    return str(v)
