"""Driver API: small capability protocols, value types and the joint-target check.

A robot driver is whatever satisfies :class:`Connectable`, :class:`JointMover`,
:class:`JointReader` and :class:`Stoppable` (optionally :class:`CompensationSink`, and with it
:class:`CompensationSlots` and :class:`CompensationSnapshots`, and
:class:`ControllerCalibrationReadable` where the interface shows the controller's own
calibration, and :class:`JointTemperatureReader` where it shows the joints' temperatures);
a tracker driver satisfies
:class:`Connectable` and :class:`PointMeasurer`. Capabilities are checked
with ``isinstance`` (the protocols are ``runtime_checkable``) or all at once with
:func:`require`.

Units are SI inside robocal (metres, radians, seconds); drivers convert at their boundary.
Errors come from :mod:`robocal.errors`, split by phase:

=====================  ===========================================================
phase                  errors
=====================  ===========================================================
lookup / config        DriverNotFound, DriverImportError, ConfigError
connect                ConnectFailed (also for "not connected" and a lost link)
waiting                DriverTimeout
operation              MotionRejected, MotionStopped, LimitViolation, BeamLost,
                       Unstable, MeasurementError, VerificationMismatch
                       (all OperationError)
wire                   ProtocolError: FramingError, UnexpectedReply, TransportError,
                       TransportTimeout
=====================  ===========================================================
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

from robocal.errors import DriverError, LimitViolation

if TYPE_CHECKING:
    from robocal.compensation import CompensationTable
    from robocal.drivers._compensation import ControllerSnapshot

__all__ = [
    "CompensationSink",
    "CompensationSlots",
    "CompensationSnapshots",
    "Connectable",
    "ControllerCalibration",
    "ControllerCalibrationReadable",
    "JointMover",
    "JointReader",
    "JointReading",
    "JointTemperatureReader",
    "JointTemperatures",
    "PointMeasurer",
    "RobotDriver",
    "Stoppable",
    "TrackerDriver",
    "TrackerReading",
    "TrackerStatus",
    "calibration_fingerprint",
    "check_joint_target",
    "require",
]

TrackerStatus = Literal["ok", "beam-lost", "unstable", "warming-up"]


@dataclass(frozen=True, slots=True)
class JointReading:
    """Joint angles reported by the controller.

    Attributes
    ----------
    q_rad : tuple of float
        Actual joint angles, radians, length ``dof``.
    timestamp : float
        ``time.time()`` when the reading was taken, seconds.
    """

    q_rad: tuple[float, ...]
    timestamp: float


@dataclass(frozen=True, slots=True)
class TrackerReading:
    """One (averaged) tracker measurement of the reflector centre, tracker frame.

    Attributes
    ----------
    position_m : tuple of 3 float
        Reflector centre, metres.
    std_m : tuple of 3 float or None
        Standard uncertainty of ``position_m`` per axis, metres, if the tracker reports it.
    n : int
        Number of samples averaged.
    rms_m : float or None
        RMS distance of the samples from their mean, metres.
    timestamp : float
        Measurement time (``time.time()`` scale), seconds.
    status : {"ok", "beam-lost", "unstable", "warming-up"}
        Quality flag; drivers raise instead of returning anything but ``"ok"``.
    weather : mapping
        Environment at measurement: ``temp_c``, ``press_hpa``, ``hum_pct`` when known.
    point_id : str or None
        The caller's point identifier, echoed.
    cov_m2 : 3 x 3 tuple of float or None
        Covariance of ``position_m``, square metres, row-major, if the tracker reports it
        (its diagonal is ``std_m`` squared).
    """

    position_m: tuple[float, float, float]
    std_m: tuple[float, float, float] | None
    n: int
    rms_m: float | None
    timestamp: float
    status: TrackerStatus = "ok"
    weather: Mapping[str, float] = field(default_factory=dict)
    point_id: str | None = None
    cov_m2: tuple[tuple[float, float, float], ...] | None = None


@runtime_checkable
class Connectable(Protocol):
    """Explicit connection lifecycle; nothing happens in ``__init__``."""

    async def connect(self, *, timeout: float) -> None:
        """Connect and initialise the device; raise ConnectFailed or DriverTimeout."""
        ...

    async def close(self) -> None:
        """Release the device; idempotent, safe after a failed connect, never raises."""
        ...


@runtime_checkable
class JointMover(Protocol):
    """Joint-space motion to a target, waiting until the robot is in position."""

    @property
    def dof(self) -> int:
        """Number of joints."""
        ...

    @property
    def joint_limits_rad(self) -> tuple[tuple[float, float], ...]:
        """Configured ``(min, max)`` per joint, radians; targets outside are refused."""
        ...

    async def move_to(
        self, q_rad: Sequence[float], *, speed_pct: float, timeout: float
    ) -> JointReading:
        """Move to ``q_rad`` (radians), wait in position, return the actual joints.

        Raises LimitViolation (nothing sent), MotionRejected, DriverTimeout, ConnectFailed.
        """
        ...


@runtime_checkable
class Stoppable(Protocol):
    """Halting motion at once, wherever the robot is (ADR 0008).

    ``stop()`` is always allowed: idle or mid-move, after a motion fault, and (as a no-op)
    before ``connect`` or after ``close``. It is idempotent. It returns once the controller
    has confirmed the halt and is ready for the next ``move_to``; a ``move_to`` waiting on
    the halted motion raises MotionStopped. Raises ConnectFailed or DriverTimeout only when
    a connected device cannot be reached to confirm the halt.
    """

    async def stop(self) -> None:
        """Halt any motion now and leave the controller ready for the next move."""
        ...


@runtime_checkable
class JointReader(Protocol):
    """Reading of the actual joint angles."""

    async def read_joints(self) -> JointReading:
        """Return the actual joint angles (radians)."""
        ...


@dataclass(frozen=True, slots=True)
class JointTemperatures:
    """Joint (motor or gearbox) temperatures reported by the controller.

    Attributes
    ----------
    temps_c : tuple of float
        Temperature per joint, °C, length ``dof``.
    timestamp : float
        When they were read, seconds on the controller's clock (monotonic, any origin; a
        simulator's clock runs in simulated time): rates of change are taken on it.
    """

    temps_c: tuple[float, ...]
    timestamp: float


@runtime_checkable
class JointTemperatureReader(Protocol):
    """Reading the joints' temperatures (Universal Robots over RTDE, the mock robot; FANUC
    RMI, KUKA KVP and ABB RWS drivers do not read them)."""

    async def read_joint_temperatures(self) -> JointTemperatures:
        """Return the temperature of every joint now; raise ConnectFailed or DriverTimeout."""
        ...


@runtime_checkable
class PointMeasurer(Protocol):
    """Triggered point measurement of a reflector."""

    async def measure(
        self, *, samples: int, timeout: float, point_id: str | None = None
    ) -> TrackerReading:
        """Measure the reflector, averaging ``samples``; raise BeamLost, Unstable, DriverTimeout."""
        ...


@runtime_checkable
class CompensationSink(Protocol):
    """Storage of a compensation table on the controller, verified by reading it back."""

    async def write_compensation(self, table: CompensationTable) -> None:
        """Write ``table``, read it back and compare; raise VerificationMismatch on difference."""
        ...

    async def read_compensation(self) -> CompensationTable | None:
        """Return the table held by the controller, or None when there is none."""
        ...


@runtime_checkable
class CompensationSlots(Protocol):
    """Reading the controller's values in the places a given table would be written to."""

    async def read_compensation_like(self, table: CompensationTable) -> CompensationTable | None:
        """``table``'s slots as the controller holds them, as a table (None: nothing there)."""
        ...


