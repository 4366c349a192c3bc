"""Typed shapes of what the daemon's HTTP API returns and of its progress events.

:class:`~robocal.daemon.service.CalibrationService` returns plain dicts; the API validates
and serialises every JSON response through these models (a key renamed in the service
fails a test instead of surprising a client), and :class:`~robocal.daemon.events.EventBus`
validates every event against its kind's model. ``openapi_spec()`` is generated from them.

Units follow the wire convention: mm, degrees, seconds; times are ISO 8601 strings (UTC)
except the event ``time`` (Unix seconds).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter

__all__ = [
    "EVENT_MODELS",
    "AuditEntry",
    "CampaignStatus",
    "CampaignSummary",
    "CompensationEvent",
    "CompensationState",
    "ErrorBody",
    "Event",
    "EventPoll",
    "FitEvent",
    "Health",
    "LogEvent",
    "Measurement",
    "PoseEvent",
    "ReportEvent",
    "ReportProgress",
    "RetryEvent",
    "StateEvent",
    "event_adapter",
]

CampaignStateName = Literal["created", "running", "paused", "measured", "fitted", "approved",
                            "pushed", "faulted", "aborted"]


class _Closed(BaseModel):
    """A response object whose keys are all known: an unknown key is a bug."""

    model_config = ConfigDict(extra="forbid")


# --- campaigns -------------------------------------------------------------------------------
#: Where a push's table is now (one truth: :meth:`CalibrationService.push_states`).
CompensationStateName = Literal["active", "superseded", "rolled back"]


class CampaignSummary(_Closed):
    """One campaign (``GET /campaigns`` entries; the head of a campaign status)."""

    id: str
    name: str
    state: CampaignStateName
    reason: str
    robot: str
    poses_total: int = Field(ge=0)
    poses_measured: int = Field(ge=0)
    measure_only: bool
    created: str
    updated: str
    created_by: str
    plan_digest: str
    config_digest: str
    selected_model: str | None
    compensation_state: CompensationStateName | None = Field(
        default=None, description="a pushed campaign's table now: active, superseded by a "
                                  "later push, or rolled back")
    push_key: str | None = Field(
        default=None, description="journal key of the campaign's push: the one id the push is "
                                  "shown by (status, list, watch, report, /compensation)")
    verifies: str | None = Field(
        default=None, description="journal key of the push or rollback this run verifies "
                                  "(a verification run, a child of that push); else null")


class Transition(_Closed):
    """One state change of a campaign."""

    at: str
    from_state: CampaignStateName | None
    to_state: CampaignStateName
    reason: str
    actor: str


class FitSummary(BaseModel):
    """The summary of one fitted model (or its ``error``).

    Open (``extra="allow"``): beyond ``model`` the keys are identification's fit report
    (train/validation statistics, outliers, parameter details), which that layer versions.
    """

    model_config = ConfigDict(extra="allow")

    model: str
    error: str | None = None


class ErrorStats(_Closed):
    """Position errors of a verification run (mm)."""

    n: int
    rms_mm: float | None = None
    mean_mm: float | None = None
    max_mm: float | None = None


class TargetError(_Closed):
    """One re-measured target: error before and after compensation (mm)."""

    index: int
    before_mm: float
    after_mm: float


class Verification(_Closed):
    """The verification run of a push or rollback: its targets measured again."""

    state: Literal["pending", "measuring", "done", "skipped", "failed"]
    campaign: str | None
    updated: str
    reason: str | None = None
    indices: list[int] | None = None
    model_campaign: str | None = None
    action: str | None = None
    before: ErrorStats | None = None
    after: ErrorStats | None = None
    per_target: list[TargetError] | None = None


class CampaignPush(BaseModel):
    """One journaled push of a campaign.

    Open (``extra="allow"``): the journal's detail (the table description, ``forced``,
    ``refusal``, ``reason``, ...) is merged in and differs between pushes, rollbacks and
    reconciled entries.
    """

    model_config = ConfigDict(extra="allow")

    key: str
    action: Literal["push", "rollback"]
    state: Literal["intended", "completed", "abandoned"]
    actor: str
    at: str
    outcome: str
    checksum: str
    table_id: int
    verification: Verification | None


class PushSummary(_Closed):
    """A campaign's last completed push in a few numbers (mm)."""

    key: str
    at: str
    actor: str
    model: str | None
    kind: str | None
    checksum: str
    predicted_rms_mm: float | None
    nominal_rms_mm: float | None
    model_accuracy_mm: float | None
    forced: bool | None
    verification: str | None
    measured_before_rms_mm: float | None
    measured_after_rms_mm: float | None
    measured_n: int | None
    compensation_state: CompensationStateName | None = None
    superseded_by: str | None = Field(default=None, description="key of the push on top of it")
    rolled_back_by: str | None = Field(default=None, description="key of the rollback")
    rolled_back_at: str | None = None


