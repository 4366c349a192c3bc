"""The kuka_kvp driver against the KUKAVARPROXY simulator: refusals, faults, compensation."""

from __future__ import annotations

import contextlib
import math
from collections.abc import AsyncIterator
from typing import Any

import pytest

from robocal.compensation import CompensationTable, TargetRow
from robocal.drivers import load_robot_driver
from robocal.drivers.kuka_kvp import KukaKvpRobot
from robocal.drivers.sim import FaultConfig, KukaKvpSimulator, KukaSimOptions, SimWorld
from robocal.errors import (
    CompensationError,
    ConfigError,
    ConnectFailed,
    LimitViolation,
    MotionRejected,
)


@contextlib.asynccontextmanager
async def kuka(world: SimWorld, *, faults: FaultConfig | None = None, **sim_options: Any
               ) -> AsyncIterator[tuple[KukaKvpSimulator, dict[str, Any]]]:
    sim = KukaKvpSimulator(world, KukaSimOptions(time_scale=0.0, **sim_options), faults)
    await sim.start()
    try:
        limits = [list(lim) for lim in world.joint_limits_deg]
        yield sim, {"port": sim.port, "joint_limits_deg": limits, "poll_interval_s": 0.001}
    finally:
        await sim.stop()


def _mid(world: SimWorld, frac: float = 0.5) -> list[float]:
    return [lo + frac * (hi - lo) for lo, hi in world.joint_limits_rad]


def _targets(world: SimWorld, indices: tuple[int, ...]) -> CompensationTable:
    rows = [TargetRow(index=i, q_deg=[math.degrees(v) for v in _mid(world, 0.4 + 0.01 * i)],
                      status="ok", model_residual_mm=0.01) for i in indices]
    rows.append(TargetRow(index=7, q_deg=[0.0] * world.dof, status="unreachable",
                          model_residual_mm=0.0))
    return CompensationTable(kind="targets", targets=rows, model_id="m", robot="r",
                             valid_range_deg=[], predicted_residual_mm=0.02).sealed()


async def test_connect_needs_the_running_loop(world):
    async with kuka(world, program_running=False) as (sim, options):
        robot = load_robot_driver("kuka_kvp", options)
        with pytest.raises(ConnectFailed, match=r"\$PRO_STATE1 #P_STOP"):
            await robot.connect(timeout=2)
        assert robot.state == "closed"
        assert [r.name for r in sim.requests] == ["$ROBNAME[]", "$PRO_STATE1"]


async def test_loop_refuses_a_target_beyond_the_software_limits(world):
    soft = tuple((lo + 20.0, hi) for lo, hi in world.joint_limits_deg)
    async with kuka(world, joint_limits_deg=soft) as (sim, options), KukaKvpRobot(options) as robot:
        q = _mid(world)
        q[0] = math.radians(world.joint_limits_deg[0][0] + 10.0)  # inside robocal's limits
        with pytest.raises(LimitViolation, match="RC_ERROR 1"):
            await robot.move_to(q, timeout=5)
        assert sim.moves == 0 and sim.read("RC_STATUS") == ("3", True)
        reached = await robot.move_to(_mid(world), timeout=5)  # the next move works
        assert max(abs(a - b) for a, b in zip(reached.q_rad, _mid(world), strict=True)) < 1e-4


async def test_motion_fault_is_rejected_and_the_loop_goes_on(world):
    async with (kuka(world, faults=FaultConfig(alarm_rate=1.0)) as (sim, options),
                KukaKvpRobot(options) as robot):
        with pytest.raises(MotionRejected, match="motion fault"):
            await robot.move_to(_mid(world), timeout=5)
        sim.faults.config = FaultConfig()
        await robot.move_to(_mid(world), timeout=5)
        assert sim.moves == 1


async def test_targets_table_in_rc_comp_with_snapshot_and_restore(world):
    async with kuka(world) as (sim, options), KukaKvpRobot(options) as robot:
        assert await robot.read_compensation() is None
        table = _targets(world, (0, 2, 5))
        before = await robot.snapshot_compensation(table)
        assert set(before.items) == {"rc_comp:1", "rc_comp:3", "rc_comp:6", "rc_comp_n"}
        await robot.write_compensation(table)
        assert sim.read("RC_COMP_N") == ("6", True)
        assert sim.read("RC_COMP_ID[]") == (f'"{table.checksum[:64]}"', True)
        back = await robot.read_compensation()
        assert back is not None and back.targets is not None
        assert [r.index for r in back.targets] == [0, 2, 5, 7]
        # someone edits the array on the pendant: the slots show it
        sim.write("RC_COMP[3]", "{A1 1.5}")
        like = await robot.read_compensation_like(table)
        assert like.targets is not None and like.targets[1].q_deg[0] == 1.5
        await robot.restore_snapshot(before)
        assert sim.read("RC_COMP[3]")[0].startswith("{E6AXIS: A1 0.0,")
        assert sim.read("RC_COMP_N") == ("0", True)
        assert await robot.read_compensation() is None


async def test_tables_that_do_not_fit_are_refused_before_writing(world):
    async with (kuka(world, comp_size=4) as (sim, options),
                KukaKvpRobot({**options, "comp_size": 4}) as robot):
        sent = len(sim.requests)
        with pytest.raises(CompensationError, match="RC_COMP"):
            await robot.write_compensation(_targets(world, (0, 4)))
        frames = CompensationTable.model_validate({
            "kind": "frames", "model_id": "m", "robot": "r", "valid_range_deg": [],
            "predicted_residual_mm": 0.0,
            "frames": {"base": dict.fromkeys("xyzwpr", 0.0),
                       "tool": dict.fromkeys("xyzwpr", 0.0)}})
        with pytest.raises(CompensationError, match="only 'targets'"):
            await robot.write_compensation(frames)
        assert len(sim.requests) == sent


async def test_lost_proxy_and_options(world):
    async with kuka(world) as (sim, options):
        robot = KukaKvpRobot(options)
        await robot.connect(timeout=2)
        await sim.stop()
        with pytest.raises(ConnectFailed):
            await robot.read_joints()
        await robot.close()
    with pytest.raises(ConfigError):
        KukaKvpRobot({"joint_limits_deg": [[-1.0, 1.0]] * 6, "colour": "orange"})


async def test_controller_calibration_reads_abs_accur_mastering_and_machine_data(world):
    async with kuka(world) as (sim, options):
        robot = load_robot_driver("kuka_kvp", options)
        await robot.connect(timeout=2)
        try:
            first = await robot.controller_calibration()
            assert first.absolute_accuracy is False
            assert first.facts["$ABS_ACCUR"] == "#NONE"
            assert first.facts["$MAMES[2]"] == "-90.0"
            assert first.facts["$TIRORO"].startswith("{FRAME:")
            assert await robot.controller_calibration() == first
            sim.calibration_vars["$MAMES[2]"] = "-90.0012"  # mastered again
            second = await robot.controller_calibration()
            assert second.fingerprint != first.fingerprint
            sim.calibration_vars["$ABS_ACCUR"] = "#ACTIVATED"
            assert (await robot.controller_calibration()).absolute_accuracy is True
            # a controller that does not know a variable (KSS 5 has no ENUM $ABS_ACCUR ...)
            del sim.calibration_vars["$ABS_ACCUR"]
            third = await robot.controller_calibration()
            assert third.facts["$ABS_ACCUR"] is None and third.absolute_accuracy is None
        finally:
            await robot.close()
