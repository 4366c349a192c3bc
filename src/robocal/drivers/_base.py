"""Optional driver base class: options validation, lifecycle bookkeeping, error translation."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, ClassVar, Literal, Self

import structlog
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from robocal.drivers.api import (
    CompensationSink,
    CompensationSlots,
    CompensationSnapshots,
    check_joint_target,
)
from robocal.errors import (
    ConfigError,
    ConnectFailed,
    DriverError,
    DriverTimeout,
    TransportError,
    TransportTimeout,
    VerificationMismatch,
)

__all__ = [
    "CompensatingRobotBase",
    "DriverBase", "DriverOptions", "RobotDriverBase", "RobotOptions", "validate_options"]

DriverState = Literal["new", "connecting", "connected", "closed"]


class DriverOptions(BaseModel):
    """Base of every driver's options: frozen, unknown keys rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class RobotOptions(DriverOptions):
    """Options every robot driver has.

    ``joint_limits_deg`` (degrees, one ``[min, max]`` per joint) also fixes the joint count;
    the driver refuses any target outside them before sending anything.
    """

    joint_limits_deg: tuple[tuple[float, float], ...] = Field(min_length=1, max_length=9)
    default_speed_pct: float = Field(default=10.0, gt=0.0, le=100.0)

    @field_validator("joint_limits_deg")
    @classmethod
    def _ordered(cls, v: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
        for i, (lo, hi) in enumerate(v):
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"J{i + 1} limits must be finite with min < max, got {lo}, {hi}")
        return v


def validate_options(cls: type[DriverOptions], options: Any, *, kind: str) -> DriverOptions:
    """Return ``options`` validated against ``cls``; raise ConfigError naming kind and key."""
    if isinstance(options, cls):
        return options
    if options is None:
        options = {}
    if isinstance(options, BaseModel):
        options = options.model_dump()
    if not isinstance(options, Mapping):
        raise ConfigError(f"options must be a mapping, got {type(options).__name__}", source=kind)
    try:
        return cls.model_validate(dict(options))
    except ValidationError as err:
        first = err.errors()[0]
        key = ".".join(str(p) for p in first["loc"]) or None
        raise ConfigError(
            f"{first['msg']} ({err.error_count()} error(s))", source=f"{kind} options", key=key
        ) from err


class DriverBase:
    """Lifecycle bookkeeping shared by robocal's drivers (third-party drivers may ignore it).

    Subclasses set ``kind`` and ``Options`` and implement ``_connect_impl``/``_close_impl``.
    ``__init__`` stores the validated options only; no I/O happens before :meth:`connect`.
    """

    kind: ClassVar[str] = "base"
    Options: ClassVar[type[DriverOptions]] = DriverOptions

    def __init__(self, options: DriverOptions | Mapping[str, Any] | None = None) -> None:
        self.options = validate_options(self.Options, options, kind=self.kind)
        self.state: DriverState = "new"
        self.log = structlog.get_logger(f"robocal.drivers.{self.kind}").bind(driver=self.kind)

    @property
    def connected(self) -> bool:
        """True after a successful connect and before close."""
        return self.state == "connected"

    async def connect(self, *, timeout: float = 10.0) -> None:
        """Connect (no-op when connected); clean up and re-raise on failure."""
        if self.state == "connected":
            return
        self.state = "connecting"
        try:
            with self.translate_errors(connecting=True):
                await self._connect_impl(timeout)
        except BaseException:
            await self._safe_close()
            self.state = "closed"
            raise
        self.state = "connected"
        self.log.info("connected")

    async def close(self) -> None:
        """Close; idempotent, safe after a failed connect, never raises."""
        if self.state in ("new", "closed"):
            self.state = "closed"
            return
        await self._safe_close()
        self.state = "closed"
        self.log.info("closed")

    async def _safe_close(self) -> None:
        try:
            await self._close_impl()
        except Exception as err:  # close() must never raise
            self.log.warning("error while closing", error=repr(err))

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _ensure_connected(self) -> None:
        if self.state != "connected":
            raise ConnectFailed("not connected; call connect() first", kind=self.kind)

    @contextlib.contextmanager
    def translate_errors(self, *, connecting: bool = False) -> Iterator[None]:
        """Re-raise transport failures as driver errors (``raise ... from``)."""
        try:
            yield
        except DriverError:
            raise
        except TransportTimeout as err:
            raise DriverTimeout(str(err), kind=self.kind) from err
        except TransportError as err:
            what = "cannot connect" if connecting else "connection lost"
            raise ConnectFailed(f"{what}: {err}", kind=self.kind) from err

    def _check_read_back(self, diff: list[str], what: str) -> None:
        """Raise VerificationMismatch ``"<what>: <first difference>"`` if ``diff`` is not
        empty (as from ``table_diff`` or ``snapshot_diff``; at most 20 kept)."""
        if diff:
            raise VerificationMismatch(f"{what}: {diff[0]}", kind=self.kind, diff=diff[:20])

    async def _connect_impl(self, timeout: float) -> None:
        raise NotImplementedError

    async def _close_impl(self) -> None:
        raise NotImplementedError


class RobotDriverBase(DriverBase):
    """Base for robot drivers: joint count, limits and the pre-send target check."""

    Options: ClassVar[type[DriverOptions]] = RobotOptions
    options: RobotOptions

    @property
    def dof(self) -> int:
        """Number of joints (from the configured joint limits)."""
        return len(self.options.joint_limits_deg)

    @property
    def joint_limits_rad(self) -> tuple[tuple[float, float], ...]:
        """Configured joint limits, radians."""
        limits = self.options.joint_limits_deg
        return tuple((math.radians(lo), math.radians(hi)) for lo, hi in limits)

    def _check_target(self, q_rad: Sequence[float]) -> tuple[float, ...]:
        return check_joint_target(q_rad, self.joint_limits_rad, kind=self.kind)

    def _move_target(
        self, q_rad: Sequence[float], speed_pct: float | None
    ) -> tuple[tuple[float, ...], float]:
        """Checked target (radians; LimitViolation, nothing sent) and speed (% of maximum)."""
        speed = self.options.default_speed_pct if speed_pct is None else speed_pct
        return self._check_target(q_rad), speed


class CompensatingRobotBase(
    RobotDriverBase, CompensationSink, CompensationSlots, CompensationSnapshots
):
    """Base for controller drivers that write, re-read and snapshot compensation tables."""
