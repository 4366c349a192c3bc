"""The daemon stops the robot at once on pause, abort, shutdown and driver faults.

Against the in-process simulators (FANUC RMI, Modbus PLC, LTP/1) with real-time motion, and
the mock driver: the simulated robot halts within 0.2 s of the request, the stop is logged
and audited (``motion.stop``: trigger, reason, when), and a paused campaign resumes by moving
to the unfinished pose again, every pose measured exactly once.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest

from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.daemon.store import Store
from robocal.drivers.sim import LtpSimOptions, ModbusSimOptions, SimCell, SimWorld
from robocal.drivers.sim.fanuc_rmi import FanucSimOptions
from tests._waiting import eventually
from tests.unit.daemon.conftest import ROBOT, random_plan

HALT_BOUND_S = 0.2


async def _halted_after(world: SimWorld, t_request: float, watch_s: float = 0.25) -> float:
    """Watch the world's joints for ``watch_s``; seconds after ``t_request`` of the last change."""
    last = world.q_actual_rad
    last_change = t_request
    end = time.monotonic() + watch_s
    while time.monotonic() < end:
        await asyncio.sleep(0.002)
        q = world.q_actual_rad
        if np.any(q != last):
            last, last_change = q, time.monotonic()
    return last_change - t_request


def _motion_stops(svc_or_store: Any) -> list[dict[str, Any]]:
    store = svc_or_store.store if isinstance(svc_or_store, CalibrationService) else svc_or_store
    return [a for a in store.audit_log() if a["action"] == "motion.stop"]


@contextlib.asynccontextmanager
async def _cell_service(tmp_path: Any, kind: str, *, time_scale: float = 0.1,
                        robot_extra: dict[str, Any] | None = None,
                        modbus: ModbusSimOptions | None = None, connect: bool = True
                        ) -> AsyncIterator[tuple[CalibrationService, SimWorld]]:
    """A service over ``kind``'s simulator (moves at ``time_scale`` of real time) and LTP/1."""
    cell = SimCell(
        robot=ROBOT, seed=2,
        fanuc=FanucSimOptions(time_scale=time_scale) if kind == "fanuc_rmi" else False,
        modbus=(modbus or ModbusSimOptions(time_scale=time_scale))
        if kind == "modbus_plc" else False,
        ltp=LtpSimOptions(time_scale=0.0))
    async with cell:
        cfg = parse_config({
            "data_dir": str(tmp_path / "state"), "robot_description": ROBOT,
            "robot": {"kind": kind,
                      "options": {**cell.robot_options(kind), **(robot_extra or {})}},
            "tracker": {"kind": "ltp", "options": cell.tracker_options("tcp")},
            "measurement": {"settle_s": 0.0, "samples": 2},
            "fit": {"models": ["constant"], "select": "constant", "executor": "thread",
                    "report": False, "cpa": False},
        }, source="test")
        svc = CalibrationService(cfg)
        await svc.start(connect=connect)
        try:
            yield svc, cell.world
        finally:
            await svc.stop()


@contextlib.asynccontextmanager
async def _mock_service(make_config: Any, move_time_s: float = 0.4
                        ) -> AsyncIterator[tuple[CalibrationService, SimWorld]]:
    svc = CalibrationService(make_config(robot={"options": {"move_time_s": move_time_s}}))
    await svc.start()
    try:
        robot = await svc.hub.robot()
        yield svc, robot.world  # type: ignore[attr-defined]
    finally:
        await svc.stop()


async def _mid_move(svc: CalibrationService, world: SimWorld, cid: str, *,
                    after_measured: int) -> None:
    """Wait until ``after_measured`` poses are stored and the robot is moving again."""
    await eventually(lambda: svc.store.campaign(cid).poses_measured >= after_measured
                 and world.moving, 60, what="a move in progress")
    start = world.q_actual_rad
    await eventually(lambda: np.max(np.abs(world.q_actual_rad - start)) > 1e-3, 5,
                     what="joints moving")


@pytest.mark.parametrize("kind", ["fanuc_rmi", "modbus_plc", "mock"])
async def test_pause_mid_move_halts_at_once_and_resume_measures_every_pose_once(
        kind, tmp_path, make_config):
    ctx = (_mock_service(make_config) if kind == "mock"
           else _cell_service(tmp_path, kind))
    async with ctx as (svc, world):
        st = await svc.create(random_plan(6, seed=4), actor="op", measure_only=True)
        cid = st["id"]
        await _mid_move(svc, world, cid, after_measured=2)
        measured = svc.store.campaign(cid).poses_measured
        t_request = time.monotonic()
        st = await svc.pause(cid, actor="op", reason="operator break")
        returned_s = time.monotonic() - t_request
        last_change = await _halted_after(world, t_request)
        halt_at = (world.last_halt_time or math.inf) - t_request
        assert st["state"] == "paused"
        assert 0.0 <= halt_at < HALT_BOUND_S and last_change < HALT_BOUND_S
        assert returned_s < 2.0 and not world.moving
        # the unfinished pose left nothing behind
        assert svc.store.campaign(cid).poses_measured == measured
        stops = _motion_stops(svc)
        assert len(stops) == 1
        d = stops[0]["detail"]
        assert stops[0]["actor"] == "op" and stops[0]["campaign"] == cid
        assert d["trigger"] == "pause" and d["reason"] == "operator break"
        assert d["outcome"] == "stopped" and d["requested_at"] and d["stop_s"] < HALT_BOUND_S
        await svc.resume(cid, actor="op")
        st = await svc.wait(cid, ["measured", "faulted"], timeout=120)
        assert st["state"] == "measured", st["reason"]
        rows = svc.store.measurements(cid)
        assert sorted(r.pose_idx for r in rows) == list(range(6))  # none lost, none twice
        # the pose cut short was moved to again and measured where the plan says
        redo = next(r for r in rows if r.pose_idx == measured)
        assert np.allclose(redo.q_act_deg, redo.q_cmd_deg, atol=0.05)


