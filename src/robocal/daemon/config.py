"""Daemon configuration: one TOML file, validated by frozen pydantic models.

Every model forbids unknown keys, so a typo fails at start-up with the file and the key path
(``robocal.toml: key 'measurement.sampels': Extra inputs are not permitted``) instead of being
ignored. Relative paths are resolved against the configuration file's directory, ``~`` in
``data_dir`` is the running user's home; ``data_dir`` defaults to ``$STATE_DIRECTORY`` (set
by systemd's ``StateDirectory=``) or ``/var/lib/robocal``.

Example (``deploy/config/robocal.example.toml`` is the annotated version)::

    data_dir = "/var/lib/robocal"
    robot_description = "fanuc_lrmate200i"

    [robot]
    kind = "fanuc_rmi"
    options = { host = "192.168.1.10" }

    [tracker]
    kind = "ltp"
    options = { url = "serial:///dev/robocal-tracker?baudrate=115200" }
"""

from __future__ import annotations

import hashlib
import ipaddress
import json
import os
import stat
import urllib.parse
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    NonNegativeFloat,
    PositiveFloat,
    ValidationError,
    ValidatorFunctionWrapHandler,
    field_validator,
    model_validator,
)

from robocal._core.files import read_toml
from robocal._core.model_names import MODELS, FitModel
from robocal._core.thermal import TEMPERATURE_RANGE_C
from robocal.errors import ConfigError

__all__ = [
    "ApiConfig",
    "AppConfig",
    "CheckConfig",
    "CompensationConfig",
    "DriverConfig",
    "FitConfig",
    "FleetConfig",
    "LimitsConfig",
    "LoggingConfig",
    "MeasurementConfig",
    "WarmupConfig",
    "config_digest",
    "config_errors",
    "config_warnings",
    "is_loopback",
    "load_config",
    "parse_config",
]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DriverConfig(_Model):
    """A driver by entry-point name, with options validated by the driver's ``Options`` model.

    For robot drivers, ``joint_limits_deg`` defaults to the robot description's limits.
    """

    kind: str = Field(min_length=1)
    options: dict[str, Any] = Field(default_factory=dict)
    connect_timeout_s: float = Field(default=10.0, gt=0.0)


class ApiConfig(_Model):
    """Where the local HTTP/JSON API listens.

    ``socket`` (default ``robocal.sock`` in ``data_dir``) is a Unix socket whose file mode
    (``socket_mode``, default 0660) is the access control. TCP is off unless ``tcp_port`` is
    set, and then ``token_file`` (a file holding the bearer token) is required.
    ``viewer_token_file`` (optional) holds a second token that signs in to the operator's
    station (and reads the API) with the viewer role: read only.

    A request body may have ``max_body_bytes`` (default 512 KiB, some 1,600 plan poses, five
    times a large campaign; parsing and storing a plan stalls the event loop for about
    0.3 ms per pose, see docs/benchmarks.md). On TCP, connections that present the token have
    ``max_connections`` slots of their own; all others share one pool counted over every
    source address, and a full pool cuts the oldest unauthenticated connection of the address
    holding the most (an address over ``max_connections_per_client`` loses its own oldest
    first) instead of refusing the newcomer (ADR 0025). Request headers must arrive within
    ``header_timeout_s``, a body within ``body_timeout_s``; idle keep-alive connections close
    after ``keepalive_timeout_s``. A TCP flood therefore cannot starve the Unix socket.
    """

    socket: Path | None = Path("robocal.sock")
    socket_mode: int = Field(default=0o660, ge=0, le=0o777)
    tcp_host: str = "127.0.0.1"
    tcp_port: int | None = Field(default=None, ge=0, le=65535)
    token_file: Path | None = None
    viewer_token_file: Path | None = None
    max_body_bytes: int = Field(default=512 * 1024, ge=1024, le=64 * 1024 * 1024)
    max_connections: int = Field(default=64, ge=1, le=4096)
    max_connections_per_client: int = Field(default=8, ge=1, le=4096)
    header_timeout_s: float = Field(default=10.0, gt=0.0, le=300.0)
    body_timeout_s: float = Field(default=60.0, gt=0.0, le=3600.0)
    keepalive_timeout_s: float = Field(default=15.0, gt=0.0, le=3600.0)

    @model_validator(mode="after")
    def _check(self) -> ApiConfig:
        if self.tcp_port is not None and self.token_file is None:
            raise ValueError("tcp_port needs token_file: the TCP API always requires a token")
        if self.viewer_token_file is not None and self.token_file is None:
            raise ValueError("viewer_token_file needs token_file (the operator's token)")
        if self.socket is None and self.tcp_port is None:
            raise ValueError("the API needs a socket or a tcp_port")
        return self


