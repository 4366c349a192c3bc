"""Drift checks (issue 31, ADR 0041): the judgement and recommendation, the thresholds in the
configuration, and ``robocal check`` through the API, the CLI, the station and the log."""

from __future__ import annotations

import asyncio
import configparser
import contextlib
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import structlog
from aiohttp.test_utils import TestClient, TestServer
from hypothesis import given
from hypothesis import strategies as hs

from robocal.daemon import checking
from robocal.daemon.api import ApiServer, make_app, openapi_spec
from robocal.daemon.checking import (
    constant_refit_rms_mm,
    judge,
    recommend,
    spread_indices,
)
from robocal.daemon.config import CheckConfig
from robocal.daemon.service import CalibrationService
from robocal.errors import CampaignError, ConfigError
from tests.unit.daemon.test_service import program_plan
from tests.unit.daemon.test_station import TOKEN, VIEWER, _csrf, _sign_in
from tests.unit.report.svgdoc import figures, texts

CFG = CheckConfig(warn_rms_mm=0.05, fail_rms_mm=0.1, warn_max_mm=0.2, fail_max_mm=0.4,
                  warn_growth_mm=0.04, fail_growth_mm=0.1, full_rms_mm=0.5, reuse_poses=20,
                  reuse_validation_poses=6)
DRIFT = (0.0, 0.004)  # deg/day on J2: about 0.017 mm a day at the reflector


# --- the judgement -------------------------------------------------------------------------------
@pytest.mark.parametrize(("rms", "mx", "growth", "verdict"), [
    (0.01, 0.02, None, "pass"),
    (0.049, 0.19, 0.039, "pass"),
    (0.05, 0.1, None, "warn"),          # RMS at the warn threshold
    (0.01, 0.2, None, "warn"),          # max at its warn threshold
    (0.03, 0.1, 0.04, "warn"),          # growth since the last check
    (0.1, 0.1, None, "fail"),
    (0.03, 0.45, 0.0, "fail"),
    (0.03, 0.1, 0.11, "fail"),
])
def test_verdict_is_the_worst_threshold_reached(rms, mx, growth, verdict):
    got, reasons = judge(rms, mx, growth, CFG)
    assert got == verdict
    assert (reasons == []) == (verdict == "pass")
    if verdict == "fail":
        assert "fail threshold" in reasons[0]


def test_relative_rms_thresholds_judge_a_good_model_by_its_own_held_out_rms():
    """A model at 0.009 mm held out drifting to 0.03 mm is still under the absolute warn
    threshold (0.05 mm); with warn/fail at 3x/6x its held-out RMS it warns, then fails, and
    the reason names where the threshold came from. Unset ratios or an unknown model RMS
    leave the absolute thresholds; a ratio never raises a threshold."""
    rel = CFG.model_copy(update={"warn_rms_ratio": 3.0, "fail_rms_ratio": 6.0})
    assert judge(0.03, 0.05, None, CFG, 0.009)[0] == "pass"
    verdict, reasons = judge(0.03, 0.05, None, rel, 0.009)
    assert verdict == "warn" and "3 x the model's held-out 0.0090 mm" in reasons[0]
    assert judge(0.055, 0.06, None, rel, 0.009)[0] == "fail"
    assert judge(0.03, 0.05, None, rel, None)[0] == "pass"
    assert judge(0.03, 0.05, None, rel, 0.05)[0] == "pass"   # 3 x 0.05 > 0.05 absolute
    assert judge(0.05, 0.05, None, rel, 0.05)[0] == "warn"


