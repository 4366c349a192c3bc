"""The ABB RWS driver and simulator: the RAPID module's declarations, logins and sessions,
refusals at connect, motion errors, and compensation in ``rc_comp``."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import re
import signal
import ssl
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
import trustme

from robocal.compensation import CompensationTable, TargetRow
from robocal.drivers import load_robot_driver
from robocal.drivers.sim import AbbRwsSimulator, AbbSimOptions, SimWorld
from robocal.errors import (
    CompensationError,
    ConnectFailed,
    LimitViolation,
    MotionRejected,
    UnexpectedReply,
)
from robocal.protocols import abb_rws as rws
from tests._waiting import eventually

MODULE_SOURCE = Path(__file__).resolve().parents[3] / "deploy" / "abb" / "RobocalServer.mod"


@contextlib.asynccontextmanager
async def abb_sim(world: SimWorld, **options: Any) -> AsyncIterator[AbbRwsSimulator]:
    sim = AbbRwsSimulator(world, AbbSimOptions(time_scale=0.0, **options))
    await sim.start()
    try:
        yield sim
    finally:
        await sim.stop()


def driver_options(sim: AbbRwsSimulator, world: SimWorld, **extra: Any) -> dict[str, Any]:
    return {"port": sim.port, "scheme": "http", "robotware": sim.options.robotware,
            "joint_limits_deg": [list(lim) for lim in world.joint_limits_deg],
            "poll_interval_s": 0.002, **extra}


def test_simulator_declares_what_the_rapid_module_declares(world):
    """The simulated module has exactly the PERS data of deploy/abb/RobocalServer.mod."""
    src = MODULE_SOURCE.read_text()
    declared = {m.group(2).lower(): (m.group(1), int(m.group(3) or 0))
                for m in re.finditer(r"^\s*PERS (\w+) (\w+)(?:\{(\d+)\})?", src, re.M)}
    sim = AbbRwsSimulator(world, AbbSimOptions())
    assert declared == {k: (s.dattyp, s.dims) for k, s in sim.symbols.items()}
    assert re.search(r"CONST num rc_comp_size := (\d+);", src).group(1) == str(  # type: ignore[union-attr]
        sim.options.comp_size)
    # the module's main drops a pending command first, then loops on the handshake
    assert re.search(r"rc_done := rc_seq;\s*WHILE TRUE DO\s*WaitUntil rc_seq <> rc_done", src)


async def test_digest_login_xhtml_answers_and_replay_refusal(world):
    async with abb_sim(world, robotware=6) as sim, aiohttp.ClientSession() as http:
        url = sim.base_url + "/rw/panel/ctrlstate"
        async with http.get(url) as r:
            assert r.status == 401
            challenge = rws.parse_challenge(r.headers["WWW-Authenticate"])
        assert challenge.realm == rws.REALM and challenge.qop == "auth"
        auth = rws.digest_authorization(challenge, username="Default User", password="robotics",
                                        method="GET", uri="/rw/panel/ctrlstate", nc=1,
                                        cnonce="abc")
        async with http.get(url, headers={"Authorization": auth}) as r:
            assert r.status == 200 and r.headers["Content-Type"] == rws.XHTML
            items = rws.parse_states(await r.read(), r.headers["Content-Type"])
            assert rws.single(items, "ctrlstate") == "motoroff"
            assert "-http-session-" in r.cookies and "ABBCX" in r.cookies
        http.cookie_jar.clear()
        async with http.get(url, headers={"Authorization": auth}) as r:
            assert r.status == 401  # the same nonce count again: a replay
        wrong = rws.digest_authorization(challenge, username="Default User", password="x",
                                         method="GET", uri="/rw/panel/ctrlstate", nc=2,
                                         cnonce="abc")
        async with http.get(url, headers={"Authorization": wrong}) as r:
            assert r.status == 401


async def test_rws2_wants_versioned_form_bodies_and_basic_auth(world):
    async with abb_sim(world, robotware=7) as sim, aiohttp.ClientSession() as http:
        basic = {"Authorization": rws.basic_authorization("Admin", "robotics")}
        url = sim.base_url + "/rw/panel/ctrl-state"
        async with http.post(url, data={"ctrl-state": "motoron"}, headers=basic) as r:
            assert r.status == 415  # form body without ;v=2.0
        async with http.post(url, data={"ctrl-state": "motoron"},
                             headers={**basic, "Content-Type": rws.FORM_RWS2}) as r:
            assert r.status == 204
        async with http.get(sim.base_url + "/rw/panel/ctrlstate", headers=basic) as r:
            assert r.headers["Content-Type"] == rws.JSON_RWS2
            assert rws.single(rws.parse_states(await r.read(), rws.JSON_RWS2),
                              "ctrlstate") == "motoron"
        async with http.get(sim.base_url + "/rw/panel/opmode",
                            headers={**basic, "Accept": "application/json"}) as r:
            assert r.status == 406  # an unversioned media type
        http.cookie_jar.clear()
        digest_like = {"Authorization": rws.basic_authorization("Admin", "wrong")}
        async with http.get(sim.base_url + "/rw/panel/opmode", headers=digest_like) as r:
            assert r.status == 401 and r.headers["WWW-Authenticate"].startswith("Basic")


@pytest.mark.parametrize("robotware", [6, 7])
async def test_connect_refusals(world, robotware):
    async with abb_sim(world, robotware=robotware) as sim:
        bad = load_robot_driver("abb_rws", driver_options(sim, world, password="nope"))
        with pytest.raises(ConnectFailed, match="refused user"):
            await bad.connect(timeout=5)
        sim.opmode = "MANR"
        manual = load_robot_driver("abb_rws", driver_options(sim, world))
        with pytest.raises(ConnectFailed, match="AUTO"):
            await manual.connect(timeout=5)
        sim.opmode = "AUTO"
        off = load_robot_driver("abb_rws", driver_options(sim, world, motors_on=False))
        with pytest.raises(ConnectFailed, match="motors are off"):
            await off.connect(timeout=5)
        other = load_robot_driver("abb_rws", driver_options(sim, world, module="Other"))
        with pytest.raises(ConnectFailed, match=r"RobocalServer\.mod"):
            await other.connect(timeout=5)
        assert sim.execstate == "stopped"  # nothing was started by the refused sessions


async def test_sessions_are_limited_and_logout_frees_one(world):
    async with abb_sim(world, robotware=6, max_sessions=1) as sim:
        first = load_robot_driver("abb_rws", driver_options(sim, world))
        second = load_robot_driver("abb_rws", driver_options(sim, world))
        await first.connect(timeout=5)
        try:
            with pytest.raises(ConnectFailed, match="too many sessions"):
                await second.connect(timeout=5)
        finally:
            await first.close()
        await second.connect(timeout=5)
        await second.close()


async def test_idle_sessions_end(world):
    """A client that never logs out holds its session only until it has been idle long."""
    async with abb_sim(world, robotware=7, max_sessions=1, session_idle_s=0.1) as sim:
        basic = {"Authorization": rws.basic_authorization("Admin", "robotics")}
        async with aiohttp.ClientSession() as http, http.get(  # logs in, never logs out
                sim.base_url + "/rw/panel/opmode", headers=basic) as r:
            assert r.status == 200
        late = load_robot_driver("abb_rws", driver_options(sim, world))

        async def connects() -> bool:
            try:
                await late.connect(timeout=5)
            except ConnectFailed as err:
                assert "too many sessions" in str(err)
                return False
            return True

        try:
            await eventually(connects, 5, interval=0.02, what="the idle session ended")
        finally:
            await late.close()


async def test_motion_error_is_rejected_and_the_next_move_restarts_the_program(world):
    async with abb_sim(world, robotware=6) as sim:
        wide = [[lo - 20.0, hi + 20.0] for lo, hi in world.joint_limits_deg]
        robot = load_robot_driver("abb_rws", driver_options(sim, world, joint_limits_deg=wide))
        await robot.connect(timeout=5)
        try:
            outside = [math.radians(hi + 10.0) for _, hi in world.joint_limits_deg]
            with pytest.raises(MotionRejected, match="50050"):
                await robot.move_to(outside, speed_pct=50, timeout=5)
            assert sim.execstate == "stopped" and sim.elog[-1].code == 50050
            target = [0.5 * math.radians(lo + hi) for lo, hi in world.joint_limits_deg]
            r = await robot.move_to(target, speed_pct=50, timeout=5)
            assert max(abs(a - b) for a, b in zip(r.q_rad, target, strict=True)) < 1e-3
        finally:
            await robot.close()


def _targets(rows: list[TargetRow]) -> CompensationTable:
    return CompensationTable(kind="targets", model_id="m", robot="r",
                             valid_range_deg=[(-90.0, 90.0)] * 6, predicted_residual_mm=0.1,
                             targets=rows).sealed()


@pytest.mark.parametrize("robotware", [6, 7])
async def test_targets_table_snapshot_and_restore(world, robotware):
    async with abb_sim(world, robotware=robotware) as sim:
        robot: Any = load_robot_driver("abb_rws", driver_options(sim, world))
        await robot.connect(timeout=5)
        try:
            table = _targets([
                TargetRow(index=0, q_deg=[1, 2, 3, 4, 5, 6], status="ok", model_residual_mm=0.01),
                TargetRow(index=3, q_deg=[0] * 6, status="unreachable", model_residual_mm=9.0),
                TargetRow(index=7, q_deg=[-10, 20, -30, 40, -50, 60.125], status="ok",
                          model_residual_mm=0.02),
            ])
            before = await robot.snapshot_compensation(table)
            await robot.write_compensation(table)
            back = await robot.read_compensation()
            assert back is not None and back.checksum == table.checksum
            assert rws.parse_jointtarget_array(sim.symbols["rc_comp"].value)[7].robax[5] == 60.125
            assert rws.parse_num(sim.symbols["rc_comp_n"].value) == 8
            await robot.restore_snapshot(before)
            assert await robot.read_compensation() is None
            assert (await robot.snapshot_compensation(table)).items == before.items
            too_far = _targets([TargetRow(index=sim.options.comp_size, q_deg=[0] * 6,
                                          status="ok", model_residual_mm=0.0)])
            with pytest.raises(CompensationError, match="rc_comp"):
                await robot.write_compensation(too_far)
            outside = _targets([TargetRow(index=0, q_deg=[400, 0, 0, 0, 0, 0], status="ok",
                                          model_residual_mm=0.0)])
            with pytest.raises(LimitViolation):
                await robot.write_compensation(outside)
            assert sim.symbols["rc_comp"].value == before.items["rc_comp"]  # nothing written
        finally:
            await robot.close()


async def test_robocal_sim_abb_as_a_process(tmp_path):
    """``robocal sim abb --robotware 7`` serves RWS 2.0 until SIGTERM; the driver moves it."""
    ports_file = tmp_path / "ports.json"
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "robocal.drivers.sim", "abb", "--robotware", "7",
        "--time-scale", "0", "--ports-file", str(ports_file),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
        env={**os.environ, "PYTHONWARNINGS": "ignore"})
    try:
        assert proc.stdout is not None
        ports = json.loads(await asyncio.wait_for(proc.stdout.readline(), 30))
        assert ports["abb_rws"]["robotware"] == 7 and set(ports) == {"host", "robot", "abb_rws"}
        robot = load_robot_driver("abb_rws", {
            "port": ports["abb_rws"]["port"], "scheme": "http", "robotware": 7,
            "joint_limits_deg": [(-90.0, 90.0)] * 6, "poll_interval_s": 0.002})
        await robot.connect(timeout=10)
        try:
            r = await robot.move_to([0.3] * 6, timeout=10)
            assert r.q_rad[0] == pytest.approx(0.3, abs=1e-4)
        finally:
            await robot.close()
        proc.send_signal(signal.SIGTERM)
        assert await asyncio.wait_for(proc.wait(), 20) == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_stop_after_motors_off_halts_and_the_next_move_names_the_cause(world):
    """A guard stop switched the motors off: stop() still confirms the halt; the next move is
    rejected with the controller's reason until the motors are on again."""
    async with abb_sim(world, robotware=7) as sim:
        robot = load_robot_driver("abb_rws", driver_options(sim, world, motors_on=False,
                                                            username="Admin"))
        sim.ctrlstate = "motoron"
        await robot.connect(timeout=5)
        try:
            sim.ctrlstate = "motoroff"  # as a guard stop leaves it
            await robot.stop()
            assert sim.execstate == "stopped"
            target = [0.5 * math.radians(lo + hi) for lo, hi in world.joint_limits_deg]
            with pytest.raises(MotionRejected, match="motors are off"):
                await robot.move_to(target, speed_pct=50, timeout=5)
            sim.ctrlstate = "motoron"
            r = await robot.move_to(target, speed_pct=50, timeout=5)
            assert max(abs(a - b) for a, b in zip(r.q_rad, target, strict=True)) < 1e-3
        finally:
            await robot.close()


