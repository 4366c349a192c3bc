"""One truth of what the controller holds (issue 32, first acceptance criterion): push, roll
back, push again, push on top, roll back twice; after every step ``campaign status``,
``campaign list``, the closing line of ``campaign watch``, the report's Compensation section
and the API (``/campaigns``, ``/campaigns/{id}``, ``/compensation``) name each push by the
same key and agree on where its table is (active / superseded / rolled back) and on the
measured before -> after. The report is rewritten in the background; the test waits for its
``report`` event, never for a fixed time."""

from __future__ import annotations

import asyncio
import json
import shutil
from pathlib import Path
from typing import Any

from robocal.daemon.service import CalibrationService
from tests.unit.daemon.test_push_abort_race import _approved_copy
from tests.unit.daemon.test_service import program_plan


def _config(make_config: Any, sock: Path) -> Any:
    return make_config(api={"socket": str(sock)}, robot={"options": {"move_time_s": 0.01}},
                       limits={"max_joint_correction_deg": 5.0},
                       compensation={"verify_count": 4}, fit={"report": True})


def _cut(page: str) -> str:
    """The Compensation section of a report page."""
    start = page.index('<section id="compensation">')
    return page[start:page.index("</section>", start)]


def _section(svc: CalibrationService, cid: str) -> tuple[dict[str, Any], str]:
    """report.json and the HTML Compensation section of ``cid``."""
    d = svc._campaign_dir(cid)
    return (json.loads((d / "report.json").read_text(encoding="utf-8")),
            _cut((d / "report.html").read_text(encoding="utf-8")))


def _now(p: dict[str, Any]) -> str:
    """The report's "now" text for the API's push summary ``p``."""
    from robocal.report._html import nice_date

    return {"active": "active on the controller",
            "superseded": f"superseded by push {p['superseded_by']}",
            "rolled back": f"rolled back at {nice_date(str(p['rolled_back_at']))} by "
                           f"rollback {p['rolled_back_by']}"}[p["compensation_state"]]


def _shows(doc: dict[str, Any], html: str, want: dict[str, Any] | None) -> bool:
    """Whether a report (JSON, HTML section) shows the API's push summary ``want`` (None:
    approved, not pushed)."""
    if doc.get("approval") is None:
        return False
    pushes = [e for e in doc.get("compensation") or [] if e["action"] == "push"]
    if want is None:
        return not pushes and "Not pushed to the controller yet." in html
    if len(pushes) != 1:
        return False
    e, v = pushes[0], pushes[0]["verification"] or {}
    return (e["key"] == want["key"]
            and all(e.get(k) == want[k] for k in ("compensation_state", "superseded_by",
                                                  "rolled_back_by", "rolled_back_at"))
            and (v.get("before") or {}).get("rms_mm") == want["measured_before_rms_mm"]
            and (v.get("after") or {}).get("rms_mm") == want["measured_after_rms_mm"]
            and f"push {want['key']}</b>" in html and f"Now: <b>{_now(want)}</b>" in html
            and f"{want['measured_before_rms_mm']:.4f} mm before -&gt; "
                f"{want['measured_after_rms_mm']:.4f} mm after" in html)


async def _report_shows(svc: CalibrationService, q: asyncio.Queue[Any], cid: str,
                        want: dict[str, Any] | None) -> None:
    """Wait, event by event, until ``cid``'s report files show ``want`` (see :func:`_shows`)."""
    async with asyncio.timeout(30):
        while not _shows(*_section(svc, cid), want):
            assert await q.get() is not None, "the service stopped"


