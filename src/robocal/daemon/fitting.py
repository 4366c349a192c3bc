"""Identification off the event loop: a picklable fit job run in a worker process or thread.

:func:`run_fit_job` takes plain data (the robot description as a dict, measurements as
lists in mm/deg) and returns plain data (summaries, MODEL.json texts, report paths), so it can
run in a ``spawn`` worker process: the event loop keeps answering the API and pinging the
systemd watchdog while scipy works. Everything numerical is :mod:`robocal.identification`'s;
this module only arranges the data and calls it.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import datetime as dt
import json
import math
import multiprocessing
import re
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from robocal._core.files import atomic_write_text, json_default
from robocal._core.measurements import MeasurementSet
from robocal._core.model_names import CPA, NOMINAL
from robocal.daemon.schemas import Measurement
from robocal.errors import ConfigError, IdentificationError, RobocalError
from robocal.kinematics import CalibratedModel, RobotDescription

if TYPE_CHECKING:  # imported where used: the daemon starts without identification
    from robocal.identification import Accuracy, CPAResult, FitOptions, FitResult

__all__ = ["LATER", "FitRunner", "RowsByPurpose", "build_fit_job", "measurement_set",
           "rows_by_purpose", "run_fit_job", "run_report_job"]

_CPA = re.compile(r"^cpa-j(\d+)$")

#: ``report`` value of a fit job whose report is rendered afterwards by :func:`run_report_job`
LATER = "later"
# reports left pending by fit jobs in this process: token -> _write_report's arguments
_PENDING_REPORTS: dict[str, tuple[Any, ...]] = {}


def load_model(text: str, *, source: str, secret: bytes | None,
               nominal: RobotDescription | None) -> CalibratedModel:
    """A stored MODEL.json verified: content hash, site signature (with ``secret``) and the
    robot description against the daemon's ``nominal`` one (:meth:`CalibratedModel.from_dict`).
    """
    return CalibratedModel.from_dict(json.loads(text), source=source, secret=secret,
                                     nominal=nominal)


def sign_fits(fits: dict[str, tuple[dict[str, Any], str | None]], secret: bytes | None,
              robot: RobotDescription) -> dict[str, tuple[dict[str, Any], str | None]]:
    """Fitted models (summary, MODEL.json text) signed with the site ``secret`` (unchanged
    without one); a model that does not verify is kept out with the error in its summary."""
    if secret is None:
        return fits
    out: dict[str, tuple[dict[str, Any], str | None]] = {}
    for name, (summary, text) in fits.items():
        if text is None:
            out[name] = (summary, None)
            continue
        try:
            cal = load_model(text, source=f"fitted model {name!r}", secret=None, nominal=robot)
        except ConfigError as err:
            out[name] = ({**summary, "error": str(err)}, None)
            continue
        out[name] = (summary, json.dumps(cal.to_dict(secret=secret), default=json_default))
    return out


def temperature_log(rows: Sequence[Measurement]) -> dict[str, Any]:
    """The report's joint temperatures: ``joint_temps`` (°C per joint, every row that has
    them, in pose order) and ``joint_temps_t_s`` (s since the first of them); empty when no
    row has them."""
    warm = [r for r in rows if r.temps_c]
    if not warm:
        return {}
    t = [dt.datetime.fromisoformat(r.measured_at).timestamp() for r in warm]
    return {"joint_temps": [list(r.temps_c) for r in warm],
            "joint_temps_t_s": [v - t[0] for v in t]}


def measurement_set(rows: Sequence[Measurement], *, commanded: bool = False
                    ) -> MeasurementSet:
    """Stored rows (mm, deg) as a :class:`MeasurementSet` (SI), pose ids ``P<index>``.

    Joints are the actual ones read back from the controller, or the commanded ones; joint
    temperatures come along when every row has them.
    """
    if not rows:
        raise IdentificationError("no measurements")
    q = np.radians(np.array([r.q_cmd_deg if commanded else r.q_act_deg for r in rows],
                            dtype=float))
    p = np.array([r.p_mm for r in rows], dtype=float) * 1e-3
    sig = None
    if all(r.sigma_mm is not None for r in rows):
        sig = np.array([r.sigma_mm for r in rows], dtype=float) * 1e-3
        if np.any(sig <= 0):
            sig = None
    temps = None  # joint temperatures where every row has them (ADR 0042)
    if all(len(r.temps_c) == q.shape[1] for r in rows):
        temps = np.array([r.temps_c for r in rows], dtype=float)
    return MeasurementSet(q=q, p=p, sigma=sig, pose_id=tuple(f"P{r.pose_idx:04d}" for r in rows),
                          temps=temps)


def fit_options(options: Mapping[str, Any] | None) -> FitOptions:
    """``robocal.identification.FitOptions(**options)``; ConfigError naming a bad option."""
    from robocal.identification import FitOptions

    opts = dict(options or {})
    for key, value in opts.items():  # TOML arrays arrive as lists; FitOptions wants tuples
        if isinstance(value, list):
            opts[key] = tuple(value)
    try:
        return FitOptions(**opts)
    except TypeError as err:
        raise ConfigError(str(err), source="fit.options") from err
    except ConfigError as err:
        raise ConfigError(str(err), source="fit.options") from err


def build_fit_job(*, campaign: str, robot: RobotDescription, rows: Sequence[Measurement],
                  models: Sequence[str], cpa: bool, out_dir: Path | None,
                  report: bool | str,
                  log: Mapping[str, Any] | None = None,
                  options: Mapping[str, Any] | None = None,
                  acceptance: Mapping[str, Any] | None = None,
                  model_data: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Plain-data description of one campaign's fit (picklable); ``model_data`` goes into
    every MODEL.json's ``data`` section (provenance, outside the content hash); ``report``:
    write it (True), not (False) or leave it to :func:`run_report_job` (:data:`LATER`)."""
    return {
        "model_data": dict(model_data or {}),
        "acceptance": dict(acceptance or {}),
        "options": dict(options or {}),
        "campaign": campaign,
        "robot": robot.to_dict(),
        "rows": [r.model_dump(mode="json") for r in rows],
        "models": list(models),
        "cpa": cpa,
        "out_dir": None if out_dir is None else str(out_dir),
        "report": report,
        "log": dict(log or {}),
    }