def test_recommendation_none_reuse_or_full():
    assert recommend("pass", 0.02, None, CFG)["action"] == "none"
    reuse = recommend("warn", 0.07, 0.01, CFG)
    assert reuse["action"] == "reuse" and reuse["poses"] == 20
    assert reuse["validation_poses"] == 6 and "--reuse" in reuse["why"]
    # what a refit of the constant part leaves is too much: the joint-dependent part changed
    assert recommend("fail", 0.2, 0.12, CFG)["action"] == "full"
    # ... unless the model never did better than that (within reuse_ratio)
    assert recommend("fail", 0.2, 0.12, CFG, model_rms_mm=0.11)["action"] == "reuse"
    assert recommend("fail", 0.2, 0.12, CFG, model_rms_mm=0.09)["action"] == "full"
    # beyond full_rms_mm no refit is trusted; too few poses to tell: full
    assert recommend("fail", 0.6, 0.0, CFG)["action"] == "full"
    assert recommend("warn", 0.07, None, CFG)["action"] == "full"


@pytest.mark.parametrize("bad", [
    {"warn_rms_mm": 0.2, "fail_rms_mm": 0.1},
    {"warn_max_mm": 0.5, "fail_max_mm": 0.5},
    {"warn_growth_mm": 0.3},
    {"full_rms_mm": 0.1},
    {"poses": 2},
    {"reuse_poses": 5},
    {"warn_rms": 0.1},
    {"warn_rms_ratio": 4.0, "fail_rms_ratio": 3.0},
    {"warn_rms_ratio": 0.5},
])
def test_thresholds_are_validated(make_config, bad):
    with pytest.raises(ConfigError, match="check"):
        make_config(check=bad)


def test_default_thresholds(make_config):
    c = make_config().check
    assert (c.poses, c.warn_rms_mm, c.fail_rms_mm, c.reuse_poses) == (20, 0.10, 0.20, 50)


@given(hs.integers(1, 40), hs.integers(1, 45), hs.integers(0, 3))
def test_spread_indices_are_distinct_and_start_with_the_held_out(n, count, seed):
    q = np.random.default_rng(seed).uniform(-2, 2, (n, 6))
    first = list(range(n - 1, max(-1, n - 4), -1))
    idx = spread_indices(q, count, first=first)
    assert len(idx) == min(n, count) == len(set(idx))
    assert all(0 <= i < n for i in idx)
    if count < n:
        assert idx[:min(count, len(first))] == first[:count]
    assert idx == spread_indices(q, count, first=first)


# --- on the simulated cell -----------------------------------------------------------------------
def _config(make_config, robot=None, **more):
    return make_config(robot={"options": {"scenario": "constant", **(robot or {})}},
                       tracker={"options": {"scenario": "constant"}},
                       limits={"max_joint_correction_deg": 5.0},
                       compensation={"verify_count": 0},
                       check={**CFG.model_dump(), "poses": 12}, **more)


async def _pushed(svc: CalibrationService) -> str:
    st = await svc.create(program_plan(30, validation=8), actor="t")
    st = await svc.wait(st["id"], ["fitted"], timeout=60)
    assert st["state"] == "fitted", st["reason"]
    await svc.approve(st["id"], actor="t")
    await svc.push(st["id"], actor="t")
    return str(st["id"])


@pytest.fixture
async def svc(make_config):
    s = CalibrationService(_config(make_config))
    await s.start()
    yield s
    await s.stop()


async def _world(svc: CalibrationService):
    world = (await svc.hub.robot()).world
    world.cell.drift_deg_per_day = DRIFT
    return world


async def test_nothing_to_check_before_a_push(svc):
    with pytest.raises(CampaignError, match="no calibration's compensation is active"):
        await svc.checks.start(actor="t")
    assert svc.checks.log.history() == []


async def test_refit_of_the_constant_part_tells_offset_drift_from_other_errors(svc):
    cid = await _pushed(svc)
    cal = svc.fitted_model(cid)
    q = np.radians(np.array([p.q_deg for p in svc.store.poses(cid)]))
    drifted = cal.predict(q + np.radians([0.0, 0.02, -0.01, 0.0, 0.0, 0.0]))
    assert np.sqrt(np.mean(np.sum((drifted - cal.predict(q))**2, axis=1))) > 1e-4
    assert constant_refit_rms_mm(cal, q, drifted) < 0.002
    wobble = cal.predict(q) + np.random.default_rng(0).normal(0, 0.1e-3, (len(q), 3))
    assert 0.1 < constant_refit_rms_mm(cal, q, wobble) < 0.2
    assert constant_refit_rms_mm(cal, q[:5], wobble[:5]) is None  # too few poses


