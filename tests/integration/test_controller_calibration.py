"""The controller's own calibration through the daemon (ADR 0033), against the simulators.

A campaign records what the controller applies (KUKA ``$MAMES``/``$ABS_ACCUR``, ABB's motion
configuration, UR's kinematics info) in its status and its MODEL.json; a push onto a
controller whose calibration changed since, or with a vendor absolute-accuracy option
active, is refused with nothing written, and goes through when forced (audited).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from aiohttp.test_utils import TestClient, TestServer
from tests.integration.test_ur_campaign import service as ur_service
from tests.integration.test_ur_campaign import ur_plan
from tests.unit.daemon.conftest import ROBOT, base_config
from tests.unit.daemon.test_service import program_plan

from robocal.daemon.api import make_app
from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.drivers.sim import AbbSimOptions, KukaSimOptions, LtpSimOptions, SimCell
from robocal.errors import CompensationError


def _service(cell: SimCell, tmp_path: Path, kind: str) -> CalibrationService:
    cfg = base_config(tmp_path, limits={"max_joint_correction_deg": 5.0},
                      compensation={"verify_count": 0})
    cfg["robot"] = {"kind": kind, "options": cell.robot_options(kind)}
    cfg["tracker"] = {"kind": "ltp", "options": {**cell.tracker_options("tcp"),
                                                 "stab_ms": 10}}
    return CalibrationService(parse_config(cfg, source="test"))


async def _approved(svc: CalibrationService, plan: Any) -> dict[str, Any]:
    st = await svc.create(plan, actor="a")
    st = await svc.wait(st["id"], ["fitted", "faulted"], timeout=120)
    assert st["state"] == "fitted", st["reason"]
    return await svc.approve(st["id"], actor="a")


def _model_files(svc: CalibrationService, cid: str) -> list[dict[str, Any]]:
    """Every MODEL.json of the campaign: in the store and in its directory."""
    rec = svc.store.campaign(cid)
    stored = svc.store.model_json(cid, rec.selected_model or "")
    assert stored is not None
    files = sorted(Path(svc.status(cid)["files"]).glob("MODEL-*.json"))
    assert files
    return [json.loads(stored)] + [json.loads(f.read_text()) for f in files]


def _actions(svc: CalibrationService, cid: str) -> list[dict[str, Any]]:
    return [a for a in svc.audit() if a["campaign"] == cid]


async def test_kuka_remastered_after_the_campaign_refuses_the_push_unless_forced(tmp_path):
    cell = SimCell(robot=ROBOT, seed=4, fanuc=False, modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0), kuka=KukaSimOptions(time_scale=0.0))
    async with cell:
        sim = cell.kuka_sim
        assert sim is not None
        svc = _service(cell, tmp_path, "kuka_kvp")
        await svc.start()
        try:
            st = await _approved(svc, program_plan(30, validation=8))
            cid = st["id"]
            rec = st["controller_calibration"]
            assert rec["state"] == "read" and rec["source"] == "kuka-kvp-system-variables"
            assert rec["absolute_accuracy"] is False and rec["facts"]["$MAMES[2]"] == "-90.0"
            # the fingerprint is in the campaign's models, stored and on disk
            for doc in _model_files(svc, cid):
                assert doc["data"]["controller_calibration"]["fingerprint"] == rec["fingerprint"]

            sim.calibration_vars["$MAMES[2]"] = "-90.0125"  # axis 2 mastered again
            # through the HTTP API, as `robocal campaign push [--force]` sends it
            async with TestClient(TestServer(make_app(svc))) as http:
                r = await http.get(f"/campaigns/{cid}")  # the status schema holds the record
                assert (await r.json())["controller_calibration"] == rec
                r = await http.post(f"/campaigns/{cid}/push")
                err = (await r.json())["error"]
                assert r.status == 422 and err["type"] == "CompensationError"
                assert re.search(r"changed since campaign .*MAMES\[2\]", err["message"])
                assert sim.read("RC_COMP_N") == ("0", True)  # nothing written
                assert svc.status(cid)["state"] == "approved"
                refused = [a for a in _actions(svc, cid)
                           if a["action"] == "compensation.push-refused"]
                assert len(refused) == 1 and "MAMES" in refused[0]["detail"]["refusal"]

                r = await http.post(f"/campaigns/{cid}/push", json={"force": True},
                                    headers={"X-Robocal-Actor": "boss"})
                assert r.status == 200 and (await r.json())["state"] == "pushed"
            assert int(sim.read("RC_COMP_N")[0]) > 0
            check = [a for a in _actions(svc, cid)
                     if a["action"] == "controller.calibration-checked"][-1]
            assert check["actor"].startswith("boss") and check["detail"]["forced"] is True
            assert check["detail"]["campaign_fingerprint"] == rec["fingerprint"]
            assert check["detail"]["controller_fingerprint"] != rec["fingerprint"]
        finally:
            await svc.stop()


async def test_abb_absolute_accuracy_active_refuses_the_push_unless_forced(tmp_path):
    cell = SimCell(robot=ROBOT, seed=5, fanuc=False, modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0),
                   abb=AbbSimOptions(time_scale=0.0, absolute_accuracy=True))
    async with cell:
        sim = cell.abb_sim
        assert sim is not None
        svc = _service(cell, tmp_path, "abb_rws")
        await svc.start()
        try:
            st = await _approved(svc, program_plan(30, validation=8))
            cid = st["id"]
            rec = st["controller_calibration"]
            assert rec["absolute_accuracy"] is True and rec["source"] == "abb-rws-cfg-moc"
            assert rec["facts"]["MOC/ROBOT/ROB_1"]["use_robot_calib"] == "r1_calib"
            for doc in _model_files(svc, cid):
                assert doc["data"]["controller_calibration"]["absolute_accuracy"] is True
            before = sim.symbols["rc_comp_n"].value
            # the fingerprint is unchanged: the refusal is the vendor option alone
            with pytest.raises(CompensationError, match="absolute-accuracy option is active"):
                await svc.push(cid, actor="a")
            assert sim.symbols["rc_comp_n"].value == before
            st = await svc.push(cid, actor="a", force=True)
            assert st["state"] == "pushed" and sim.symbols["rc_comp_n"].value != before
            check = [a for a in _actions(svc, cid)
                     if a["action"] == "controller.calibration-checked"][-1]
            assert check["detail"]["forced"] is True and check["detail"]["absolute_accuracy"]
            assert check["detail"]["controller_fingerprint"] == rec["fingerprint"]
            # the push record says it was forced, and over what
            assert st["push"]["forced"] is True
            pushed = st["compensation"][-1]["controller_calibration"]
            assert pushed["forced"] and "absolute-accuracy" in pushed["refusals"][0]
        finally:
            await svc.stop()


async def test_ur_kinematics_changed_after_the_campaign_refuses_the_push(tmp_path):
    async with ur_service(tmp_path, time_scale=0.0) as (svc, cell):
        sim = cell.ur_sim
        assert sim is not None
        st = await _approved(svc, ur_plan(30, seed=3, validation=8))
        cid = st["id"]
        rec = st["controller_calibration"]
        assert rec["source"] == "ur-kinematics-info" and rec["absolute_accuracy"] is False
        assert rec["facts"]["checksums"] == sim.kinematics().fingerprint()
        for doc in _model_files(svc, cid):
            assert doc["data"]["controller_calibration"]["fingerprint"] == rec["fingerprint"]
        k = sim.kinematics()
        sim.set_kinematics(k.dh_theta, k.dh_a, [d + 2e-4 for d in k.dh_d], k.dh_alpha)
        with pytest.raises(CompensationError, match=r"changed since campaign .*dh_d_m"):
            await svc.push(cid, actor="a")
        assert svc.status(cid)["state"] == "approved"
        st = await svc.push(cid, actor="a", force=True)
        assert st["state"] == "pushed" and st["push"]["forced"] is True


async def test_a_driver_that_shows_nothing_records_unavailable_and_pushes(service_mock):
    svc = service_mock
    st = await _approved(svc, program_plan(24, validation=6))
    rec = st["controller_calibration"]
    assert rec["state"] == "unavailable" and "does not show" in rec["reason"]
    assert rec["fingerprint"] is None
    st = await svc.push(st["id"], actor="a")
    assert st["state"] == "pushed" and st["push"]["forced"] is False
    assert st["compensation"][-1]["controller_calibration"]["state"] == "unavailable"


@pytest.fixture
async def service_mock(tmp_path):
    svc = CalibrationService(parse_config(
        base_config(tmp_path, compensation={"verify_count": 0}), source="test"))
    await svc.start()
    try:
        yield svc
    finally:
        await svc.stop()


def test_campaign_status_text_names_the_controller_calibration():
    from robocal.cli._campaign import _describe

    base = {"id": "c1", "state": "fitted", "poses_measured": 5, "poses_total": 5}
    read = {"state": "read", "fingerprint": "0123456789abcdef", "source": "abb-rws-cfg-moc",
            "absolute_accuracy": True, "reason": ""}
    text = _describe({**base, "controller_calibration": read})
    assert ("controller calibration 0123456789abcdef (abb-rws-cfg-moc; vendor absolute "
            "accuracy ON)") in text
    text = _describe({**base, "controller_calibration": {"state": "unavailable",
                                                         "reason": "RMI shows none"}})
    assert "controller calibration unavailable (RMI shows none)" in text
    assert "controller calibration" not in _describe(base)