async def test_robotware7_over_https_checks_the_certificate(world, tmp_path):
    """RobotWare 7 serves HTTPS only: the driver trusts the site's CA file, refuses an
    unknown certificate, and connects unchecked only when told to."""
    ca = trustme.CA()
    server_ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ca.issue_cert("127.0.0.1").configure_cert(server_ctx)
    ca_file = tmp_path / "omnicore-ca.pem"
    ca.cert_pem.write_to_path(str(ca_file))
    sim = AbbRwsSimulator(world, AbbSimOptions(robotware=7, time_scale=0.0))
    await sim.start(ssl_context=server_ctx)
    try:
        assert sim.base_url.startswith("https://")
        base = driver_options(sim, world, scheme="https")
        unknown = load_robot_driver("abb_rws", base)
        with pytest.raises(ConnectFailed, match=r"(?i)certificate"):
            await unknown.connect(timeout=5)
        missing = load_robot_driver("abb_rws", {**base, "ca_file": str(tmp_path / "none.pem")})
        with pytest.raises(ConnectFailed, match="ca_file"):
            await missing.connect(timeout=5)
        for extra in ({"ca_file": str(ca_file)}, {"verify_tls": False}):
            robot = load_robot_driver("abb_rws", {**base, **extra})
            await robot.connect(timeout=5)
            try:
                r = await robot.move_to([0.2] * world.dof, speed_pct=50, timeout=5)
                assert r.q_rad[0] == pytest.approx(0.2, abs=1e-4)
            finally:
                await robot.close()
    finally:
        await sim.stop()