def _rows(job: Mapping[str, Any]) -> list[Measurement]:
    return [Measurement.model_validate(r) for r in job["rows"]]


def _summary(name: str, cal: CalibratedModel, seconds: float, *,
             train: Accuracy | None = None, validation: Accuracy | None = None,
             outliers: Sequence[str] = (), status: str | None = None,
             details: Mapping[str, Any] | None = None) -> tuple[dict[str, Any], str]:
    """One model's summary (mm) and its MODEL.json text."""
    summary: dict[str, Any] = {
        "model": name,
        "seconds": round(seconds, 3),
        "train": None if train is None else train.to_dict(),
        "validation": None if validation is None else validation.to_dict(),
        "outliers": [str(x) for x in outliers],
    }
    if status is not None:
        summary["status"] = status
    if details is not None:
        summary["details"] = json.loads(json.dumps(details, default=json_default))
    summary["model_id"] = cal.model_id
    summary["n_params"] = int(cal.params.size)
    return summary, json.dumps(cal.to_dict(), default=json_default)


def _fit_summary(name: str, res: FitResult, seconds: float) -> tuple[dict[str, Any], str]:
    """Summary of an identification :class:`FitResult`."""
    return _summary(name, res.calibrated, seconds, train=res.train, validation=res.validation,
                    outliers=res.outliers, status=res.status, details=res.summary())


def _cpa_summary(res: CPAResult, seconds: float) -> tuple[dict[str, Any], str]:
    """Summary of a :class:`CPAResult` (no training accuracy, no outliers, no status)."""
    return _summary(CPA, res.calibrated, seconds, validation=res.validation,
                    details=res.summary())


@dataclasses.dataclass(frozen=True)
class RowsByPurpose:
    """A campaign's measurements by what they are for (plan purposes).

    ``calibration`` trains the models: the rows marked ``calibration``, or, in a plan with
    no such marks, every row that is not for validation, ISO 9283 or CPA. ``iso`` holds
    ``iso-Pk`` rows, ``cpa`` the ``cpa-jK`` sweeps by K (1-based joint number).
    """

    calibration: list[Measurement]
    validation: list[Measurement]
    iso: list[Measurement]
    cpa: dict[int, list[Measurement]]