class LimitsConfig(_Model):
    """Safety limits.

    Attributes
    ----------
    joint_margin_deg
        Plan targets must stay this far inside the robot description's joint limits.
    speed_pct
        Speed of campaign motions, percent.
    max_joint_correction_deg
        Largest joint correction a pushed table may contain (``targets`` and ``joint``).
    max_frame_translation_mm, max_frame_rotation_deg
        Largest change of the tool frame (vs. the robot description) and of the base frame
        (vs. the table currently on the controller) a ``frames`` table may contain.
    max_base_distance_mm
        Farthest the tracker may be from the robot base in a ``frames`` table: bounds the
        first push, which has no earlier table to be compared with.
    """

    joint_margin_deg: float = Field(default=1.0, ge=0.0, le=90.0)
    speed_pct: float = Field(default=20.0, gt=0.0, le=100.0)
    # a targets table's 6-D corrections reach a degree where the joint zero offsets are off
    # by tenths of a degree and near the wrist singularity; the demo cell needs up to ~1.5
    max_joint_correction_deg: PositiveFloat = 2.0
    max_frame_translation_mm: PositiveFloat = 10.0
    max_frame_rotation_deg: PositiveFloat = 1.0
    max_base_distance_mm: PositiveFloat = 50_000.0


class MeasurementConfig(_Model):
    """Per-pose measurement: settling, sampling, retries and validation.

    A reading is retried (with exponential backoff) on a broken beam, an unstable target,
    a tracker timeout, too large a sample RMS (``max_rms_mm``) or too large a distance from
    the prediction (``max_distance_mm``: nominal or previous model, after a rigid fit to the
    poses measured so far); after ``retries`` retries the campaign is faulted.
    """

    samples: int = Field(default=10, ge=1, le=10_000)
    timeout_s: PositiveFloat = 10.0
    settle_s: NonNegativeFloat = 0.2
    move_timeout_s: PositiveFloat = 120.0
    retries: int = Field(default=4, ge=0, le=100)
    backoff_s: NonNegativeFloat = 0.1
    backoff_factor: float = Field(default=2.0, ge=1.0)
    max_backoff_s: NonNegativeFloat = 5.0
    max_rms_mm: PositiveFloat = 0.05
    max_distance_mm: PositiveFloat = 25.0
    min_poses_for_distance: int = Field(default=6, ge=4)
    max_joint_deviation_deg: PositiveFloat = 0.5


class WarmupConfig(_Model):
    """The warm-up routine run before a campaign's first measured pose (ADR 0042).

    ``pattern = "plan"``: the campaign's own poses (via-points included) in plan order,
    cycled; each cycle starts with the same checked first move as a campaign (limits, the
    cell's swept path, via the plan's home). ``pattern = "poses"``: ``poses_deg`` (joints,
    degrees) cycled; the whole cycle (from where the robot stands, via the plan's home,
    through every pose and back to the first) is checked the same way before anything
    moves. It ends after ``duration_s``, or, with
    ``until_settled_c_per_min``, once ``duration_s`` (if given) has passed and no joint's
    temperature changed by more than that per minute over the last ``settle_window_s``;
    never later than ``max_s``. Time is the robot controller's clock of the temperature
    readings where the driver reads them, else the daemon's; ``until_settled_c_per_min``
    needs a driver that reads joint temperatures.
    """

    pattern: Literal["plan", "poses"] = "plan"
    poses_deg: tuple[tuple[float, ...], ...] = ()
    duration_s: float | None = Field(default=None, gt=0.0)
    until_settled_c_per_min: float | None = Field(default=None, gt=0.0)
    settle_window_s: float = Field(default=120.0, gt=0.0)
    max_s: float = Field(default=3600.0, gt=0.0)

    @model_validator(mode="after")
    def _has_an_end(self) -> WarmupConfig:
        if self.duration_s is None and self.until_settled_c_per_min is None:
            raise ValueError("warmup needs duration_s or until_settled_c_per_min")
        if (self.pattern == "poses") != bool(self.poses_deg):
            raise ValueError('poses_deg is given with pattern = "poses" (two poses or more), '
                             "and only then")
        if self.pattern == "poses" and len(self.poses_deg) < 2:
            raise ValueError('pattern = "poses" needs two poses or more in poses_deg')
        return self