@pytest.mark.parametrize("robotware", [6, 7])
async def test_controller_calibration_reads_the_motion_configuration(world, robotware):
    async with abb_sim(world, robotware=robotware, motors_on=True) as sim:
        robot = load_robot_driver("abb_rws", driver_options(sim, world))
        await robot.connect(timeout=5)
        try:
            first = await robot.controller_calibration()
            assert first.absolute_accuracy is False
            assert first.facts["MOC/ROBOT/ROB_1"]["use_robot_calib"] == "r1_uncalib"
            assert first.facts["MOC/MOTOR_CALIB"]["rob1_2"]["cal_offset"] == "5.602300"
            assert await robot.controller_calibration() == first
            # a fine calibration of axis 2 changes the fingerprint
            sim.cfg["MOC"]["MOTOR_CALIB"]["rob1_2"]["cal_offset"] = "5.602410"
            second = await robot.controller_calibration()
            assert second.fingerprint != first.fingerprint
            # Absolute Accuracy loaded
            sim.cfg["MOC"]["ROBOT"]["ROB_1"]["use_robot_calib"] = "r1_calib"
            assert (await robot.controller_calibration()).absolute_accuracy is True
            # a controller without the resource: nothing to say, not a failure
            del sim.cfg["MOC"]["ROBOT"]
            third = await robot.controller_calibration()
            assert third.absolute_accuracy is None and third.facts["MOC/ROBOT/ROB_1"] is None
        finally:
            await robot.close()