@contextlib.asynccontextmanager
async def _served(make_config, tmp_path, capsys, **config):
    """A service with its API on a Unix socket, and ``cli(*argv)`` running ``robocal check``
    against it: (exit code, stdout, stderr)."""
    from robocal.cli.main import main

    sock = tmp_path / "api.sock"
    svc = CalibrationService(_config(make_config, api={"socket": str(sock)}, **config))
    await svc.start()
    api = ApiServer(svc, svc.config)
    await api.start()

    async def cli(*argv: str) -> tuple[int, str, str]:
        rc = await asyncio.wait_for(asyncio.to_thread(main, ["check", *argv, "--socket",
                                                             str(sock)]), 60)
        out = capsys.readouterr()
        return rc, out.out, out.err

    try:
        yield svc, cli
    finally:
        await api.stop()
        await svc.stop()


async def test_cli_exit_codes_history_and_json(make_config, tmp_path, capsys):
    async with _served(make_config, tmp_path, capsys) as (svc, cli):
        rc, _, err = await cli()
        assert rc == 2 and "no calibration's compensation is active" in err
        cid = await _pushed(svc)
        world = await _world(svc)
        rc, out, _ = await cli()
        assert rc == 0, out
        assert f"check 1 of model constant (campaign {cid}): PASS" in out
        assert "recommendation: nothing to do" in out
        world.cell.sim_days = 3.5  # about 0.06 mm: over warn_rms_mm
        rc, out, err = await cli()
        assert rc == 3, out
        assert re.search(r"PASS|WARN", out).group() == "WARN", out
        assert re.search(r"RMS 0\.0[56]\d\d mm, max", out), out
        assert "re-calibrate with --reuse on 20 poses (+ 6 held out): robocal check " \
               "--recalibrate 2" in out
        assert "drift check 2 warns" in err
        world.cell.sim_days = 8.0  # about 0.14 mm: over fail_rms_mm
        os.environ["JOURNAL_STREAM"] = "8:1234"  # as under systemd: journald priorities
        try:
            rc, out, err = await cli("--json")
        finally:
            del os.environ["JOURNAL_STREAM"]
        assert rc == 4
        doc = json.loads(out[out.index("{\n"):out.rindex("\n}") + 2])  # daemon logs around
        assert doc["verdict"] == "fail" and doc["recommendation"] == "reuse"
        assert doc["detail"]["growth_mm"] > 0.05 and len(doc["detail"]["per_pose_mm"]) == 12
        assert "\n<3>robocal check: drift check 3 FAILED" in "\n" + err
        rc, out, _ = await cli("--history")
        assert rc == 0
        rows = [ln.split() for ln in out.splitlines() if ln[:5].strip().isdigit()]
        assert [(r[0], r[3]) for r in rows] == [("1", "pass"), ("2", "warn"), ("3", "fail")]
        rms = [c["rms_mm"] for c in svc.checks.log.history()]
        assert "\ntrend (RMS mm, oldest first): " + " -> ".join(
            f"{v:.4f}" for v in rms) + "\n" in out
        assert rms == sorted(rms)
        rc, out, _ = await cli("--recalibrate", "3")
        assert rc == 0
        refit = next(ln for ln in out.splitlines() if re.fullmatch("[0-9a-f]{12}", ln))
        assert checking.reuse_source(svc.store, refit) == (cid, "constant")
        assert svc.status(refit)["poses_total"] == 26
        await svc.abort(refit, actor="t")
        rc, _, err = await cli("--recalibrate", "99")
        assert rc == 2 and "no check 99" in err