@pytest.mark.parametrize("kind", ["fanuc_rmi", "modbus_plc"])
async def test_abort_mid_move_halts_the_simulated_robot_within_bound(kind, tmp_path):
    async with _cell_service(tmp_path, kind) as (svc, world):
        st = await svc.create(random_plan(8, seed=5), actor="op", measure_only=True)
        cid = st["id"]
        await _mid_move(svc, world, cid, after_measured=1)
        t_request = time.monotonic()
        st = await svc.abort(cid, actor="op", reason="person in the cell")
        last_change = await _halted_after(world, t_request)
        halt_at = (world.last_halt_time or math.inf) - t_request
        assert st["state"] == "aborted"
        assert 0.0 <= halt_at < HALT_BOUND_S and last_change < HALT_BOUND_S
        (stop,) = _motion_stops(svc)
        assert stop["detail"]["trigger"] == "abort" and stop["detail"]["outcome"] == "stopped"
        assert stop["detail"]["reason"] == "person in the cell"


async def test_shutdown_mid_move_stops_the_robot_first(tmp_path):
    async with _cell_service(tmp_path, "modbus_plc") as (svc, world):
        st = await svc.create(random_plan(8, seed=6), actor="op", measure_only=True)
        cid = st["id"]
        await _mid_move(svc, world, cid, after_measured=1)
        t_request = time.monotonic()
        await svc.stop()
        last_change = await _halted_after(world, t_request)
        halt_at = (world.last_halt_time or math.inf) - t_request
        assert 0.0 <= halt_at < HALT_BOUND_S and last_change < HALT_BOUND_S
        store = Store(svc.config.db_path).open()
        try:
            (stop,) = _motion_stops(store)
            # the campaign stays "running", to resume at the next start
            assert store.campaign(cid).state.value == "running"
        finally:
            store.close()
        assert stop["detail"]["trigger"] == "shutdown" and stop["campaign"] == cid
        assert stop["detail"]["outcome"] == "stopped"


async def test_heartbeat_loss_during_a_move_stops_the_robot_and_faults(tmp_path):
    """The PLC's heartbeat (its watchdog) goes stale mid-move: ABORT goes out, robot halts."""
    sim_options = ModbusSimOptions(time_scale=1.0, heartbeat_stalled=True)
    extra = {"heartbeat_period_s": 0.05, "heartbeat_timeout_s": 0.3}
    async with _cell_service(tmp_path, "modbus_plc", modbus=sim_options, robot_extra=extra,
                             connect=False) as (svc, world):
        st = await svc.create(random_plan(4, seed=7), actor="op", measure_only=True)
        st = await svc.wait(st["id"], ["faulted"], timeout=30)
        assert "heartbeat" in st["reason"]
        (stop,) = _motion_stops(svc)
        assert stop["detail"]["trigger"] == "driver-fault"
        assert stop["detail"]["outcome"] == "stopped" and "heartbeat" in stop["detail"]["reason"]
        assert world.halts == 1 and not world.moving  # halted mid-move, not at the target
        assert await _halted_after(world, time.monotonic(), 0.1) == 0.0


async def test_driver_fault_mid_move_on_rmi_stops_then_faults(tmp_path):
    """A tracker-independent fault during a move (the move times out) stops the robot."""
    async with _cell_service(tmp_path, "fanuc_rmi", time_scale=1.0) as (svc, world):
        svc.config = svc.config.model_copy(
            update={"measurement": svc.config.measurement.model_copy(
                update={"move_timeout_s": 0.15})})
        svc.hub.config = svc.config
        st = await svc.create(random_plan(4, seed=8), actor="op", measure_only=True)
        st = await svc.wait(st["id"], ["faulted"], timeout=30)
        assert "DriverTimeout" in st["reason"]
        (stop,) = _motion_stops(svc)
        assert stop["detail"]["trigger"] == "driver-fault"
        assert stop["detail"]["outcome"] == "stopped"
        assert world.halts == 1 and not world.moving


async def test_a_shutdown_stop_that_raises_is_logged_not_swallowed(make_config, monkeypatch):
    """The daemon's shutdown stop goes on past an unexpected failure, with an error line."""
    from structlog.testing import capture_logs

    from robocal.daemon import main as daemon_main
    from robocal.daemon import service as service_mod

    async def broken_halt(*args: Any, **kwargs: Any) -> bool:
        raise RuntimeError("controller link in an unexpected state")

    async with _mock_service(make_config) as (svc, _world):
        monkeypatch.setattr(service_mod, "halt_motion", broken_halt)
        with capture_logs() as logs:
            assert await daemon_main.stop_robot_for_shutdown(svc) is False
    errors = [e for e in logs if e["log_level"] == "error"]
    assert errors and "may still be moving" in errors[0]["event"]
    assert "unexpected state" in errors[0]["error"]