@runtime_checkable
class CompensationSnapshots(Protocol):
    """Verbatim snapshots of a table's slots, taken before robocal first writes there, and
    their restoration (a rollback to the controller's own values)."""

    async def snapshot_compensation(self, table: CompensationTable) -> ControllerSnapshot:
        """Read what the controller holds in the slots ``table`` would write."""
        ...

    async def restore_snapshot(self, snapshot: ControllerSnapshot) -> None:
        """Write ``snapshot`` back, read it again and compare; raise VerificationMismatch."""
        ...


@dataclass(frozen=True, slots=True)
class ControllerCalibration:
    """What the controller says about the kinematic calibration it already applies (ADR 0033).

    Attributes
    ----------
    source : str
        What was read, e.g. ``"ur-kinematics-info"``, ``"abb-rws-cfg-moc"``,
        ``"kuka-kvp-system-variables"``.
    facts : mapping
        The values as read (JSON-ready; vendor units and spellings kept; None for a value the
        controller does not know).
    absolute_accuracy : bool or None
        A vendor absolute-accuracy option (ABB Absolute Accuracy, KUKA positionally accurate
        robot model) is active; None when the interface does not say.
    fingerprint : str
        :func:`calibration_fingerprint` of ``source`` and ``facts``: equal fingerprints, same
        controller calibration.
    """

    source: str
    facts: Mapping[str, Any]
    absolute_accuracy: bool | None
    fingerprint: str = ""

    def __post_init__(self) -> None:
        if not self.fingerprint:
            object.__setattr__(self, "fingerprint",
                               calibration_fingerprint(self.source, self.facts))

    def to_json(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"source": self.source, "fingerprint": self.fingerprint,
                "absolute_accuracy": self.absolute_accuracy,
                "facts": json.loads(json.dumps(self.facts, sort_keys=True))}