class FitProgress(_Closed):
    """The fit the daemon is running for a measured campaign."""

    models: list[str]
    started: str = Field(description="when the fit started (ISO 8601, UTC)")
    elapsed_s: float


class ControllerCalibrationRecord(_Closed):
    """What the controller applied of its own calibration when the campaign started
    (ADR 0033)."""

    state: Literal["read", "unavailable"]
    read_at: str
    fingerprint: str | None
    absolute_accuracy: bool | None = Field(
        description="a vendor absolute-accuracy option was active (None: not shown)")
    source: str | None
    facts: dict[str, Any] = Field(description="the values as read, vendor units")
    reason: str = Field(description="why it is unavailable")


class ReportProgress(_Closed):
    """Where the report of a campaign's fit stands (it renders after the fit is stored)."""

    state: Literal["rendering", "ready", "failed"]
    html: str | None = None
    reason: str | None = None


class CampaignStatus(CampaignSummary):
    """``GET /campaigns/{cid}`` and every campaign action's answer."""

    fits: dict[str, FitSummary]
    transitions: list[Transition]
    pose_overhead_s: float | None = Field(description="median time per pose (s)")
    files: str = Field(description="directory of the campaign's report files")
    compensation: list[CampaignPush]
    push: PushSummary | None
    fitting: FitProgress | None = Field(
        default=None, description="the fit in progress (measured campaigns), else null")
    controller_calibration: ControllerCalibrationRecord | None = None
    report: ReportProgress | None = Field(
        default=None, description="the report of this daemon's fit: rendering (after the fit "
        "was stored), then ready or failed; null when none was rendered since the start")


class Measurement(_Closed):
    """A stored measurement (mm, degrees)."""

    pose_idx: int
    purpose: str
    q_cmd_deg: list[float]
    q_act_deg: list[float]
    p_mm: list[float] = Field(min_length=3, max_length=3)
    sigma_mm: list[float] | None = Field(min_length=3, max_length=3)
    rms_mm: float | None
    samples: int
    attempts: int
    distance_mm: float | None
    weather: dict[str, float]
    measured_at: str
    beam_losses: int


# --- health ----------------------------------------------------------------------------------
class DriverInfo(_Closed):
    kind: str
    connected: bool


class DriversInfo(_Closed):
    robot: DriverInfo
    tracker: DriverInfo
    last_error: str


class Health(_Closed):
    """``GET /health``."""

    status: Literal["ok", "degraded"]
    storage: str
    unsaved_states: dict[str, CampaignStateName]
    version: str
    uptime_s: float
    robot: str
    drivers: DriversInfo
    measuring: str | None
    fitting: list[str]
    config_digest: str


# --- compensation ----------------------------------------------------------------------------
class ActiveTable(_Closed):
    """The table (or controller snapshot) active on the controller."""

    table_id: int
    kind: str
    checksum: str
    campaign: str | None
    origin: str
    purpose: str
    predicted_residual_mm: float | None = None
    nominal_residual_mm: float | None = None
    model_accuracy_mm: float | None = None
    ratio: float | None = None
    warnings: list[str] | None = None


class PushHistoryEntry(_Closed):
    """One write to the controller: baseline snapshot, push or rollback."""

    id: int
    at: str
    action: Literal["push", "rollback", "baseline"]
    table_id: int
    campaign: str | None
    actor: str
    kind: str
    checksum: str
    origin: str
    key: str | None = None
    predicted_residual_mm: float | None = None
    nominal_residual_mm: float | None = None
    forced: bool | None = None
    refusal: str | None = None
    reason: str | None = None
    verification: Verification | None = None
    compensation_state: CompensationStateName | None = Field(
        default=None, description="for a push: its table now (active, superseded, rolled back)")
    superseded_by: str | None = Field(default=None, description="key of the push on top of it")
    rolled_back_by: str | None = Field(default=None, description="key of the rollback")
    rolled_back_at: str | None = None