async def test_a_check_waits_for_a_measuring_campaign_with_wait_idle(make_config, tmp_path,
                                                                     capsys):
    """While another campaign measures, ``robocal check`` refuses at once (exit 2), or with
    ``--wait-idle`` waits for the robot to be free and then checks."""
    async with _served(make_config, tmp_path, capsys,
                       robot={"move_time_s": 0.05}) as (svc, cli):
        await _pushed(svc)
        busy = await svc.create(program_plan(30), actor="t")  # ~1.5 s of moves
        assert svc.measuring() == busy["id"]
        rc, _, err = await cli()
        assert rc == 2 and f"campaign {busy['id']} is measuring" in err
        assert svc.checks.log.history() == []
        rc, out, err = await cli("--wait-idle", "60")
        assert rc == 0, err
        assert f"campaign {busy['id']} is measuring; waiting up to" in err
        assert svc.status(busy["id"])["poses_measured"] == 30  # it finished first
        (check,) = svc.checks.log.history()
        assert check["state"] == "done" and "PASS" in out


async def test_api_event_log_and_station_show_the_latest_check_and_trend(svc, monkeypatch):
    cap = structlog.testing.LogCapture()
    structlog.configure(processors=[cap])
    # a fresh logger: structlog caches one on first use, under an earlier test's configuration
    monkeypatch.setattr(checking, "_log", structlog.get_logger("robocal.daemon.checking"))
    try:
        await _pushed(svc)
        world = await _world(svc)
        async with TestClient(TestServer(make_app(svc, token=TOKEN,
                                                  viewer_token=VIEWER))) as http:
            auth = {"Authorization": f"Bearer {TOKEN}"}
            for day in (0.0, 8.0):
                world.cell.sim_days = day
                r = await http.post("/checks", json={}, headers=auth)
                assert r.status == 201, await r.text()
                started = await r.json()
                assert started["state"] == "measuring"
                await svc.checks.wait(started["id"], timeout=60)
            r = await http.get("/checks/2", headers=auth)
            last = await r.json()
            assert last["verdict"] == "fail" and last["state"] == "done"
            listed = await (await http.get("/checks?limit=1", headers=auth)).json()
            assert [c["id"] for c in listed] == [2]
            assert (await http.get("/checks/x", headers=auth)).status == 404
            assert (await http.get("/checks/7", headers=auth)).status == 404
            r = await http.post("/checks", json={"plan": {"poses": []}}, headers=auth)
            assert r.status == 422
            page = await _sign_in(http, VIEWER, "vic")
        assert 'id="run-check"' not in page and 'id="recalibrate"' not in page  # read only
        async with TestClient(TestServer(make_app(svc, token=TOKEN,
                                                  viewer_token=VIEWER))) as op:
            mine = await _sign_in(op, TOKEN, "olga")
            assert 'id="run-check"' in mine and 'name="check" value="2"' in mine
            r = await op.post("/station/checks/recalibrate",
                              data={"csrf": _csrf(mine), "check": "2"})
            assert r.status == 200 and r.url.path.startswith("/station/campaigns/")
            refit = r.url.path.rsplit("/", 1)[-1]
            assert checking.reuse_source(svc.store, refit) == (last["model_campaign"],
                                                               "constant")
            await svc.abort(refit, actor="t")
            r = await op.post("/station/checks/run", data={"csrf": _csrf(mine)})
            assert r.status == 200, await r.text()
            third = svc.checks.log.get(3)
            assert r.url.path == f"/station/campaigns/{third['campaign']}"
            assert (await svc.checks.wait(3, timeout=60))["verdict"] == "fail"
        assert 'id="checks"' in page and "Latest check 2" in page
        assert '<span class="badge bad">fail</span>' in page
        assert "re-calibrate with --reuse (20 poses + 6 held out)" in page
        trend = f"{svc.checks.log.get(1)['rms_mm']:.4f} mm → {last['rms_mm']:.4f} mm"
        assert trend in page
    finally:
        structlog.reset_defaults()
    failed = [e for e in cap.entries if e["event"] == "drift check failed"]
    assert len(failed) == 2 and failed[0]["log_level"] == "error"
    assert failed[0]["recommendation"] == "reuse"
    events = [e for e in svc.events.history() if e["kind"] == "check"]
    assert [(e["state"], e.get("verdict")) for e in events] == [
        ("measuring", None), ("done", "pass"), ("measuring", None), ("done", "fail"),
        ("measuring", None), ("done", "fail")]
    assert "/checks/{check}/recalibrate" in openapi_spec()["paths"]
    audit = [a for a in svc.audit() if a["action"] == "check.done"]
    assert [a["detail"]["verdict"] for a in audit] == ["pass", "fail", "fail"]
    # the model's report gets the checks (its Drift checks section)
    record = svc.report_records()[last["model_campaign"]]
    assert [c["verdict"] for c in record["checks"]] == ["pass", "fail", "fail"]
    assert record["check_thresholds"] == {"warn_rms_mm": 0.05, "fail_rms_mm": 0.1}