class FitConfig(_Model):
    """Identification after measuring.

    ``models`` are fitted in order; ``select`` names the one proposed for approval
    (``best``: the lowest held-out RMS). ``executor`` runs fits in a worker process (default)
    or thread, so the event loop keeps serving the API and the watchdog. ``options`` are
    keyword arguments of :class:`robocal.identification.FitOptions` (checked at start-up).
    """

    models: tuple[FitModel, ...] = MODELS
    select: Literal[FitModel, "best"] = "auto"
    cpa: bool = True
    executor: Literal["process", "thread"] = "process"
    timeout_s: float = Field(default=1800.0, gt=0.0)
    report: bool = True
    options: dict[str, Any] = Field(default_factory=dict)
    #: The report's verdict thresholds for this cell (keys of :class:`robocal.report.Acceptance`,
    #: e.g. ``max_rms_mm = 0.3``, ``min_percent_described = 70``).
    acceptance: dict[str, float | None] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _check(self) -> FitConfig:
        if not self.models:
            raise ValueError("models must name at least one model")
        if self.acceptance:  # imported only when used: the report package is not small
            from robocal.report import Acceptance

            Acceptance.from_mapping(self.acceptance)
        if self.select != "best" and self.select not in self.models:
            raise ValueError(f"select={self.select!r} is not among models {list(self.models)}")
        return self


class CompensationConfig(_Model):
    """What is pushed after approval (see ``docs/compensation-tables.md``).

    Attributes
    ----------
    kind
        ``targets`` (default): the production targets compensated with the approved model;
        ``joint``: per-joint corrections; ``frames``: base/tool alignment only (not
        compensation).
    targets_file
        CSV ``q1..qN`` (degrees): the robot program's targets as taught; row ``i`` is written
        to position registers ``pr_base + 2i`` and ``pr_base + 2i + 1`` (FANUC) or table row
        ``i`` (PLC). Without it the campaign's validation poses are used.
    max_residual_ratio
        A table is pushed only if its predicted residual is below this fraction of the
        nominal (uncompensated) residual, unless the operator forces it.
    verify_count
        Pushed targets measured again with the tracker after a push or rollback (spread over
        the targets; 0: no verification run).
    max_outside_coverage
        A push is refused, unless forced, when more than this share (0..1) of the program's
        targets lies outside the joint ranges the model was calibrated on (ADR 0026).
    temperatures
        The joint temperatures the table compensates for when the model has a thermal term
        (ADR 0054): ``reference`` (the model's reference temperatures, the mean of its
        campaign's), ``current`` (read from the robot when pushing; the robot's driver must
        read joint temperatures), or one temperature per joint (°C: the production robot's,
        warm).
    """

    kind: Literal["frames", "targets", "joint"] = "targets"
    targets_file: Path | None = None
    max_residual_ratio: float = Field(default=0.5, gt=0.0, le=1.0)
    verify_count: int = Field(default=10, ge=0, le=10000)
    max_outside_coverage: float = Field(default=0.10, ge=0.0, le=1.0)
    temperatures: Literal["reference", "current"] | Annotated[
        list[Annotated[float, Field(ge=TEMPERATURE_RANGE_C[0], le=TEMPERATURE_RANGE_C[1],
                                    allow_inf_nan=False)]],
        Field(min_length=1)] = "reference"

    @field_validator("temperatures", mode="wrap")
    @classmethod
    def _one_temperatures_error(cls, value: Any, handler: ValidatorFunctionWrapHandler
                                ) -> Any:
        # one message instead of one per member of the union
        try:
            return handler(value)
        except ValidationError:
            lo, hi = TEMPERATURE_RANGE_C
            raise ValueError(f'must be "reference", "current" or a list of joint '
                             f"temperatures in degC between {lo:g} and {hi:g}, got "
                             f"{value!r}") from None


