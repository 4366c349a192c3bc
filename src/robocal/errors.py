"""The one exception tree of robocal.

Every failure robocal raises derives from :class:`RobocalError`. Subclasses are split by
phase (configuration, driver, protocol, identification, compensation, campaign) and mix in
the builtin a caller would naturally catch (``ValueError``, ``TimeoutError``, ...).
Numerical non-convergence of a solver is reported as a status, not raised, except where a
command-line contract asks for an error.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


class RobocalError(Exception):
    """Root of every error robocal raises."""


# --- input ------------------------------------------------------------------------------------
class ConfigError(RobocalError, ValueError):
    """A configuration, description or data file is invalid.

    ``source`` names the file (or request), ``key`` the offending key or column.
    """

    def __init__(self, message: str, *, source: str | None = None, key: str | None = None):
        self.source = source
        self.key = key
        parts = []
        if source:
            parts.append(str(source))
        if key:
            parts.append(f"key {key!r}")
        prefix = ": ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class DataError(ConfigError):
    """A measurement or joint file is unusable (missing columns, NaN, wrong joint count)."""


class FileWriteError(ConfigError, OSError):
    """An output file could not be written (a directory, no such folder, no permission, disk
    full). Also an ``OSError``, so code that handles I/O failures still sees it."""


# --- drivers ----------------------------------------------------------------------------------
class DriverError(RobocalError):
    """A driver failed. ``kind`` names the driver."""

    def __init__(self, message: str, *, kind: str | None = None):
        self.kind = kind
        super().__init__(f"[{kind}] {message}" if kind else message)


class DriverNotFound(DriverError, LookupError):
    """No driver is registered under that name."""


class DriverImportError(DriverError, ImportError):
    """A registered driver could not be imported."""


class ConnectFailed(DriverError, ConnectionError):
    """Connecting to a device failed."""


class DriverTimeout(DriverError, TimeoutError):
    """A device did not answer in time."""


class OperationError(DriverError):
    """A device refused or failed an operation.

    What the device said, where a subclass has it: ``code``, the controller's error code
    (:class:`MotionRejected`); ``diff``, the differences read back (:class:`VerificationMismatch`).
    """

    def __init__(self, message: str, *, kind: str | None = None, code: Any = None,
                 diff: Any = None):
        super().__init__(message, kind=kind)
        self.code, self.diff = code, diff


class MotionRejected(OperationError):
    """The controller refused or faulted a motion. ``code`` is the controller's code."""


class MotionStopped(OperationError):
    """A motion ended early because ``stop()`` was called; the robot halted short of the target."""


class LimitViolation(OperationError, ValueError):
    """A joint target lies outside the joint limits; it was not sent."""


class MeasurementError(OperationError):
    """The tracker could not deliver a measurement."""


class BeamLost(MeasurementError):
    """The tracker beam was broken or the target was not found (recoverable)."""


class MeasurementRejected(MeasurementError):
    """A reading failed the daemon's validation (stability or distance from the prediction)."""


class Unstable(MeasurementError):
    """The target did not become stable within the time allowed (recoverable)."""


class VerificationMismatch(OperationError):
    """Data read back from a device differs from what was written. ``diff`` holds details."""


# --- emScon tracker status errors (raised by robocal.drivers.emscon) -----------------------
class EmsconStatusError(OperationError):
    """The tracker answered a command with a non-zero ``ES_ResultStatus``.

    ``status`` is the raw code (possibly outside the published enum), ``command`` the ID.
    """

    def __init__(self, message: str, *, kind: str | None = "emscon", status: int, command: int):
        self.status = status
        self.command = command
        super().__init__(message, kind=kind)


class EmsconBusy(EmsconStatusError):
    """``ServerBusy`` (1) persisted through every retry."""


class EmsconNotInitialized(EmsconStatusError):
    """``TrackerNotInitialized`` (39)."""


class EmsconBeamLost(EmsconStatusError, BeamLost):
    """No lock on the reflector: a status listed in ``beam_broken_statuses``, or event 25."""


class EmsconUnstable(EmsconStatusError, Unstable):
    """A status listed in ``unstable_statuses`` (default ``SensorNotStable``)."""