def test_report_section_shows_the_checks_and_their_trend(tmp_path):
    from robocal.report import add_checks_section

    (tmp_path / "report.html").write_text("<html><body><main><section id=\"verdict\">ok"
                                          "</section></main></body></html>")
    (tmp_path / "report.json").write_text(json.dumps({"format": "robocal.report/1"}))
    checks = [{"id": i + 1, "created": f"2026-11-2{i}T05:30:00+00:00", "state": "done",
               "verdict": v, "rms_mm": r, "max_mm": 2 * r, "n": 20, "growth_mm": None,
               "recommendation": a}
              for i, (v, r, a) in enumerate([("pass", 0.01, "none"), ("pass", 0.03, "none"),
                                             ("warn", 0.06, "reuse")])]
    th = {"warn_rms_mm": 0.05, "fail_rms_mm": 0.1}
    assert add_checks_section(tmp_path, checks[:2], thresholds=th)
    assert add_checks_section(tmp_path, checks, thresholds=th)
    assert not add_checks_section(tmp_path, checks, thresholds=th)  # shows them already
    page = (tmp_path / "report.html").read_text()
    assert page.count('<section id="checks">') == 1
    section = page[page.index('<section id="checks">'):]
    assert "Latest: check 3" in section and "<b>warn</b>" in section
    assert "re-calibrate with --reuse" in section and "0.0600" in section
    assert section.count("<tr>") == 4
    (plot,) = figures(section)  # RMS and max of each check against the thresholds
    assert {"RMS", "max", "warn rms", "fail rms", "check"} <= set(texts(plot))
    assert json.loads((tmp_path / "report.json").read_text())["checks"] == checks
    assert not add_checks_section(tmp_path / "none", [])


def test_the_systemd_units_run_a_check_the_cli_takes():
    from robocal.cli.main import build_parser

    deploy = Path(__file__).resolve().parents[3] / "deploy" / "systemd"
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]
    unit.read(deploy / "robocal-check.service")
    argv = unit["Service"]["ExecStart"].split()
    assert argv[0].endswith("/robocal") and argv[1] == "check"
    args = build_parser("check", lazy=True).parse_args(argv[1:])
    assert args.config == Path("/etc/robocal/config.toml") and not args.no_wait
    # the unit outlives the longest wait for the robot plus the check itself
    assert float(unit["Service"]["TimeoutStartSec"]) > args.wait_idle + args.wait_timeout
    assert unit["Service"]["Type"] == "oneshot"
    assert unit["Unit"]["Requisite"] == "robocal.service"
    timer = configparser.ConfigParser(strict=False, interpolation=None)
    timer.optionxform = str  # type: ignore[assignment,method-assign]
    timer.read(deploy / "robocal-check.timer")
    assert timer["Timer"]["Unit"] == "robocal-check.service"
    assert timer["Timer"]["OnCalendar"] and timer["Timer"]["Persistent"] == "true"