async def test_push_rollback_push_again_status_list_watch_report_and_api_agree(
        make_config, tmp_path, capsys):
    import aiohttp

    from robocal.cli.main import main
    from robocal.daemon.api import ApiServer
    from robocal.daemon.client import DaemonClient

    sock = tmp_path / "api.sock"
    cfg = _config(make_config, sock)
    svc = CalibrationService(cfg)
    await svc.start()
    api = ApiServer(svc, cfg)
    await api.start()
    http = DaemonClient.from_args(socket_path=sock, timeout=30)

    async def get(path: str) -> Any:
        return await asyncio.to_thread(http.request, "GET", path)

    async def get_html(path: str) -> str:
        async with (aiohttp.ClientSession(connector=aiohttp.UnixConnector(path=str(sock)))
                    as session, session.get(f"http://robocal{path}") as r):
            assert r.status == 200 and r.content_type == "text/html", await r.text()
            return await r.text()

    async def served_report_shows(cid: str, want: dict[str, Any] | None) -> None:
        """The report as the API serves it (``report.json``, ``report.html``)."""
        doc = await get(f"/campaigns/{cid}/report.json")
        assert _shows(doc, _cut(await get_html(f"/campaigns/{cid}/report.html")), want), doc

    async def cli(*argv: str, rc: int = 0) -> str:
        code = await asyncio.wait_for(asyncio.to_thread(main, [*argv, "--socket", str(sock)]),
                                      60)
        out = capsys.readouterr().out
        assert code == rc, (argv, code, out)
        return out

    try:
        st = await svc.create(program_plan(36, validation=10), actor="a")
        a = str(st["id"])
        st = await svc.wait(a, ["fitted"], timeout=60)
        assert st["state"] == "fitted", st["reason"]
        # two more fitted campaigns: copies of the model, each with a copy of A's report
        b, c = (_approved_copy(svc, a, program_plan(36, validation=10)) for _ in range(2))
        for cid in (b, c):
            svc._campaign_dir(cid).mkdir(parents=True, exist_ok=True)
            for name in ("report.html", "report.json"):
                shutil.copy(svc._campaign_dir(a) / name, svc._campaign_dir(cid) / name)
        approved = [b, c]

        async def agree(expect: dict[str, str | None]) -> None:
            """Every view against the API's campaign status, for each campaign."""
            listed = {x["id"]: x for x in await get("/campaigns")}
            history = {h["key"]: h for h in (await get("/compensation"))["history"]
                       if h["action"] == "push"}
            list_text = await cli("campaign", "list")
            for cid, want in expect.items():
                st = await get(f"/campaigns/{cid}")
                assert st.get("compensation_state") == want, (cid, st)
                assert listed[cid].get("compensation_state") == want
                assert listed[cid].get("push_key") == st.get("push_key")
                status_text = await cli("campaign", "status", cid)
                watch_text = await cli("campaign", "watch", cid)
                final = [ln for ln in watch_text.splitlines() if ln.startswith(f"{cid}: ")]
                line = next(ln for ln in list_text.splitlines() if ln.startswith(cid))
                if want is None:
                    assert st["push"] is None and st.get("push_key") is None
                    assert "push" not in line and len(final) == 1, (line, watch_text)
                    assert final[0].startswith(f"{cid}: approved: "), watch_text
                    await _report_shows(svc, q, cid, None)
                    await served_report_shows(cid, None)
                    continue
                p, key = st["push"], st["push_key"]
                assert p["key"] == key and p["compensation_state"] == want
                h = history[key]  # the API's history names it by the same key
                assert h["campaign"] == cid and h["compensation_state"] == want
                for k in ("superseded_by", "rolled_back_by", "rolled_back_at"):
                    assert h[k] == p[k], k
                v = h["verification"]
                assert v["state"] == "done"
                assert v["before"]["rms_mm"] == p["measured_before_rms_mm"]
                assert v["after"]["rms_mm"] == p["measured_after_rms_mm"]
                shown = f"pushed (push {key}: {want})"
                assert shown in line, line
                assert len(final) == 1 and final[0].startswith(f"{cid}: {shown}: "), watch_text
                assert f"state     {shown}" in status_text, status_text
                assert f"push      {key}  model" in status_text
                assert (f"measured  {p['measured_before_rms_mm']:.4f} mm before -> "
                        f"{p['measured_after_rms_mm']:.4f} mm after") in status_text
                if want == "superseded":
                    assert f"superseded by push {p['superseded_by']}" in status_text
                    assert history[p["superseded_by"]]["compensation_state"] == "active"
                elif want == "rolled back":
                    assert (f"rolled back at {p['rolled_back_at']} by rollback "
                            f"{p['rolled_back_by']}") in status_text
                await _report_shows(svc, q, cid, p)
                await served_report_shows(cid, p)

        async with svc.events.subscribe() as q:
            await cli("campaign", "approve", a)
            await agree({a: None, b: None, c: None})

            pushed = await cli("campaign", "push", a)
            key_a = (await get(f"/campaigns/{a}"))["push_key"]
            assert f"as push {key_a}" in pushed and "mm before ->" in pushed
            await agree({a: "active", b: None})

            rolled = await cli("compensation", "rollback", "--reason", "wrong model")
            assert "mm before ->" in rolled
            await agree({a: "rolled back", b: None})

            await cli("campaign", "push", b)
            await agree({a: "rolled back", b: "active", c: None})

            await cli("campaign", "push", c)
            await agree({a: "rolled back", b: "superseded", c: "active"})

            await cli("compensation", "rollback")
            await agree({a: "rolled back", b: "active", c: "rolled back"})

            await cli("compensation", "rollback")
            await agree({a: "rolled back", b: "rolled back", c: "rolled back"})
            # `compensation list` names every push by its key and says where it is
            listing = await cli("compensation", "list")
            for cid in (a, b, c):
                assert (f"{(await get(f'/campaigns/{cid}'))['push_key']} rolled back"
                        in listing), listing
        assert approved == [b, c]
    finally:
        await api.stop()
        await svc.stop()


