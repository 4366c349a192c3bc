"""Typed shapes of the daemon's records, of what its HTTP API returns and of its events.

A record the daemon stores has one type here, used by the store, the service, the API and
the CLI alike: :class:`Measurement`, :class:`JournalRow` (with its :class:`PushDetail` or
:class:`RollbackDetail`). The composite answers (campaign status, compensation state) are
still assembled as mappings by :class:`~robocal.daemon.service.CalibrationService`; the API
validates and serialises every JSON response through these models (a key renamed in the
service fails a test instead of surprising a client), and
:class:`~robocal.daemon.events.EventBus` validates every event against its kind's model.
``openapi_spec()`` is generated from them (ADR 0044).

Units follow the wire convention: mm, degrees, seconds; times are ISO 8601 strings (UTC)
except the event ``time`` (Unix seconds).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator

from robocal.daemon.campaign import CampaignState

__all__ = [
    "EVENT_MODELS",
    "AuditEntry",
    "CampaignStatus",
    "CampaignSummary",
    "CheckEvent",
    "CheckRecord",
    "CompensationEvent",
    "CompensationState",
    "ErrorBody",
    "Event",
    "EventPoll",
    "FitEvent",
    "Health",
    "JournalRow",
    "LogEvent",
    "Measurement",
    "PoseEvent",
    "PushDetail",
    "ReportEvent",
    "ReportProgress",
    "RetryEvent",
    "RollbackDetail",
    "StateEvent",
    "event_adapter",
]

CampaignStateName = Literal["created", "running", "paused", "measured", "fitted", "approved",
                            "pushed", "faulted", "aborted"]


class _Closed(BaseModel):
    """A response object whose keys are all known: an unknown key is a bug."""

    model_config = ConfigDict(extra="forbid")


# --- campaigns -------------------------------------------------------------------------------
#: Where a push's table is now (one truth: :meth:`CompensationManager.push_states`).
CompensationStateName = Literal["active", "superseded", "rolled back"]


class CampaignSummary(_Closed):
    """One campaign: the store's record of it (:meth:`Store.campaign
    <robocal.daemon.store.Store.campaign>`), ``GET /campaigns`` entries and the head of a
    campaign status. ``compensation_state`` and ``push_key`` are the service's view (the
    journal's), unset in the store's record."""

    id: str
    name: str
    state: CampaignState
    reason: str = Field(description="why it is in this state (the last transition's reason)")
    robot: str
    poses_total: int = Field(ge=0, description="poses to measure (via-points not counted)")
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
    temperatures_c: list[float] | None = Field(
        default=None, description="joint temperatures (degC) the table compensates for; "
                                  "None: the model's reference (ADR 0054)")
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
    """A stored measurement (mm, degrees): the one type of it, from the campaign runner to
    the store, the fit, the API and ``robocal report``."""

    model_config = ConfigDict(frozen=True)

    pose_idx: int
    purpose: str
    q_cmd_deg: tuple[float, ...]
    q_act_deg: tuple[float, ...]
    p_mm: tuple[float, float, float]
    sigma_mm: tuple[float, float, float] | None
    rms_mm: float | None
    samples: int
    attempts: int
    distance_mm: float | None
    weather: dict[str, float]
    measured_at: str
    beam_losses: int = 0
    temps_c: tuple[float, ...] = Field(default=(),
                                       description="joint temperatures, degC (empty: not read)")


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
#: A table's predicted figures (mm), as :func:`robocal.compensation.describe_table` gives them.
PredictedMm = Annotated[float | None, Field(
    description="RMS error the fit predicts with the table (mm)")]
NominalMm = Annotated[float | None, Field(description="RMS error the fit predicts without it (mm)")]
ModelAccuracyMm = Annotated[float | None, Field(
    description="held-out RMS error of the fitted model (mm)")]
class ActiveTable(_Closed):
    """The table (or controller snapshot) active on the controller."""

    table_id: int
    kind: str
    checksum: str
    campaign: str | None
    origin: str
    purpose: str = Field(description="what the table corrects, in words")
    predicted_residual_mm: PredictedMm = None
    nominal_residual_mm: NominalMm = None
    model_accuracy_mm: ModelAccuracyMm = None
    ratio: float | None = Field(default=None, description="predicted / nominal residual")
    warnings: list[str] | None = None


class PushHistoryEntry(_Closed):
    """One write to the controller: baseline snapshot, push or rollback."""

    id: int
    at: str
    action: Literal["push", "rollback", "baseline"] = Field(
        description="baseline: the controller's own values, read before the first push")
    table_id: int = Field(description="the table (or snapshot) on the controller after it")
    campaign: str | None
    actor: str
    kind: str = Field(description="targets, joint, frames, or snapshot")
    checksum: str
    origin: str = Field(description="campaign (a robocal table) or controller (a snapshot)")
    key: str | None = Field(default=None, description="journal key of the push or rollback")
    predicted_residual_mm: PredictedMm = None
    nominal_residual_mm: NominalMm = None
    forced: bool | None = Field(default=None, description="pushed over a refusal (audited)")
    refusal: str | None = Field(default=None, description="why it was refused unforced")
    reason: str | None = None
    verification: Verification | None = None
    compensation_state: CompensationStateName | None = Field(
        default=None, description="for a push: its table now (active, superseded, rolled back)")
    superseded_by: str | None = Field(default=None, description="key of the push on top of it")
    rolled_back_by: str | None = Field(default=None, description="key of the rollback")
    rolled_back_at: str | None = None


class PushDetail(_Closed):
    """What a push journals beside its row: the table's description and what was forced.

    The program's joints (``program_q_deg``, deg, one row per target) are what its
    verification run measures again; they are not shown in the API's journal (too long).
    """

    model_config = ConfigDict(frozen=True)

    kind: str
    purpose: str
    predicted_residual_mm: PredictedMm = None
    nominal_residual_mm: NominalMm = None
    model_accuracy_mm: ModelAccuracyMm = None
    ratio: float | None = None
    warnings: list[str] = Field(default_factory=list)
    model: str | None = None
    model_id: str | None = None
    coverage: dict[str, Any] | None = Field(
        default=None, description="program targets outside the fitted model's coverage")
    forced: bool = False
    refusal: str | None = Field(default=None, description="why it was refused unforced")
    reason: str = ""
    controller_calibration: dict[str, Any] | None = None
    program_q_deg: list[list[float]] | None = None
    target_p_mm: list[list[float]] | None = Field(
        default=None, description="the program's target positions (mm), where it gives them")
    temperatures: dict[str, Any] | None = Field(
        default=None, description="the joint temperatures the table compensates for (ADR 0054)")


class RollbackDetail(_Closed):
    """What a rollback journals: the tables swapped and what its verification run measures
    again (the restored table's targets, or the rolled-back one's, now uncompensated)."""

    model_config = ConfigDict(frozen=True)

    reason: str = ""
    restored_table_id: int | None = None
    rolled_back_table_id: int | None = None
    program_q_deg: list[list[float]] | None = None
    model_campaign: str | None = Field(
        default=None, description="the campaign whose fitted model built those targets' table")
    target_p_mm: list[list[float]] | None = None
    restores: str | None = Field(default=None,
                                 description="'controller original' or '<kind> table'")


#: Bulky detail fields left out of the API's journal and campaign views.
BULKY_DETAIL = frozenset({"program_q_deg", "target_p_mm"})


class JournalRow(_Closed):
    """One row of the push journal (``table_id``: the table written; for a rollback, the one
    restored), as stored and as the API shows it."""

    model_config = ConfigDict(frozen=True)

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
    detail: PushDetail | RollbackDetail

    @model_validator(mode="before")
    @classmethod
    def _detail_of_action(cls, data: Any) -> Any:
        """A detail given as a mapping is read as the model of the row's action."""
        if isinstance(data, dict) and isinstance(data.get("detail"), dict):
            shape = RollbackDetail if data.get("action") == "rollback" else PushDetail
            data = {**data, "detail": shape.model_validate(data["detail"])}
        return data

    def model_campaign(self) -> str | None:
        """The campaign whose fitted model built the targets this entry's verification run
        measures: a push's own, or the one a rollback's detail names."""
        if self.campaign is not None or isinstance(self.detail, PushDetail):
            return self.campaign
        return self.detail.model_campaign

    def shown(self) -> dict[str, Any]:
        """The row as the API's journal shows it (the bulky detail fields left out)."""
        return {**self.model_dump(exclude={"detail"}),
                "detail": self.detail.model_dump(exclude=set(BULKY_DETAIL), exclude_unset=True)}


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


class WarmupEvent(_EventBase):
    """The warm-up routine before a campaign's first measured pose started, moved on or
    ended (ADR 0042)."""

    kind: Literal["warmup"]
    phase: Literal["started", "progress", "done"]
    elapsed_s: float = Field(description="since the routine started (controller clock)")
    temps_c: list[float] | None = Field(default=None, description="joint temperatures, degC")
    rate_c_per_min: float | None = Field(
        default=None, description="largest joint temperature change per minute")
    reason: str | None = None


class ReportFiles(_Closed):
    """Where a fit's report was written, or why it was not."""

    paths: dict[Literal["html", "json"], str] | None = None
    skipped: str | None = None


class FitEvent(_EventBase):
    """Fitting started, finished or failed."""

    kind: Literal["fit"]
    phase: Literal["started", "done", "failed"]
    models: list[str] | None = None
    selected: str | None = Field(default=None, description="the model proposed for approval")
    validation_rms_mm: float | None = Field(
        default=None, description="held-out RMS error of the selected model (mm)")
    report: ReportFiles | None = None
    seconds: float | None = Field(default=None, description="how long the fit took (s)")
    reason: str | None = None


class CompensationEvent(_EventBase):
    """A push, rollback, reconciliation or verification run finished."""

    kind: Literal["compensation"]
    action: Literal["push", "rollback", "verified", "push-reconciled",
                    "rollback-reconciled"]
    key: str
    checksum: str | None = None
    state: str | None = Field(default=None, description="a reconciled entry's journal state")
    before_rms_mm: float | None = Field(
        default=None, description="verified: RMS error of the targets before (mm)")
    after_rms_mm: float | None = Field(
        default=None, description="verified: RMS error of the targets after (mm)")


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


class CheckEvent(_EventBase):
    """A drift check started, was judged or failed (ADR 0041); ``campaign`` is its
    measure-only campaign."""

    kind: Literal["check"]
    check: int
    state: Literal["measuring", "done", "failed"]
    verdict: Literal["pass", "warn", "fail"] | None = None
    rms_mm: float | None = None
    max_mm: float | None = None
    recommendation: Literal["none", "reuse", "full"] | None = None
    reason: str | None = None


class CheckRecord(_Closed):
    """A drift check (``GET /checks``, ADR 0041): its measure-only campaign, the model it
    checked, and once judged its verdict, errors (mm) and recommendation; ``detail`` holds
    the reasons, the growth since the last check, the per-pose errors and the advice."""

    id: int
    campaign: str | None
    created: str
    updated: str
    state: Literal["measuring", "done", "failed"]
    actor: str
    model_campaign: str
    model: str
    verdict: Literal["pass", "warn", "fail"] | None
    rms_mm: float | None
    max_mm: float | None
    n: int | None
    recommendation: Literal["none", "reuse", "full"] | None
    detail: dict[str, Any]


Event = Annotated[StateEvent | PoseEvent | RetryEvent | FitEvent | CompensationEvent
                  | ReportEvent | LogEvent | CheckEvent | WarmupEvent,
                  Field(discriminator="kind")]

#: The model of each event kind.
EVENT_MODELS: dict[str, type[_EventBase]] = {
    "state": StateEvent, "pose": PoseEvent, "retry": RetryEvent, "fit": FitEvent,
    "compensation": CompensationEvent, "report": ReportEvent, "log": LogEvent,
    "check": CheckEvent, "warmup": WarmupEvent}

event_adapter: TypeAdapter[Event] = TypeAdapter(Event)


class EventPoll(_Closed):
    """``GET /events/poll``."""

    events: list[Event]
    last_seq: int