def test_cfg_instances_parse_and_refuse_malformed_items():
    items = [{"_type": "cfg-dt-instance-li", "_title": "ROB_1",
              "attrib": [{"_type": "cfg-ia-t-li", "_title": "use_robot_calib",
                          "value": "r1_calib"}]},
             {"_type": "something-else", "_title": "x"}]
    assert rws.parse_cfg_instances(items) == {"ROB_1": {"use_robot_calib": "r1_calib"}}
    with pytest.raises(UnexpectedReply, match="malformed configuration attribute"):
        rws.parse_cfg_instances([{"_type": "cfg-dt-instance-li", "_title": "R",
                                  "attrib": ["not an object"]}])
    with pytest.raises(ValueError, match="configuration name"):
        rws.cfg_instances("rws1", "MOC", "ROBOT", "../x")


async def test_cfg_instance_in_xhtml_nests_its_attributes(world):
    async with abb_sim(world, robotware=6) as sim, aiohttp.ClientSession() as http:
        path = "/rw/cfg/MOC/ROBOT/instances/ROB_1"
        async with http.get(sim.base_url + path) as r:
            challenge = rws.parse_challenge(r.headers["WWW-Authenticate"])
        auth = rws.digest_authorization(challenge, username="Default User", password="robotics",
                                        method="GET", uri=path, nc=1, cnonce="abc")
        async with http.get(sim.base_url + path, headers={"Authorization": auth}) as r:
            assert r.status == 200 and r.headers["Content-Type"] == rws.XHTML
            page = (await r.read()).decode()
        assert re.search(r'<li class="cfg-dt-instance-li" title="ROB_1"><span class="rdonly">'
                         r'false</span><ul><li class="cfg-ia-t-li" title="name">.*<li '
                         r'class="cfg-ia-t-li" title="use_robot_calib"><span class="value">'
                         r"r1_uncalib</span></li></ul></li>", page)