class LoggingConfig(_Model):
    """structlog output: JSON lines (for journald) or a console renderer."""

    level: Literal["debug", "info", "warning", "error"] = "info"
    format: Literal["json", "console"] = "json"


class FleetConfig(_Model):
    """Replication of the store to a shared PostgreSQL fleet database (ADR 0035); off unless
    ``url`` is set.

    ``url`` is a libpq connection URI (``postgresql://user@host/db?sslmode=verify-full&...``;
    TLS and client certificates through its ``ssl*`` parameters); the password belongs in
    ``password_file`` (mode 0600), never in the URL. ``robot_serial`` names the robot in the
    fleet; ``cell_name`` (default: the host name) is for people, the cell's key is an id kept
    in the store. Failed attempts are retried after ``backoff_s``, doubling up to
    ``max_backoff_s``; ``poll_s`` is how often new rows are looked for.
    """

    url: str | None = None
    password_file: Path | None = None
    robot_serial: str | None = None
    cell_name: str | None = None
    batch_rows: int = Field(default=500, ge=1, le=100_000)
    poll_s: float = Field(default=1.0, gt=0.0, le=3600.0)
    connect_timeout_s: float = Field(default=10.0, gt=0.0, le=600.0)
    backoff_s: float = Field(default=1.0, gt=0.0)
    max_backoff_s: float = Field(default=60.0, gt=0.0)

    @model_validator(mode="after")
    def _check(self) -> FleetConfig:
        if self.url is not None:
            if not self.url.startswith(("postgresql://", "postgres://")):
                raise ValueError("url must be a postgresql:// URI")
            if not self.robot_serial:
                raise ValueError("robot_serial is required with url: the fleet lists robots "
                                 "by serial")
        return self


class CheckConfig(_Model):
    """Scheduled drift checks (``robocal check``, ADR 0041): a short measure-only campaign
    against the active compensation's model, judged against these thresholds (mm).

    A check *fails* when its RMS or max error reaches ``fail_rms_mm`` / ``fail_max_mm`` or its
    RMS grew by ``fail_growth_mm`` since the last check of the same model; it *warns* at the
    ``warn_*`` values. A check that does not pass recommends a re-calibration with
    ``--reuse`` on ``reuse_poses`` poses (plus ``reuse_validation_poses`` held out) when a
    refit of the joint offsets and the tracker placement would bring its error back under
    ``warn_rms_mm`` or within ``reuse_ratio`` times the model's own held-out RMS, else a full
    calibration (also from ``full_rms_mm`` on).

    ``warn_rms_ratio`` / ``fail_rms_ratio`` (optional) judge the RMS against the model's own
    held-out RMS as well: a check warns (fails) from that many times it on, when that is
    below the absolute threshold (a model at 0.01 mm is drifting long before 0.1 mm).
    """

    poses: int = Field(default=20, ge=3, le=1000)
    warn_rms_mm: float = Field(default=0.10, gt=0.0)
    fail_rms_mm: float = Field(default=0.20, gt=0.0)
    warn_max_mm: float = Field(default=0.30, gt=0.0)
    fail_max_mm: float = Field(default=0.60, gt=0.0)
    warn_growth_mm: float = Field(default=0.05, gt=0.0)
    fail_growth_mm: float = Field(default=0.15, gt=0.0)
    full_rms_mm: float = Field(default=1.0, gt=0.0)
    warn_rms_ratio: float | None = Field(default=None, gt=1.0, le=1000.0)
    fail_rms_ratio: float | None = Field(default=None, gt=1.0, le=1000.0)
    reuse_ratio: float = Field(default=1.25, ge=1.0, le=10.0)
    reuse_poses: int = Field(default=50, ge=11, le=10_000)
    reuse_validation_poses: int = Field(default=10, ge=1, le=10_000)
    timeout_s: float = Field(default=3600.0, gt=0.0)

    @model_validator(mode="after")
    def _check(self) -> CheckConfig:
        for what in ("rms", "max", "growth"):
            warn, fail = getattr(self, f"warn_{what}_mm"), getattr(self, f"fail_{what}_mm")
            if not warn < fail:
                raise ValueError(f"warn_{what}_mm ({warn}) must be below fail_{what}_mm "
                                 f"({fail})")
        warn_r, fail_r = self.warn_rms_ratio, self.fail_rms_ratio
        if warn_r is not None and fail_r is not None and not warn_r < fail_r:
            raise ValueError(f"warn_rms_ratio ({warn_r}) must be below fail_rms_ratio "
                             f"({fail_r})")
        if self.full_rms_mm < self.fail_rms_mm:
            raise ValueError(f"full_rms_mm ({self.full_rms_mm}) must not be below "
                             f"fail_rms_mm ({self.fail_rms_mm})")
        return self