class EmsconMeasurementError(EmsconStatusError, MeasurementError):
    """Any other failure of ``StartMeasurement`` or of its result packet."""


class EmsconTimeout(EmsconStatusError, DriverTimeout):
    """``ModuleTimedOut`` (41): the tracker's own internal timeout."""


# --- wire protocols ---------------------------------------------------------------------------
class ProtocolError(RobocalError):
    """Bytes on the wire could not be understood. ``last_frames`` holds recent raw frames."""

    def __init__(self, message: str, *, last_frames: Sequence[bytes] = ()):
        self.last_frames = list(last_frames)
        super().__init__(message)


class FramingError(ProtocolError, ValueError):
    """A frame was malformed (too long, truncated, bad characters)."""


class UnexpectedReply(ProtocolError):
    """A well-formed reply did not match the request (wrong tag, sequence id or verb)."""


class TransportError(ProtocolError, ConnectionError):
    """The transport failed (closed, reset, device gone)."""


class RequestPending(RobocalError, RuntimeError):
    """A request/reply session was used out of turn: a request was to be sent while an earlier
    one is still outstanding, or a reply was awaited with nothing outstanding (a driver bug)."""


class TransportTimeout(ProtocolError, TimeoutError):
    """A read on the transport timed out."""


# --- numerical --------------------------------------------------------------------------------
class IdentificationError(RobocalError):
    """Identification could not be carried out."""


class NotIdentifiable(IdentificationError, ValueError):
    """Too few poses or too little excitation for the requested model."""

    def __init__(self, message: str, *, parameters: Sequence[str] = ()):
        self.parameters = list(parameters)
        super().__init__(message)


class NotConverged(IdentificationError):
    """An iterative solver did not converge."""


class CompensationError(RobocalError):
    """Compensation could not be computed, or exceeds the configured bounds."""


# --- campaigns --------------------------------------------------------------------------------
class CampaignError(RobocalError):
    """A campaign operation is not possible."""


class InvalidTransition(CampaignError):
    """A campaign state transition is not in the transition table."""

    def __init__(self, from_state: str, to_state: str, reason: str = ""):
        self.from_state = from_state
        self.to_state = to_state
        if from_state == to_state:
            msg = f"the campaign is already {from_state}"
        else:
            done = _STATE_VERBS.get(to_state, f"moved to {to_state!r}")
            msg = f"a campaign that is {from_state} cannot be {done}"
        super().__init__(f"{msg} ({reason})" if reason else msg)


#: What reaching a campaign state means to an operator ("cannot be <verb>").
_STATE_VERBS = {
    "running": "started or resumed", "paused": "paused", "faulted": "marked faulted",
    "measured": "marked measured", "fitted": "marked fitted", "approved": "approved",
    "pushed": "pushed", "aborted": "aborted", "created": "created again",
}


class UnknownCampaign(CampaignError, LookupError):
    """No campaign with that id."""


class StorageError(RobocalError):
    """The daemon's store cannot write (disk full, I/O error). Nothing stored is lost; the
    work that needed the write is paused until space is back."""


class ApprovalRequired(CampaignError, PermissionError):
    """Compensation was to be pushed without operator approval."""


# --- daemon client ----------------------------------------------------------------------------
class DaemonUnavailable(RobocalError, ConnectionError):
    """The daemon could not be reached."""


_API_STATUS_TEXT = {
    400: "the daemon could not use the request",
    401: "not authorised: give the daemon's token (--token-file or ROBOCAL_TOKEN)",
    403: "not allowed",
    404: "not found on the daemon",
    409: "not possible in the campaign's current state",
    413: "the request is too large",
    422: "the daemon cannot do that with what it has",
    500: "the daemon failed internally; see its log (journalctl -u robocal)",
}


class ApiError(RobocalError):
    """The daemon answered with an error (HTTP ``status``, error ``kind`` and its message)."""

    def __init__(self, status: int, kind: str, message: str) -> None:
        self.status = status
        self.kind = kind
        # The operator reads the daemon's sentence; the status and type stay attributes.
        super().__init__(message or _API_STATUS_TEXT.get(status,
                                                         f"the daemon refused ({status})"))