async def test_a_check_whose_campaign_ends_unmeasured_fails_loudly(svc):
    await _pushed(svc)
    started = await svc.checks.start(actor="t")
    await svc.abort(started["campaign"], actor="t", reason="tracker knocked")
    c = await svc.checks.wait(started["id"], timeout=30)
    assert c["state"] == "failed" and c["verdict"] == "fail"
    assert "aborted" in c["detail"]["reason"] and c["rms_mm"] is None
    failed = [e for e in svc.events.history() if e["kind"] == "check"][-1]
    assert failed["state"] == "failed" and "tracker knocked" in failed["reason"]


async def test_a_check_cut_by_a_restart_is_measured_and_judged_after_it(make_config):
    cfg = _config(make_config, robot={"move_time_s": 0.003})
    svc = CalibrationService(cfg)
    await svc.start()
    try:
        cid = await _pushed(svc)
        started = await svc.checks.start(actor="timer")
    finally:
        await svc.stop()  # while the check measures: its campaign stays running
    again = CalibrationService(cfg)
    await again.start()
    try:
        assert again.checks.log.get(started["id"])["state"] == "measuring"
        c = await again.checks.wait(started["id"], timeout=60)
        assert c["state"] == "done" and c["verdict"] == "pass", c
        assert c["model_campaign"] == cid and c["n"] == 12
    finally:
        await again.stop()


async def _planned(svc: CalibrationService, plan) -> str:
    """Calibrated from a planned campaign (the robot ends where the cell's moves are safe),
    approved and pushed."""
    st = await svc.wait((await svc.create(plan, actor="t"))["id"], ["fitted"], timeout=60)
    await svc.approve(st["id"], actor="t")
    await svc.push(st["id"], actor="t")
    return str(st["id"])


def _from_home(poses, home) -> bool:
    """Every measured pose is visited from ``home`` (a via pose right before it)."""
    return all(p.purpose == "via" and p.q_deg == tuple(home) for p in poses[::2]) and \
        all(p.measure for p in poses[1::2]) and len(poses) % 2 == 0


async def test_checks_and_reuse_refits_of_a_planned_campaign_go_through_its_home(svc,
                                                                                 real_plan):
    await _planned(svc, real_plan)
    home = real_plan["motion"]["home_deg"]
    refit = (await svc.checks.recalibrate(actor="t"))["id"]
    assert _from_home(svc.store.poses(refit), home)
    st = await svc.wait(refit, ["fitted"], timeout=60)
    assert st["selected_model"] == "reuse", st["reason"]
    await svc.approve(refit, actor="t")
    await svc.push(refit, actor="t")
    # the refit's own plan is bare: its check and its next refit go through the home of the
    # planned campaign it refits
    c = await svc.checks.wait((await svc.checks.start(actor="t"))["id"], timeout=60)
    assert c["state"] == "done" and c["model_campaign"] == refit
    assert _from_home(svc.store.poses(c["campaign"]), home)
    again = (await svc.checks.recalibrate(actor="t"))["id"]
    assert _from_home(svc.store.poses(again), home)
    await svc.abort(again, actor="t")


async def test_a_check_measures_the_poses_of_a_plan_given(svc, real_plan):
    await _planned(svc, real_plan)
    c = await svc.checks.wait((await svc.checks.start(actor="t", plan=real_plan))["id"],
                              timeout=60)
    assert c["state"] == "done" and c["n"] == 25  # every measured pose of the plan
    poses = svc.store.poses(c["campaign"])
    assert [p.q_deg for p in poses] == [tuple(p["joints_deg"]) for p in real_plan["poses"]]