def _default_data_dir() -> Path:
    state = os.environ.get("STATE_DIRECTORY")
    if state:
        return Path(state.split(":")[0])
    return Path("/var/lib/robocal")


class AppConfig(_Model):
    """The whole daemon configuration."""

    data_dir: Path = Field(default_factory=_default_data_dir)
    robot_description: str = Field(min_length=1)
    cell: str | None = None
    #: a file (mode 0600) holding this site's secret; MODEL.json files the daemon stores are
    #: signed with it (HMAC-SHA256) and only signed ones are loaded
    site_secret_file: Path | None = None
    robot: DriverConfig
    tracker: DriverConfig
    api: ApiConfig = ApiConfig()
    limits: LimitsConfig = LimitsConfig()
    measurement: MeasurementConfig = MeasurementConfig()
    #: the warm-up routine before each campaign's first measured pose; none when absent
    warmup: WarmupConfig | None = None
    fit: FitConfig = FitConfig()
    compensation: CompensationConfig = CompensationConfig()
    logging: LoggingConfig = LoggingConfig()
    fleet: FleetConfig = FleetConfig()
    check: CheckConfig = CheckConfig()

    @property
    def socket_path(self) -> Path | None:
        """Absolute path of the API's Unix socket, or None."""
        s = self.api.socket
        if s is None:
            return None
        return s if s.is_absolute() else self.data_dir / s

    @property
    def db_path(self) -> Path:
        """The SQLite store."""
        return self.data_dir / "robocal.sqlite3"

    def read_token(self) -> str | None:
        """Return the bearer token from ``api.token_file`` (stripped), or None.

        Raises
        ------
        ConfigError
            If the file cannot be read, is readable or writable by group or others, or holds
            fewer than 16 characters.
        """
        path = self.api.token_file
        return None if path is None else _private_text(path, "token")

    def read_viewer_token(self) -> str | None:
        """Return the station's read-only token from ``api.viewer_token_file``, or None.

        Raises
        ------
        ConfigError
            As :meth:`read_token`, or if it equals the operator's token.
        """
        path = self.api.viewer_token_file
        viewer = None if path is None else _private_text(path, "token")
        if viewer is not None and viewer == self.read_token():
            raise ConfigError("the viewer token must differ from the operator's token",
                              source=str(self.api.viewer_token_file))
        return viewer

    def read_site_secret(self) -> bytes | None:
        """Return the site secret from ``site_secret_file`` (stripped, UTF-8), or None.

        Raises
        ------
        ConfigError
            As :meth:`read_token`, for the secret file.
        """
        path = self.site_secret_file
        return None if path is None else _private_text(path, "site secret").encode()


def _private_text(path: Path, what: str) -> str:
    """The stripped text of a secret file only its owner can read or change, >= 16 chars."""
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
        text = path.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read {what} file: {err}", source=str(path)) from err
    if mode & 0o077:
        raise ConfigError(f"{what} file has mode {mode:04o}: others could read or change the "
                          f"{what}; make it the daemon user's alone (chmod 600)",
                          source=str(path))
    if len(text) < 16:
        raise ConfigError(f"{what} must have at least 16 characters", source=str(path))
    return text