def calibration_fingerprint(source: str, facts: Mapping[str, Any]) -> str:
    """SHA-256 (first 16 hex digits) of ``source`` and ``facts`` as canonical JSON."""
    text = json.dumps({"source": source, "facts": facts}, sort_keys=True,
                      separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@runtime_checkable
class ControllerCalibrationReadable(Protocol):
    """Reading what the controller applies of its own calibration (kinematics, mastering,
    a vendor absolute-accuracy option), fresh from the controller on every call."""

    async def controller_calibration(self) -> ControllerCalibration:
        """Read it now; raise ConnectFailed or DriverTimeout when the controller cannot say."""
        ...


@runtime_checkable
class RobotDriver(Connectable, JointMover, JointReader, Stoppable, Protocol):
    """A robot driver: connect, move, read joints, stop."""


@runtime_checkable
class TrackerDriver(Connectable, PointMeasurer, Protocol):
    """A tracker driver: connect, measure."""


def require(obj: object, *capabilities: type) -> None:
    """Raise DriverError naming the capabilities ``obj`` lacks (like bluesky's check_supports)."""
    missing = [c.__name__ for c in capabilities if not isinstance(obj, c)]
    if missing:
        kind = getattr(obj, "kind", None)
        raise DriverError(
            f"{type(obj).__name__} does not support {', '.join(missing)}",
            kind=kind if isinstance(kind, str) else None,
        )


def check_joint_target(
    q_rad: Sequence[float],
    limits_rad: Sequence[tuple[float, float]],
    *,
    kind: str | None = None,
) -> tuple[float, ...]:
    """Return ``q_rad`` as a tuple after checking length, finiteness and joint limits.

    Raises
    ------
    LimitViolation
        If the target has the wrong number of joints, a non-finite value, or a joint outside
        ``limits_rad``. The caller must not send anything then.
    """
    try:
        q = tuple(float(v) for v in q_rad)
    except (TypeError, ValueError) as err:
        msg = f"joint target is not a sequence of numbers: {err}"
        raise LimitViolation(msg, kind=kind) from err
    if len(q) != len(limits_rad):
        raise LimitViolation(
            f"joint target has {len(q)} values, the robot has {len(limits_rad)} joints", kind=kind
        )
    for i, (v, (lo, hi)) in enumerate(zip(q, limits_rad, strict=True)):
        if not math.isfinite(v):
            raise LimitViolation(f"J{i + 1} target {v!r} is not finite", kind=kind)
        if not lo <= v <= hi:
            raise LimitViolation(
                f"J{i + 1} target {math.degrees(v):.4f} deg outside "
                f"[{math.degrees(lo):.4f}, {math.degrees(hi):.4f}] deg; nothing sent",
                kind=kind,
            )
    return q
