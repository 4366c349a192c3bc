"""The fanuc_rmi driver through the contract suite against every controller variant.

Each switch of the RMI simulator reproduces one behaviour of real controllers (issue 13,
docs/protocols/fanuc-rmi.md): numbers without a leading zero, NextSequenceID kept across
FRC_Initialize, the plural ``JointAngles`` key, a resettable alarm at connect, and a session
port that starts listening late. The driver must pass the whole suite under all 32
combinations.
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Iterator

import pytest

from robocal.drivers import contracts, load_robot_driver
from robocal.drivers.sim import FanucRmiSimulator, FanucSimOptions, SimWorld

SWITCHES = list(itertools.product((False, True), repeat=5))


def variant_id(flags: tuple[bool, ...]) -> str:
    names = ("bare-point", "seq-persists", "plural-key", "alarm", "late-port")
    return "+".join(n for n, on in zip(names, flags, strict=True) if on) or "plain"


def sim_options(flags: tuple[bool, ...]) -> FanucSimOptions:
    bare, persists, plural, alarm, late = flags
    return FanucSimOptions(
        time_scale=0.0,
        number_style="no_leading_zero" if bare else "json",
        sequence_persists=persists,
        initial_sequence_id=4242 if persists else 1,
        joint_key="JointAngles" if plural else "JointAngle",
        alarm_at_connect=alarm,
        session_port_delay_s=0.02 if late else 0.0,
    )


@pytest.mark.parametrize("flags", SWITCHES, ids=variant_id)
async def test_fanuc_rmi_contract_on_every_controller_variant(flags):
    world = SimWorld.create(seed=5)
    # Joints a few thousandths of a degree from zero, so replies carry numbers below 1.
    world.move([1e-5 * (i + 1) for i in range(world.dof)])
    sim = FanucRmiSimulator(world, sim_options(flags))
    await sim.start()
    try:
        options = {
            "connect_port": sim.connect_port,
            "joint_limits_deg": [list(lim) for lim in world.joint_limits_deg],
        }

        @contextlib.contextmanager
        def real_time() -> Iterator[None]:
            fast = sim.options
            sim.options = fast.model_copy(update={"time_scale": 1.0})
            try:
                yield
            finally:
                sim.options = fast

        rut = contracts.RobotUnderTest(
            f"fanuc_rmi[{variant_id(flags)}]",
            make=lambda: load_robot_driver("fanuc_rmi", options),
            actual_joints=lambda: world.q_actual_rad,
            messages_received=lambda: len(sim.received),
            slow_moves=real_time,
        )
        await contracts.check_robot(rut)
        if flags[1]:
            assert sim.dropped_stale == 0 and sim.next_sequence_id > 4242
    finally:
        await sim.stop()