def _loc(loc: tuple[Any, ...]) -> str:
    return ".".join(str(p) for p in loc) or "<root>"


def _resolve(data: dict[str, Any], base: Path) -> dict[str, Any]:
    """Make relative paths in ``data`` absolute against ``base`` (before validation)."""
    out = dict(data)

    def fix(value: Any) -> Any:
        if isinstance(value, str) and value and not os.path.isabs(value):
            return str(base / value)
        return value

    for key in ("data_dir", "site_secret_file"):
        if key in out:
            d = out[key]
            # "~/..." is the running user's home: per-user state, e.g. for the simulated cell
            out[key] = fix(os.path.expanduser(d) if isinstance(d, str) else d)
    api = out.get("api")
    if isinstance(api, dict):
        api = dict(api)
        for key in ("token_file", "viewer_token_file"):
            if key in api:
                api[key] = fix(api[key])
        out["api"] = api
    comp = out.get("compensation")
    if isinstance(comp, dict) and "targets_file" in comp:
        comp = dict(comp)
        comp["targets_file"] = fix(comp["targets_file"])
        out["compensation"] = comp
    fleet = out.get("fleet")
    if isinstance(fleet, dict) and "password_file" in fleet:
        out["fleet"] = {**fleet, "password_file": fix(fleet["password_file"])}
    rd = out.get("robot_description")
    if isinstance(rd, str) and rd.endswith((".toml", ".urdf")):
        out["robot_description"] = fix(rd)
    return out


def _errors(source: str, data: Any, base: Path) -> tuple[AppConfig | None, list[str]]:
    if not isinstance(data, dict):
        return None, [f"{source}: the configuration must be a TOML table"]
    try:
        return AppConfig.model_validate(_resolve(data, base)), []
    except ValidationError as err:
        return None, [f"{source}: key {_loc(e['loc'])!r}: {e['msg']}" for e in err.errors()]


def config_errors(path: str | Path) -> list[str]:
    """Return every problem of the configuration file (empty when it is valid)."""
    path = Path(path)
    try:
        data = read_toml(path)
    except ConfigError as err:
        return [str(err)]
    return _errors(str(path), data, path.resolve().parent)[1]


def parse_config(data: dict[str, Any], *, source: str = "<config>",
                 base: Path | None = None) -> AppConfig:
    """Validate a configuration mapping; raise :class:`ConfigError` naming the first bad key."""
    cfg, errs = _errors(source, data, base or Path.cwd())
    if cfg is None:
        more = f" (and {len(errs) - 1} more)" if len(errs) > 1 else ""
        raise ConfigError(errs[0] + more)
    return cfg


def load_config(path: str | Path) -> AppConfig:
    """Read and validate a TOML configuration file.

    Raises
    ------
    ConfigError
        If the file is missing or invalid; the message names the file and the key path.
    """
    path = Path(path)
    return parse_config(read_toml(path), source=str(path), base=path.resolve().parent)


def is_loopback(host: str) -> bool:
    """True if ``host`` names only this machine (``localhost``, 127.0.0.0/8, ``::1``)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def config_warnings(config: AppConfig) -> list[str]:
    """Risky but valid settings an operator should know about (the daemon logs them too)."""
    out = []
    if config.api.tcp_port is not None and not is_loopback(config.api.tcp_host):
        out.append(f"api.tcp_host = {config.api.tcp_host!r} exposes the API beyond this "
                   "machine: anyone who can reach the port can try the token; prefer "
                   "127.0.0.1 behind an authenticating proxy or a firewall")
    url = config.fleet.url
    if url is not None:
        parts = urllib.parse.urlsplit(url)
        if parts.password:
            out.append("fleet.url holds a password: anyone who can read the configuration "
                       "can use it; put it in fleet.password_file (mode 0600)")
        if (parts.hostname and not is_loopback(parts.hostname)
                and "sslmode=verify-full" not in parts.query):
            out.append("fleet.url does not verify the database server "
                       "(add ?sslmode=verify-full&sslrootcert=CA.pem)")
    return out


def config_digest(config: AppConfig) -> str:
    """Short SHA-256 of the validated configuration (recorded with every campaign)."""
    blob = json.dumps(config.model_dump(mode="json"), sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]