async def test_a_report_left_stale_by_a_stop_is_brought_up_to_date_at_start(make_config,
                                                                             tmp_path):
    """A daemon stopped between a rollback and the report's rewrite (here: the report put
    back as it was before) shows the truth again after its next start."""
    cfg = _config(make_config, tmp_path / "api.sock")
    svc = CalibrationService(cfg)
    await svc.start()
    try:
        st = await svc.create(program_plan(36, validation=10), actor="a")
        cid = str(st["id"])
        await svc.wait(cid, ["fitted"], timeout=60)
        await svc.approve(cid, actor="a")
        key = (await svc.push(cid, actor="a"))["push_key"]
        await svc.wait_verification(key, timeout=60)
        rb = await svc.rollback(actor="a", key="rollback-before-stop")
        assert rb["active"]["kind"] == "snapshot"
        await svc.wait_verification("rollback-before-stop", timeout=60)
        await svc.reports.settled(30)
        doc, _ = _section(svc, cid)
        assert doc["compensation"][0]["compensation_state"] == "rolled back"
    finally:
        await svc.stop()
    d = svc._campaign_dir(cid)
    stale = json.loads((d / "report.json").read_text(encoding="utf-8"))
    stale["compensation"][0].update(compensation_state="active", rolled_back_by=None,
                                    rolled_back_at=None)
    (d / "report.json").write_text(json.dumps(stale))
    page = (d / "report.html").read_text(encoding="utf-8")
    (d / "report.html").write_text(page.replace("rolled back", "active on the controller"))

    again = CalibrationService(cfg)
    async with again.events.subscribe() as q:
        await again.start()
        try:
            want = again.status(cid)["push"]
            assert want["compensation_state"] == "rolled back"
            assert want["rolled_back_by"] == "rollback-before-stop"
            await _report_shows(again, q, cid, want)
        finally:
            await again.stop()


async def test_a_get_of_the_report_after_an_action_waits_for_its_rewrite(make_config, tmp_path,
                                                                         monkeypatch):
    """The rewrite runs in the background, yet ``GET /campaigns/{id}/report.json`` right after
    an approve answers with the report as rewritten (held here until the GET is waiting)."""
    import threading

    from robocal.daemon import _reports
    from robocal.daemon.api import ApiServer
    from robocal.daemon.client import DaemonClient

    sock = tmp_path / "api.sock"
    cfg = _config(make_config, sock)
    svc = CalibrationService(cfg)
    await svc.start()
    api = ApiServer(svc, cfg)
    await api.start()
    entered, release = threading.Event(), threading.Event()
    write = _reports._write

    def held(out_dir: Path, record: dict[str, Any]) -> bool:
        entered.set()
        release.wait(30)
        return write(out_dir, record)

    try:
        st = await svc.create(program_plan(36, validation=10), actor="a")
        cid = str(st["id"])
        await svc.wait(cid, ["fitted"], timeout=60)
        assert "approval" not in json.loads((svc._campaign_dir(cid) / "report.json").read_text())
        monkeypatch.setattr(_reports, "_write", held)
        asked = asyncio.Event()
        settled = svc.reports.settled

        async def waiting(timeout: float) -> None:
            asked.set()
            await settled(timeout)

        monkeypatch.setattr(svc.reports, "settled", waiting)
        await svc.approve(cid, actor="alice")
        assert await asyncio.to_thread(entered.wait, 30)
        http = DaemonClient.from_args(socket_path=sock, timeout=30)
        got = asyncio.create_task(asyncio.to_thread(http.request, "GET",
                                                    f"/campaigns/{cid}/report.json"))
        await asyncio.wait_for(asked.wait(), 30)
        release.set()
        doc = await asyncio.wait_for(got, 30)
        assert doc["approval"]["actor"] == "alice" and doc["approval"]["model"] == "constant"
    finally:
        release.set()
        await api.stop()
        await svc.stop()
