"""``robocal campaign watch`` against an in-process daemon on a Unix socket (mock drivers).

The watch follows only the run that is current when it starts, exits 0 when the campaign got
where it was going, 1 on a fault or abort (printing the reason); on a paused campaign it waits
for the resume (3 at once with --exit-on-pause).
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest

from robocal.cli.main import main
from robocal.daemon.api import ApiServer
from robocal.daemon.service import CalibrationService
from tests._waiting import eventually

from .conftest import random_plan


async def _watch(sock: Path, cid: str, *extra: str, capsys: Any) -> tuple[int, str]:
    rc = await asyncio.wait_for(
        asyncio.to_thread(main, ["campaign", "watch", cid, "--socket", str(sock), *extra]), 60)
    return rc, capsys.readouterr().out


async def _served(make_config: Any, tmp_path: Path, **sections: Any
                  ) -> tuple[CalibrationService, ApiServer, Path]:
    sock = tmp_path / "api.sock"
    cfg = make_config(api={"socket": str(sock)}, **sections)
    svc = CalibrationService(cfg)
    await svc.start()
    api = ApiServer(svc, cfg)
    await api.start()
    return svc, api, sock


async def test_watch_after_pause_and_resume_follows_the_current_run(make_config, tmp_path,
                                                                    capsys):
    svc, api, sock = await _served(
        make_config, tmp_path, robot={"options": {"move_time_s": 0.01}})
    try:
        st = await svc.create(random_plan(40, seed=3), actor="test")
        cid = st["id"]
        await svc.pause(cid, actor="test", reason="operator break")
        rc, out = await _watch(sock, cid, "--exit-on-pause", capsys=capsys)
        assert rc == 3, out
        assert "operator break" in out and "campaign resume" in out
        assert "ETA" not in out  # a paused campaign has no time of arrival
        await svc.resume(cid, actor="test")
        # the earlier "paused" event is history: the watch must follow the run to its end
        rc, out = await _watch(sock, cid, capsys=capsys)
        assert rc == 0, out
        assert svc.status(cid)["state"] == "fitted"
        assert "held-out RMS: constant" in out and "campaign approve" in out
        assert "40/40" in out and "poses/min" in out and "beam losses" in out
        rc = await asyncio.wait_for(asyncio.to_thread(
            main, ["campaign", "approve", cid, "--socket", str(sock)]), 30)
        out = capsys.readouterr().out
        assert rc == 0 and "approved model constant (held-out RMS" in out
    finally:
        await api.stop()
        await svc.stop()


async def test_watch_exits_non_zero_with_the_reason_on_a_fault(make_config, tmp_path, capsys):
    svc, api, sock = await _served(
        make_config, tmp_path, tracker={"options": {"beam_break_rate": 1.0}},
        measurement={"retries": 2, "backoff_s": 0.4, "max_backoff_s": 0.4})
    try:
        st = await svc.create(random_plan(10, seed=4), actor="test")
        rc, out = await _watch(sock, st["id"], "--json", capsys=capsys)
        lines = [json.loads(x) for x in out.splitlines() if x.startswith("{")]
        assert rc == 1
        assert lines[-1]["kind"] == "summary" and lines[-1]["state"] == "faulted"
        assert "no valid reading" in lines[-1]["reason"]
        assert sum(1 for e in lines if e.get("kind") == "retry") >= 1
        # started after the fault, the plain watch still says why
        rc, out = await _watch(sock, st["id"], capsys=capsys)
        assert rc == 1 and "faulted: " in out and "no valid reading" in out
    finally:
        await api.stop()
        await svc.stop()


async def test_watch_of_an_aborted_campaign(make_config, tmp_path, capsys):
    svc, api, sock = await _served(make_config, tmp_path)
    try:
        st = await svc.create(random_plan(10, seed=5), actor="test", start=False)
        await svc.abort(st["id"], actor="test", reason="wrong tool mounted")
        rc, out = await _watch(sock, st["id"], capsys=capsys)
        assert rc == 1 and "aborted: wrong tool mounted" in out
    finally:
        await api.stop()
        await svc.stop()


@pytest.mark.parametrize(("seconds", "text"), [(5, "0:05"), (125, "2:05"), (3725, "1:02:05")])
def test_clock(seconds, text):
    from robocal.cli._campaign import _clock

    assert _clock(seconds) == text


async def test_watch_follows_on_when_the_event_stream_ends(make_config, tmp_path, capsys,
                                                           monkeypatch):
    """A stream cut mid-campaign (proxy, restart) is reopened after the last event seen."""
    from robocal.daemon.client import DaemonClient

    real = DaemonClient.events
    calls: list[int] = []

    def flaky(self, *, campaign=None, after=0, timeout=3600.0):
        calls.append(after)
        for n, ev in enumerate(real(self, campaign=campaign, after=after, timeout=timeout)):
            yield ev
            if len(calls) < 3 and n >= 2:
                return  # the stream ends early, twice

    monkeypatch.setattr(DaemonClient, "events", flaky)
    # moves slow enough (40 x 0.05 s) that the campaign still runs when the stream is cut:
    # with per-pose commits that no longer wait for fsync, 0.01 s moves ended it before
    svc, api, sock = await _served(
        make_config, tmp_path, robot={"options": {"move_time_s": 0.05}})
    try:
        st = await svc.create(random_plan(40, seed=6), actor="test")
        rc, out = await _watch(sock, st["id"], capsys=capsys)
        assert rc == 0 and svc.status(st["id"])["state"] == "fitted", out
        assert len(calls) >= 2 and calls[1] > calls[0]   # reopened after the last event seen
    finally:
        await api.stop()
        await svc.stop()


def test_status_and_push_lines_say_what_was_pushed_and_measured():
    from robocal.cli._campaign import _describe, _push_text

    s = {"id": "c1", "state": "pushed", "poses_measured": 5, "poses_total": 5,
         "selected_model": "auto",
         "push_key": "3f2a9c1b7d04", "compensation_state": "active",
         "push": {"key": "3f2a9c1b7d04", "compensation_state": "active",
                  "kind": "targets", "checksum": "8b55f09c059280439c", "model": "auto",
                  "at": "2026-11-23T22:26:53", "actor": "alice", "predicted_rms_mm": 3e-5,
                  "model_accuracy_mm": 0.0109, "nominal_rms_mm": 1.2977,
                  "verification": "done", "measured_before_rms_mm": 1.299,
                  "measured_after_rms_mm": 0.0104, "measured_n": 10}}
    text = _describe(s)
    # the push is named by its key (as in list, watch, the report and the API); the table
    # checksum is a detail
    assert "state     pushed (push 3f2a9c1b7d04: active)" in text
    assert "push      3f2a9c1b7d04  model auto, targets table 8b55f09c0592" in text
    assert "now       active on the controller" in text
    assert "1.2990 mm before -> 0.0104 mm after (10 pushed targets re-measured)" in text
    line = _push_text(s)
    assert "as push 3f2a9c1b7d04" in line and "table checksum 8b55f09c0592" in line
    assert "kind targets" in line and "model held-out RMS 0.0109 mm" in line
    assert "measured after 0.0104 mm" in line


async def test_client_waits_for_a_daemon_that_is_starting(make_config, tmp_path):
    """--wait-for-daemon: a script may start the daemon and talk to it at once."""
    from robocal.daemon.client import DaemonClient, DaemonUnavailable

    sock = tmp_path / "api.sock"
    c = DaemonClient(socket_path=sock, timeout=5.0)
    with pytest.raises(DaemonUnavailable, match="robocal daemon --config"):
        await asyncio.to_thread(c.request, "GET", "/health")
    c.wait_s = 20.0
    attempts: list[object] = []
    connection = c._connection

    def counted(timeout: float | None = None) -> Any:  # one call per connection attempt
        attempts.append(None)
        return connection(timeout)

    c._connection = counted  # type: ignore[method-assign]
    pending = asyncio.create_task(asyncio.to_thread(c.request, "GET", "/health"))
    # refused, and trying again: the client waits instead of giving up
    await eventually(lambda: len(attempts) >= 2, 10, what="a second connection attempt")
    assert not pending.done()
    svc, api, _ = await _served(make_config, tmp_path)  # the daemon comes up late
    try:
        assert (await asyncio.wait_for(pending, 20))["status"] == "ok"
    finally:
        await api.stop()
        await svc.stop()


async def test_watch_of_a_paused_campaign_waits_for_the_resume(make_config, tmp_path, capsys):
    svc, api, sock = await _served(
        make_config, tmp_path, robot={"options": {"move_time_s": 0.01}})
    try:
        st = await svc.create(random_plan(30, seed=7), actor="test")
        cid = st["id"]
        await svc.pause(cid, actor="test", reason="coffee")
        subscribers = len(svc.events._subscribers)
        watch = asyncio.ensure_future(_watch(sock, cid, capsys=capsys))
        # the watch is in the event stream, waiting: only then resume
        await eventually(lambda: len(svc.events._subscribers) > subscribers, 30,
                         what="the watch to subscribe")
        assert not watch.done()
        await svc.resume(cid, actor="test")
        rc, out = await watch
        assert rc == 0, out
        assert "waiting for 'robocal campaign resume" in out and "30/30" in out
        assert svc.status(cid)["state"] == "fitted"
    finally:
        await api.stop()
        await svc.stop()


def test_progress_times_come_from_the_state_history():
    """Elapsed counts from the first run (not the watch's start); the rate counts measuring
    time only; paused and aborted lines carry no ETA; the fit shows how long it has run."""
    from robocal.cli._campaign import _Progress

    status = {"poses_measured": 20, "poses_total": 40, "state": "running", "transitions": [
        {"at": "2026-01-01T10:00:00+00:00", "to_state": "created"},
        {"at": "2026-01-01T10:00:00+00:00", "to_state": "running"},
        {"at": "2026-01-01T10:01:00+00:00", "to_state": "paused"},
        {"at": "2026-01-01T10:31:00+00:00", "to_state": "running"}]}
    t0 = 1767261600.0  # 2026-01-01T10:00:00Z
    prog = _Progress(status, now=t0 + 32 * 60)
    line = prog.line(now=t0 + 32 * 60)
    # 32 min since it first ran; 20 poses in 2 min of measuring: 10 poses/min, 2 min left
    assert "32:00 elapsed" in line and "10.0 poses/min" in line and "ETA 2:00" in line
    prog.update({"kind": "state", "state": "paused"}, now=t0 + 33 * 60)
    assert "ETA" not in prog.line(now=t0 + 40 * 60)
    prog.update({"kind": "state", "state": "aborted"}, now=t0 + 41 * 60)
    assert "ETA" not in prog.line(now=t0 + 41 * 60)
    done = _Progress({**status, "poses_measured": 40, "state": "measured",
                      "fitting": {"models": ["auto"], "elapsed_s": 12.0},
                      "transitions": [*status["transitions"],
                                      {"at": "2026-01-01T10:33:00+00:00",
                                       "to_state": "measured"}]}, now=t0 + 34 * 60)
    line = done.line(now=t0 + 34 * 60)
    # 40 poses in 3 min of measuring, not spread over the 34 min since the start
    assert "13.3 poses/min" in line and "| fitting auto 0:12" in line
    done.update({"kind": "state", "state": "fitted"}, now=t0 + 34 * 60 + 8)
    line = done.line(now=t0 + 35 * 60)
    assert "| fit took 0:20" in line and "13.3 poses/min" in line


def test_the_terminal_line_fits_the_terminal(monkeypatch):
    import os

    from robocal.cli._campaign import _Progress, _terminal_line

    monkeypatch.setattr("shutil.get_terminal_size", lambda fallback=(80, 24): os.terminal_size(
        (80, 24)))
    prog = _Progress({"poses_measured": 123, "poses_total": 1250, "state": "running",
                      "transitions": [{"at": "2026-01-01T10:00:00+00:00",
                                       "to_state": "running"}]})
    prog.retries, prog.beam_losses = 1234, 56
    text = _terminal_line(prog)
    assert text.startswith("\r\033[K") and "\n" not in text
    assert len(text) - len("\r\033[K") <= 79


async def test_campaign_events_lists_one_campaigns_history(make_config, tmp_path, capsys):
    svc, api, sock = await _served(make_config, tmp_path)
    try:
        other = await svc.create(random_plan(10, seed=8), actor="test", start=False)
        st = await svc.create(random_plan(10, seed=9), actor="alice", start=False)
        await svc.abort(other["id"], actor="test", reason="not this one")
        await svc.abort(st["id"], actor="alice", reason="wrong tool mounted")
        rc = await asyncio.wait_for(asyncio.to_thread(
            main, ["campaign", "events", st["id"], "--socket", str(sock)]), 30)
        # the daemon's own log lines go to the same captured stdout: keep the command's
        out = "\n".join(ln for ln in capsys.readouterr().out.splitlines()
                        if "[info" not in ln and "[warning" not in ln)
        assert rc == 0, out
        assert "created -> aborted" in out and "wrong tool mounted" in out
        assert "not this one" not in out
        rc = await asyncio.wait_for(asyncio.to_thread(
            main, ["campaign", "events", st["id"], "--json", "--socket", str(sock)]), 30)
        text = capsys.readouterr().out
        entries = json.loads("\n".join(ln for ln in text.splitlines()
                                       if "[info" not in ln and "[warning" not in ln))
        assert [e["at"] for e in entries] == sorted(e["at"] for e in entries)
        assert any(e["kind"] == "audit" for e in entries), entries
    finally:
        await api.stop()
        await svc.stop()