class JournalRow(_Closed):
    """One row of the push journal."""

    key: str
    action: Literal["push", "rollback"]
    state: Literal["intended", "completed", "abandoned"]
    campaign: str | None
    actor: str
    table_id: int
    baseline_id: int | None
    rolled_back_id: int | None
    intended_at: str
    finished_at: str | None
    outcome: str
    # open: what was journaled differs by action (table description, rollback ids, reason)
    detail: dict[str, Any]


class CompensationState(_Closed):
    """``GET /compensation`` and ``POST /compensation/rollback``."""

    active: ActiveTable | None
    stack: list[int] = Field(description="table ids active over time; the last is active now")
    history: list[PushHistoryEntry]
    journal: list[JournalRow] = Field(description="the last 50 journal rows")


class AuditEntry(_Closed):
    """One entry of the append-only audit log."""

    id: int
    at: str
    actor: str
    action: str
    campaign: str | None
    checksum: str | None
    # open: each action records its own detail (documented with the action in the service)
    detail: dict[str, Any]


# --- errors ----------------------------------------------------------------------------------
class ErrorDetail(_Closed):
    type: str = Field(description="exception or HTTP error class name")
    message: str
    status: int = Field(ge=400, le=599)


class ErrorBody(_Closed):
    """Every 4xx/5xx answer."""

    error: ErrorDetail


# --- events ----------------------------------------------------------------------------------
class _EventBase(_Closed):
    seq: int = Field(ge=1, description="increasing within one daemon run")
    time: float = Field(description="Unix time (s)")
    campaign: str | None


class StateEvent(_EventBase):
    """A campaign changed state."""

    kind: Literal["state"]
    state: CampaignStateName
    reason: str
    poses_measured: int
    poses_total: int


class PoseEvent(_EventBase):
    """A pose was measured."""

    kind: Literal["pose"]
    pose: int
    purpose: str
    poses_measured: int
    poses_total: int
    attempts: int
    distance_mm: float | None


class RetryEvent(_EventBase):
    """A reading was rejected and is retried."""

    kind: Literal["retry"]
    pose: int
    attempt: int
    problem: str


class ReportFiles(_Closed):
    """Where a fit's report was written, or why it was not."""

    paths: dict[Literal["html", "json"], str] | None = None
    skipped: str | None = None


class FitEvent(_EventBase):
    """Fitting started, finished or failed."""

    kind: Literal["fit"]
    phase: Literal["started", "done", "failed"]
    models: list[str] | None = None
    selected: str | None = None
    validation_rms_mm: float | None = None
    report: ReportFiles | None = None
    seconds: float | None = None
    reason: str | None = None


class CompensationEvent(_EventBase):
    """A push, rollback, reconciliation or verification run finished."""

    kind: Literal["compensation"]
    action: Literal["push", "rollback", "verified", "push-reconciled",
                    "rollback-reconciled"]
    key: str
    checksum: str | None = None
    state: str | None = None
    before_rms_mm: float | None = None
    after_rms_mm: float | None = None


class ReportEvent(_EventBase):
    """A campaign's report: its Compensation section rewritten to show what is true now
    (``section="compensation"``), or the report of a fit being rendered after the fit was
    stored (``section="campaign"``, ``state`` rendering, then ready or failed)."""

    kind: Literal["report"]
    section: Literal["compensation", "campaign"]
    html: str | None = None
    state: Literal["rendering", "ready", "failed"] | None = None
    reason: str | None = None


class LogEvent(_EventBase):
    """A free-text note for watchers."""

    kind: Literal["log"]
    text: str
    level: Literal["debug", "info", "warning", "error"] = "info"


Event = Annotated[StateEvent | PoseEvent | RetryEvent | FitEvent | CompensationEvent
                  | ReportEvent | LogEvent, Field(discriminator="kind")]

#: The model of each event kind.
EVENT_MODELS: dict[str, type[_EventBase]] = {
    "state": StateEvent, "pose": PoseEvent, "retry": RetryEvent, "fit": FitEvent,
    "compensation": CompensationEvent, "report": ReportEvent, "log": LogEvent}

event_adapter: TypeAdapter[Event] = TypeAdapter(Event)


class EventPoll(_Closed):
    """``GET /events/poll``."""

    events: list[Event]
    last_seq: int