def rows_by_purpose(rows: Sequence[Measurement]) -> RowsByPurpose:
    """Split ``rows`` by purpose; the one reader of campaign data for fits and reports."""
    calibration: list[Measurement] = []
    validation: list[Measurement] = []
    iso: list[Measurement] = []
    unmarked: list[Measurement] = []
    cpa: dict[int, list[Measurement]] = {}
    for r in rows:
        purpose = r.purpose.lower()
        m = _CPA.match(purpose)
        if m:
            cpa.setdefault(int(m.group(1)), []).append(r)
        elif purpose == "calibration":
            calibration.append(r)
        elif purpose == "validation":
            validation.append(r)
        elif purpose.startswith("iso-"):
            iso.append(r)
        else:
            unmarked.append(r)
    # plans without purposes: whatever is not held out calibrates
    return RowsByPurpose(calibration=calibration or unmarked, validation=validation, iso=iso,
                         cpa=dict(sorted(cpa.items())))


def _cpa_sets(by_purpose: RowsByPurpose) -> dict[int, MeasurementSet]:
    by_joint = by_purpose.cpa
    # CPA's premise is that only the swept joint moves: use the commanded sweep (the actual
    # joints differ by the controller's repeatability in every joint).
    return {j: measurement_set(rs, commanded=True) for j, rs in sorted(by_joint.items())}


def _call_cpa(robot: RobotDescription, sweeps: dict[int, MeasurementSet],
              validation: MeasurementSet | None, baseline: CalibratedModel | None,
              options: FitOptions | None = None) -> CPAResult:
    """``identification.cpa_fit`` on the sweeps (plan purposes ``cpa-jK``, K 1-based); its
    polish uses the fit options (tracker noise, outlier test)."""
    from robocal.identification import cpa_fit

    return cpa_fit(robot, [(j - 1, ms) for j, ms in sweeps.items()], validation=validation,
                   baseline=baseline, options=options)


def run_fit_job(job: Mapping[str, Any]) -> dict[str, Any]:
    """Fit every requested model (and CPA when the plan has sweeps); write files; summarise.

    Returns
    -------
    dict
        ``fits``: model -> (summary, MODEL.json text); ``errors``: model -> message;
        ``selected_hint``: the model with the lowest held-out RMS; ``report``: paths or a
        skip reason; ``seconds``.
    """
    t_start = time.perf_counter()
    if job.get("reuse"):
        return _run_reuse_job(job, t_start)
    from robocal.identification import accuracy, fit

    robot = RobotDescription.from_dict(job["robot"], source="fit job")
    rows = _rows(job)
    by_purpose = rows_by_purpose(rows)
    train = measurement_set(by_purpose.calibration)
    validation = measurement_set(by_purpose.validation) if by_purpose.validation else None
    opts = fit_options(job.get("options"))
    results: dict[str, FitResult | CPAResult | CalibratedModel] = {}
    fits: dict[str, tuple[dict[str, Any], str]] = {}
    errors: dict[str, str] = {}
    nominal: CalibratedModel | None = None
    for name in job["models"]:
        t0 = time.perf_counter()
        try:
            res = fit(robot, train, model=name, options=opts, validation=validation)
        except RobocalError as err:
            errors[name] = f"{type(err).__name__}: {err}"
            continue
        results[name] = res
        fits[name] = _fit_summary(name, res, time.perf_counter() - t0)
        if nominal is None:
            # every fit carries the same nominal baseline (base and reflector fitted)
            nominal = results[NOMINAL] = res.baseline
            fits[NOMINAL] = _summary(
                NOMINAL, nominal, 0.0, train=accuracy(nominal, train),
                validation=None if validation is None else accuracy(nominal, validation))
    sweeps = _cpa_sets(by_purpose)
    if job.get("cpa") and sweeps:
        t0 = time.perf_counter()
        try:
            cpa = _call_cpa(robot, sweeps, validation, nominal, opts)
            results[CPA] = cpa
            fits[CPA] = _cpa_summary(cpa, time.perf_counter() - t0)
        except (RobocalError, ValueError) as err:
            errors[CPA] = f"{type(err).__name__}: {err}"
    best = None
    best_rms = math.inf
    for name, (summ, _) in fits.items():
        if name in (NOMINAL, CPA) or name not in job["models"]:
            continue
        v = summ.get("validation") or summ.get("train") or {}
        rms = v.get("rms_mm")
        if isinstance(rms, int | float) and rms < best_rms:
            best, best_rms = name, float(rms)
    if job.get("model_data"):
        fits = {name: (summ, _with_data(mj, job["model_data"]))
                for name, (summ, mj) in fits.items()}
    out: dict[str, Any] = {"fits": fits, "errors": errors, "selected_hint": best,
                           "report": None}
    out_dir = job.get("out_dir")
    if out_dir:
        d = Path(out_dir)
        d.mkdir(parents=True, exist_ok=True)
        for name, (_, mj) in fits.items():
            atomic_write_text(d / f"MODEL-{name}.json", mj)
        if job.get("report") == LATER:
            # rendered by the next job of this worker (run_report_job): the fits are
            # stored and announced without waiting for the figures
            token = f"{job.get('campaign', '')}-{time.monotonic_ns()}"
            _PENDING_REPORTS[token] = (dict(job), robot, results, train, validation, d)
            out["report"] = {"pending": token}
        elif job.get("report"):
            out["report"] = _write_report(job, robot, results, train, validation, d)
    out["seconds"] = round(time.perf_counter() - t_start, 3)
    return out


