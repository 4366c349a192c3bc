"""A calibrated model: robot, error-model structure, parameters, uncertainty; and its JSON file.

MODEL.json (``format = "robocal.model/1"``) is self-describing: the whole robot description,
the error-model terms, every parameter with its unit and standard deviation (mm, deg; gravity
compliance in deg/(N m)), the tracker <- base reference, the joint range the data covered,
an optional low-order fallback used outside that range, and free-form ``metrics``/``fit``/
``data`` sections written by identification.

``model_id`` is the start of a SHA-256 over every section that changes predictions or limits
(:data:`robocal.kinematics._integrity.HASHED`, the robot description included); the
``integrity`` record holds the whole digest and, where the daemon has a site secret, an
HMAC-SHA256 with it. Loading checks both, and that the robot description is physically the
nominal robot (:func:`robocal.kinematics._integrity.check_robot`).
"""

from __future__ import annotations

import base64
import binascii
import datetime as _dt
import json
import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.files import atomic_write_text, json_default
from robocal._core.schema import fail, key, list_of, load
from robocal.errors import ConfigError
from robocal.kinematics._integrity import (
    COVERS,
    HASHED,
    SCHEME,
    builtin_nominal,
    check_robot,
    check_seal,
    digests,
)
from robocal.kinematics._model import KinematicModel
from robocal.kinematics._robot import RobotDescription
from robocal.kinematics._spec import ErrorModelSpec

Array = NDArray[np.float64]
MODEL_FORMAT = "robocal.model/1"

_TO_FILE = {"m": (1e3, "mm"), "rad": (180.0 / math.pi, "deg"),
            "rad/(N m)": (180.0 / math.pi, "deg/(N m)")}