#: The name of a reuse refit's model in a campaign's fits (ADR 0041).
REUSE = "reuse"


def _run_reuse_job(job: Mapping[str, Any], t_start: float) -> dict[str, Any]:
    """A re-calibration with ``--reuse`` (``job["reuse"]``: the earlier MODEL.json as a
    dict): :func:`robocal.identification.refit_frozen` on the calibration rows, judged on
    the validation rows; one model, :data:`REUSE`, proposed. No report is written."""
    from robocal.identification import refit_frozen

    robot = RobotDescription.from_dict(job["robot"], source="fit job")
    by_purpose = rows_by_purpose(_rows(job))
    train = measurement_set(by_purpose.calibration)
    validation = measurement_set(by_purpose.validation) if by_purpose.validation else None
    previous = CalibratedModel.from_dict(dict(job["reuse"]), source="reused model",
                                         nominal=robot)
    t0 = time.perf_counter()
    fits: dict[str, tuple[dict[str, Any], str]] = {}
    errors: dict[str, str] = {}
    try:
        res = refit_frozen(previous, train, options=fit_options(job.get("options")),
                           validation=validation)
        res.calibrated.data["reused"] = previous.model_id
        fits[REUSE] = _fit_summary(REUSE, res, time.perf_counter() - t0)
    except RobocalError as err:
        errors[REUSE] = f"{type(err).__name__}: {err}"
    if job.get("model_data"):
        fits = {name: (summ, _with_data(mj, job["model_data"]))
                for name, (summ, mj) in fits.items()}
    if job.get("out_dir") and fits:
        d = Path(job["out_dir"])
        d.mkdir(parents=True, exist_ok=True)
        atomic_write_text(d / f"MODEL-{REUSE}.json", fits[REUSE][1])
    return {"fits": fits, "errors": errors, "selected_hint": REUSE if fits else None,
            "reused": previous.model_id, "report": {"skipped": "a reuse refit has no report"},
            "seconds": round(time.perf_counter() - t_start, 3)}


def run_report_job(token: str) -> dict[str, Any]:
    """Write the report a :func:`run_fit_job` with ``report = LATER`` left pending (in the
    same worker: its fitted results stay there, nothing is pickled); returns the paths or a
    skip reason."""
    pending = _PENDING_REPORTS.pop(token, None)
    if pending is None:
        return {"skipped": "report not written: the fit worker was restarted"}
    return _write_report(*pending)


def _with_data(text: str, extra: Mapping[str, Any]) -> str:
    """A MODEL.json text with ``extra`` added to its ``data`` section (not hashed)."""
    doc = json.loads(text)
    doc["data"] = {**(doc.get("data") or {}), **extra}
    return json.dumps(doc, default=json_default)


def _write_report(job: Mapping[str, Any], robot: RobotDescription,
                  results: dict[str, FitResult | CPAResult | CalibratedModel],
                  train: MeasurementSet, validation: MeasurementSet | None,
                  out_dir: Path) -> dict[str, Any]:
    """Write ``report.html`` and ``report.json`` into ``out_dir``; a failure is reported, not
    raised (the fit stands without its report)."""
    from robocal.report import Acceptance, MeasurementLog, ReportInput, write_report

    try:
        iso_rows = rows_by_purpose(_rows(job)).iso
        selected = job.get("selected")
        inp = ReportInput(
            models=results, calibration=train, validation=validation, robot=robot,
            campaign_id=str(job.get("campaign", "")),
            log=MeasurementLog.from_mapping(job["log"]) if job.get("log") else None,
            selected=selected if selected in results else None,
            iso_measurements=measurement_set(iso_rows, commanded=True) if iso_rows else None,
            iso_purposes=[r.purpose for r in iso_rows],
            acceptance=Acceptance.from_mapping(job.get("acceptance") or None))
        html_path, json_path = write_report(inp, out_dir)
    except (RobocalError, OSError, ValueError) as err:
        reason = f"report failed: {type(err).__name__}: {err}"
        # structlog imported here: `robocal report CAMPAIGN` reads rows through this module
        # and would pay ~0.07 s (structlog.dev and rich) for a logger it never uses
        import structlog

        structlog.get_logger(__name__).warning("report failed", error=reason)
        return {"skipped": reason}
    return {"paths": {"html": str(html_path), "json": str(json_path)}}