@dataclass
class CalibratedModel:
    """An identified model ready for prediction and compensation.

    ``params`` (P,) SI; ``covariance`` (P, P) SI or None; ``coverage`` (dof, 2) rad: joint range
    the calibration data covered. Outside it, poses are predicted by ``fallback`` (a low-order
    model fitted on the same data) when one is given, so that maps never extrapolate.
    """

    model: KinematicModel
    params: Array
    covariance: Array | None = None
    coverage: Array | None = None
    fallback: CalibratedModel | None = None
    model_id: str = ""
    kind: str = "custom"
    metrics: dict[str, Any] = field(default_factory=dict)
    fit: dict[str, Any] = field(default_factory=dict)
    data: dict[str, Any] = field(default_factory=dict)
    created: str = ""
    # the hashed sections exactly as a loaded file held them, with a fingerprint of the
    # values they were read into (unit conversions do not round-trip bit for bit)
    _raw: tuple[tuple[Any, ...], dict[str, Any]] | None = field(default=None, repr=False,
                                                                compare=False)
    # the hash scheme of the file a model was read from: its id is recomputed, and the model
    # written again, under that scheme (an earlier one stays readable as it was sealed)
    _scheme: str = field(default=SCHEME, repr=False, compare=False)
    # the covariance in file form and the covariance it encodes: the id is computed several
    # times while a fit is finished, and a map model's covariance (700^2) takes 12 ms to pack
    _cov_file: tuple[bytes, dict[str, Any]] | None = field(default=None, repr=False,
                                                           compare=False)

    def __post_init__(self) -> None:
        self.params = np.asarray(self.params, dtype=float)
        if not self.model_id:
            self.model_id = self.compute_id()
        if not self.created:
            self.created = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")

    @property
    def robot(self) -> RobotDescription:
        """The robot description."""
        return self.model.robot

    @property
    def sigma(self) -> Array | None:
        """Parameter standard deviations (P,), SI, or None."""
        if self.covariance is None:
            return None
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def compute_id(self) -> str:
        """Short content hash (16 hex) of every section that changes predictions or limits.

        Hashes the sections as MODEL.json holds them (a loaded model keeps the values it read),
        so the id of a loaded file is recomputed bit for bit and an edited file is recognised.
        """
        return digests({**self._sections(), "fit": self.fit}, scheme=self.scheme)[0][:16]

    @property
    def scheme(self) -> str:
        """The hash scheme of this model's id and seal: the one of the file it was read from,
        unless that one does not cover a thermal term the model now has."""
        if "fit.thermal" in COVERS[self._scheme] or not self.fit.get("thermal"):
            return self._scheme
        return SCHEME

    def _fingerprint(self) -> tuple[Any, ...]:
        cov = None if self.covariance is None else self.covariance.tobytes()
        cover = None if self.coverage is None else self.coverage.tobytes()
        return (id(self.model), self.params.tobytes(), cov, cover, id(self.fallback))

    def _sections(self) -> dict[str, Any]:
        """The hashed sections in file form (mm, deg)."""
        if self._raw is not None and self._raw[0] == self._fingerprint():
            return dict(self._raw[1])
        sig = self.sigma
        params = []
        for k, (name, unit) in enumerate(zip(self.model.names, self.model.layout.units,
                                             strict=True)):
            f, u = _TO_FILE[unit]
            params.append({"name": name, "value": float(self.params[k] * f), "unit": u,
                           "sigma": None if sig is None else float(sig[k] * f)})
        T = self.model.T_ref.copy()
        T[:3, 3] *= 1e3
        cov = None
        if self.covariance is not None:
            key = self.covariance.tobytes() + repr(self.model.layout.units).encode()
            if self._cov_file is None or self._cov_file[0] != key:
                scale = np.array([_TO_FILE[u][0] for u in self.model.layout.units])
                self._cov_file = (key, _encode_covariance(self.covariance
                                                          * np.outer(scale, scale)))
            cov = self._cov_file[1]
        out = {
            "format": MODEL_FORMAT,
            "robot": self.robot.to_dict(),
            "error_model": self.model.spec.to_dict(),
            "T_tracker_base_ref_mm": T.tolist(),
            "parameters": params,
            "coverage_deg": None if self.coverage is None else np.degrees(self.coverage).tolist(),
            "covariance": cov,
            "fallback": None if self.fallback is None else self.fallback.to_dict(),
        }
        # as the file will hold them: numpy scalars become plain numbers
        return dict(json.loads(json.dumps(out, default=json_default)))

    def inside_coverage(self, q: Array) -> NDArray[np.bool_]:
        """Per pose: are all joints inside the covered range?"""
        q = np.atleast_2d(q)
        if self.coverage is None:
            return np.ones(q.shape[0], dtype=bool)
        return np.all((q >= self.coverage[:, 0]) & (q <= self.coverage[:, 1]), axis=1)

    def predict(self, q: Array) -> Array:
        """Predicted reflector positions (n, 3) m, tracker frame, for joint values (n, dof) rad."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        p = self.model.positions(q, self.params)
        if self.fallback is not None:
            out = ~self.inside_coverage(q)
            if out.any():
                p[out] = self.fallback.predict(q[out])
        return p

    def prediction_sigma(self, q: Array) -> Array:
        """1-sigma uncertainty (n, 3) m of the predicted position from the parameter covariance."""
        if self.covariance is None:
            raise ConfigError("model has no parameter covariance")
        _, J = self.model.jacobian(np.atleast_2d(q), self.params)
        C = np.einsum("nip,pq,niq->ni", J, self.covariance, J)
        return np.sqrt(np.clip(C, 0.0, None))

    # -- files ----------------------------------------------------------------------------
    def to_dict(self, *, secret: bytes | None = None) -> dict[str, Any]:
        """JSON-ready dict (mm, deg); ``secret`` (the site secret) adds an HMAC-SHA256 of the
        hashed sections to the ``integrity`` record."""
        sections = self._sections()
        scheme = self.scheme
        sha, mac = digests({**sections, "fit": self.fit}, secret, scheme)
        out: dict[str, Any] = {
            "format": MODEL_FORMAT,
            "model_id": self.model_id,
            "kind": self.kind,
            "created": self.created,
            **{k: v for k, v in sections.items() if k != "format"},
            "metrics": self.metrics,
            "fit": self.fit,
            "data": self.data,
            "integrity": {"scheme": scheme, "covers": list(COVERS[scheme]), "sha256": sha,
                          **({} if mac is None else {"hmac_sha256": mac})},
        }
        return out

    def save(self, path: str | Path, *, secret: bytes | None = None) -> None:
        """Write MODEL.json atomically (signed with ``secret``, the site secret, when given)."""
        atomic_write_text(path, json.dumps(self.to_dict(secret=secret), indent=1,
                                           default=json_default))

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str = "<model>", verify: bool = True,
                  secret: bytes | None = None, nominal: RobotDescription | None = None
                  ) -> CalibratedModel:
        """Inverse of :meth:`to_dict`; raise :class:`ConfigError` naming the bad key.

        With ``verify`` (the default) the content must match its ``model_id`` and
        ``integrity`` record (an edited file is refused; with ``secret``, the site secret, the
        file must also carry this site's HMAC), every number must be finite and physically
        plausible (:data:`BOUNDS`, :data:`PARAMETER_BOUNDS`), and the robot description must
        be the ``nominal`` one (default: the built-in robot it names, if any) within
        tolerance; any malformed part gives one :class:`ConfigError`.
        """
        try:
            return cls._from_dict(d, source=source, verify=verify, secret=secret, nominal=nominal)
        except ConfigError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError, IndexError,
                RecursionError) as err:
            raise ConfigError(f"malformed model file: {type(err).__name__}: {err}",
                              source=source) from err

    @classmethod
    def _from_dict(cls, d: dict[str, Any], *, source: str, verify: bool,
                   secret: bytes | None = None, nominal: RobotDescription | None = None
                   ) -> CalibratedModel:
        if not isinstance(d, dict):
            raise ConfigError("model file must hold a JSON object", source=source)
        if d.get("format") != MODEL_FORMAT:
            raise ConfigError(f"unsupported format {d.get('format')!r} (expected {MODEL_FORMAT})",
                              source=source, key="format")
        f = load(_ModelFile, d, source)
        robot = RobotDescription.from_dict(f.robot, source=f"{source}#robot")
        if verify:
            check_robot(robot, nominal if nominal is not None else builtin_nominal(robot),
                        source)
        T = f.T_tracker_base_ref_mm.copy()
        if verify:
            _check_transform(T, source)
        T[:3, 3] *= 1e-3
        model = KinematicModel(robot, _error_model(f.error_model, source), T)
        x = _parameters(model, f.parameters, source, verify)
        cov = None
        if f.covariance is not None:
            scale = np.array([_TO_FILE[u][0] for u in model.layout.units])
            cov = _decode_covariance(f.covariance, model.size, source) / np.outer(scale, scale)
            if not np.all(np.isfinite(cov)):
                raise ConfigError("covariance must be finite", source=source, key="covariance")
        cover = None
        if f.coverage_deg is not None:
            cover = np.radians(_coverage(f.coverage_deg, robot.dof, source))
        # the parent's hash (and HMAC) covers the fallback section whole
        fb = None if not f.fallback else cls.from_dict(
            f.fallback, source=f"{source}#fallback", verify=verify, nominal=nominal)
        out = cls(model=model, params=x, covariance=cov, coverage=cover, fallback=fb,
                  model_id=str(f.model_id), kind=str(f.kind), metrics=f.metrics, fit=f.fit,
                  data=f.data, created=str(f.created))
        if verify:  # last, so that a malformed or implausible part is named first
            check_seal(d, source, secret)
        out._raw = (out._fingerprint(), {k: d.get(k) for k in HASHED})
        seal = d.get("integrity")
        if isinstance(seal, dict) and seal.get("scheme") in COVERS:
            out._scheme = str(seal["scheme"])
        return out

    @classmethod
    def load(cls, path: str | Path, *, verify: bool = True, secret: bytes | None = None,
             nominal: RobotDescription | None = None) -> CalibratedModel:
        """Read MODEL.json; raise :class:`ConfigError` naming the file and problem."""
        src = str(path)
        try:
            d = json.loads(Path(path).read_text())
        except FileNotFoundError as err:
            raise ConfigError("file not found", source=src) from err
        except IsADirectoryError as err:
            raise ConfigError("is a directory, not a model file", source=src) from err
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"cannot read: {err}", source=src) from err
        except json.JSONDecodeError as err:
            raise ConfigError(f"not valid JSON: {err}", source=src) from err
        except (RecursionError, ValueError) as err:  # nested too deeply; huge integers
            raise ConfigError(f"not valid JSON: {type(err).__name__}", source=src) from err
        return cls.from_dict(d, source=src, verify=verify, secret=secret, nominal=nominal)


#: Largest magnitude a MODEL.json number may have, by file unit: 100 m for lengths (the
#: tracker <- base distance included), ten turns for angles, 10 deg/(N m) for compliance.
#: Anything larger is a damaged or hand-edited file, not a robot.
BOUNDS: dict[str, float] = {"mm": 1e5, "deg": 3600.0, "deg/(N m)": 10.0}

#: Tighter bounds by parameter group and unit. The base terms correct the tracker <- base
#: reference (itself bounded by :data:`TRACKER_RANGE_MM`), so they are small; no rotation
#: needs more than half a turn.
PARAMETER_BOUNDS: dict[tuple[str, str], float] = {("base", "mm"): 1000.0,
                                                  ("base", "deg"): 180.0,
                                                  ("tool", "mm"): 2000.0}

#: Farthest a tracker measures (the largest laser trackers reach 80 m in radius): the
#: tracker <- base reference cannot be farther.
TRACKER_RANGE_MM = 80_000.0


def _matrix4(v: Any) -> Array:
    try:
        return np.array(v, dtype=float).reshape(4, 4)
    except (TypeError, ValueError) as err:
        fail(f"not a 4x4 matrix: {err}")


def _entries(v: Any) -> list[tuple[str, float, str]]:
    if not isinstance(v, list):
        fail("must be a list of parameter entries")
    checked: list[tuple[str, float, str]] = list_of(_entry)(v)
    return checked


def _entry(v: Any) -> tuple[str, float, str]:
    try:
        name, value, unit = v["name"], float(v["value"]), v["unit"]
        hash(name)
    except (KeyError, TypeError, ValueError) as err:
        fail(f"malformed parameter entry: {err}")
    return name, value, unit


def _json_object(v: Any) -> dict[str, Any]:
    if not isinstance(v or {}, dict):
        fail("must be a JSON object")
    return dict(v or {})


@dataclass(frozen=True, kw_only=True)
class _ModelFile:
    """MODEL.json as written by :meth:`CalibratedModel.to_dict`. The robot and error-model
    sections are checked by their own parsers, the seal by :func:`check_seal`; a new section
    is one more key here (and in :data:`HASHED` when it changes predictions or limits)."""

    format: str = key()
    model_id: Any = key(None, "")
    kind: Any = key(None, "custom")
    created: Any = key(None, "")
    robot: Any = key()
    error_model: Any = key()
    T_tracker_base_ref_mm: Array = key(_matrix4)
    parameters: list[tuple[str, float, str]] = key(_entries)
    coverage_deg: Any = key(None, None)
    covariance: Any = key(None, None)
    fallback: Any = key(None, None)
    metrics: dict[str, Any] = key(_json_object, factory=dict)
    fit: dict[str, Any] = key(_json_object, factory=dict)
    data: dict[str, Any] = key(_json_object, factory=dict)
    integrity: Any = key(None, None)


def _error_model(value: Any, source: str) -> ErrorModelSpec:
    """The ``error_model`` section; any problem is one ConfigError on that key."""
    try:
        return ErrorModelSpec.from_dict(value)
    except ConfigError as err:
        raise ConfigError(str(err), source=source, key="error_model") from err
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as err:
        raise ConfigError(f"malformed error model: {type(err).__name__}: {err}",
                          source=source, key="error_model") from err


def _parameters(model: KinematicModel, entries: list[tuple[str, float, str]], source: str,
                verify: bool) -> Array:
    """Parameter vector (P,) SI from the file entries (file units): each parameter present
    once in its unit, finite; with ``verify`` within :data:`PARAMETER_BOUNDS`/:data:`BOUNDS`."""
    byname = {name: (v, u) for name, v, u in entries}
    x = np.empty(model.size)
    for k, (name, unit) in enumerate(zip(model.names, model.layout.units, strict=True)):
        if name not in byname:
            raise ConfigError("parameter missing", source=source, key=f"parameters.{name}")
        v, u = byname[name]
        f, fu = _TO_FILE[unit]
        if u != fu:
            raise ConfigError(f"unit {u!r}, expected {fu!r}", source=source,
                              key=f"parameters.{name}")
        x[k] = v / f
    if not np.all(np.isfinite(x)):
        raise ConfigError("parameters must be finite", source=source, key="parameters")
    if verify:
        for k, (name, unit) in enumerate(zip(model.names, model.layout.units, strict=True)):
            f, fu = _TO_FILE[unit]
            bound = PARAMETER_BOUNDS.get((name.split(".")[0], fu), BOUNDS[fu])
            if abs(x[k] * f) > bound:
                raise ConfigError(f"{x[k] * f:.6g} {fu} is not a plausible value (|v| <= "
                                  f"{bound:g} {fu})", source=source, key=f"parameters.{name}")
    return x


def _check_transform(T: Array, source: str) -> None:
    """A rigid transform (mm): finite, rotation orthonormal, last row 0 0 0 1, within 100 m."""
    key = "T_tracker_base_ref_mm"
    if not np.all(np.isfinite(T)):
        raise ConfigError("must be finite", source=source, key=key)
    R = T[:3, :3]
    if (not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9)
            or not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0):
        raise ConfigError("not a rigid transform (rotation not orthonormal or last row not "
                          "0 0 0 1)", source=source, key=key)
    if float(np.linalg.norm(T[:3, 3])) > TRACKER_RANGE_MM:
        raise ConfigError(f"translation beyond {TRACKER_RANGE_MM:g} mm (the farthest a "
                          "tracker measures)", source=source, key=key)


def _coverage(value: Any, dof: int, source: str) -> Array:
    """``coverage_deg``: (dof, 2) finite [low, high] pairs, low <= high, degrees."""
    try:
        c = np.array(value, dtype=float)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"not a list of [low, high] pairs: {err}", source=source,
                          key="coverage_deg") from err
    if c.shape != (dof, 2):
        raise ConfigError(f"shape {c.shape}, expected ({dof}, 2)", source=source,
                          key="coverage_deg")
    if not np.all(np.isfinite(c)) or np.any(np.abs(c) > BOUNDS["deg"]):
        raise ConfigError(f"values must be finite and within +-{BOUNDS['deg']:g} deg",
                          source=source, key="coverage_deg")
    if np.any(c[:, 0] > c[:, 1]):
        raise ConfigError("a low end is above its high end", source=source, key="coverage_deg")
    return c


def _encode_covariance(C: Array) -> dict[str, Any]:
    """Compact form of a covariance (file units): the block of estimated parameters only
    (the others are held and have zero variance), upper triangle, float32, zlib, base64.

    float32 keeps 7 significant digits, plenty for uncertainties, and a model with maps of
    hundreds of knots stays a few MB instead of tens.
    """
    idx = np.flatnonzero(np.diag(C) > 0)
    sub = C[np.ix_(idx, idx)]
    tri = sub[np.triu_indices(len(idx))].astype("<f4")
    return {"encoding": "upper-triangle float32-le zlib base64", "index": idx.tolist(),
            "data": base64.b64encode(zlib.compress(tri.tobytes(), 6)).decode("ascii")}


def _decode_covariance(d: Any, size: int, source: str) -> Array:
    try:
        idx = np.asarray(d["index"], dtype=int)
        tri = np.frombuffer(zlib.decompress(base64.b64decode(d["data"])), dtype="<f4")
        k = len(idx)
        if tri.size != k * (k + 1) // 2 or (k and (idx.min() < 0 or idx.max() >= size)):
            raise ValueError("size does not match the index")
        sub = np.zeros((k, k))
        iu = np.triu_indices(k)
        sub[iu] = tri
        sub = sub + np.triu(sub, 1).T
    except (KeyError, TypeError, ValueError, zlib.error, binascii.Error) as err:
        raise ConfigError(f"covariance block unreadable: {err}", source=source,
                          key="covariance") from err
    C = np.zeros((size, size))
    C[np.ix_(idx, idx)] = sub
    return C