def _worker_init() -> None:  # pragma: no cover - runs in the worker process
    """Log warnings only, to stderr; die with the daemon (no orphan after a kill -9)."""
    import logging
    import sys

    import structlog

    structlog.configure(
        processors=[structlog.processors.add_log_level,
                    structlog.processors.TimeStamper(fmt="iso", utc=True),
                    structlog.processors.JSONRenderer()],
        wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING),
        logger_factory=structlog.WriteLoggerFactory(file=sys.stderr))
    with contextlib.suppress(Exception):
        import ctypes
        import signal

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGKILL)
    # PR_SET_PDEATHSIG fires when the *thread* that started the worker ends, which is not
    # always the daemon's life; also watch the parent's sentinel and leave when it closes.
    parent = multiprocessing.parent_process()
    if parent is not None:
        import os
        import threading
        from multiprocessing.connection import wait

        def _leave_with_parent() -> None:
            wait([parent.sentinel])
            os._exit(0)

        threading.Thread(target=_leave_with_parent, name="robocal-parent-watch",
                         daemon=True).start()


class FitRunner:
    """Runs fit jobs in a ``spawn`` worker process (default) or a thread.

    Parameters
    ----------
    executor : {"process", "thread"}
        Where fits run.
    timeout_s : float
        A fit taking longer fails with :class:`IdentificationError`.
    """

    def __init__(self, *, executor: str = "process", timeout_s: float = 1800.0) -> None:
        self.executor_kind = executor
        self.timeout_s = timeout_s
        self._pool: concurrent.futures.Executor | None = None

    def _executor(self) -> concurrent.futures.Executor:
        if self._pool is None:
            if self.executor_kind == "process":
                self._pool = concurrent.futures.ProcessPoolExecutor(
                    max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_worker_init)
            else:
                self._pool = concurrent.futures.ThreadPoolExecutor(
                    max_workers=1, thread_name_prefix="robocal-fit")
        return self._pool

    async def run(self, job: Mapping[str, Any]) -> dict[str, Any]:
        """Run :func:`run_fit_job` off the event loop and return its result."""
        return await self._call(run_fit_job, dict(job))

    async def render(self, token: str) -> dict[str, Any]:
        """Run :func:`run_report_job` in the fit worker (one worker: the one that fitted)."""
        return await self._call(run_report_job, token)

    async def _call(self, fn: Callable[[Any], dict[str, Any]], arg: Any) -> dict[str, Any]:
        import asyncio  # here: robocal report CAMPAIGN imports this module, not asyncio

        loop = asyncio.get_running_loop()
        fut = loop.run_in_executor(self._executor(), fn, arg)
        try:
            async with asyncio.timeout(self.timeout_s):
                return await fut
        except TimeoutError as err:
            self.shutdown()
            raise IdentificationError(f"fit took longer than {self.timeout_s} s") from err
        except concurrent.futures.process.BrokenProcessPool as err:
            self._pool = None
            raise IdentificationError(f"the fit worker died: {err}") from err

    def shutdown(self) -> None:
        """Stop the worker (a fit in progress is abandoned)."""
        pool, self._pool = self._pool, None
        if pool is None:
            return
        procs = []
        if isinstance(pool, concurrent.futures.ProcessPoolExecutor):
            procs = list(getattr(pool, "_processes", {}).values())
            for proc in procs:
                with contextlib.suppress(Exception):
                    proc.kill()
        pool.shutdown(wait=False, cancel_futures=True)
        # reap the killed worker here (it is gone within milliseconds of SIGKILL): left to
        # init, it stays a zombie of this process until the daemon exits
        for proc in procs:
            with contextlib.suppress(Exception):
                proc.join(timeout=5.0)
