"""The UR simulator's wire rules, spoken to with raw sockets and robocal's codecs."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

import numpy as np
import pytest

from robocal.drivers.sim import SimCell, SimWorld, UrSimOptions, UrSimulator
from robocal.protocols import ur_dashboard as dash
from robocal.protocols import ur_primary as prim
from robocal.protocols import ur_rtde as rtde
from tests._waiting import eventually

pytestmark = pytest.mark.timeout(30)


@contextlib.asynccontextmanager
async def ur_sim(**options: object) -> AsyncIterator[UrSimulator]:
    opts = UrSimOptions(**{"time_scale": 0.0, "start_powered": True, **options})  # type: ignore[arg-type]
    async with SimCell(world=SimWorld.create("ur10", seed=2), fanuc=False, modbus=False,
                       ltp=False, ur=opts) as cell:
        assert cell.ur_sim is not None
        yield cell.ur_sim


class Rtde:
    """A minimal RTDE client for the tests."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.framer = rtde.RtdeFramer()

    @classmethod
    async def open(cls, sim: UrSimulator) -> Rtde:
        return cls(*await asyncio.open_connection(sim.host, sim.ports["rtde"]))

    async def ask(self, data: bytes, ptype: int) -> rtde.RtdePackage:
        self.writer.write(data)
        async with asyncio.timeout(5):
            while True:
                for pkg in self.framer.packages():
                    if pkg.type == ptype:
                        return pkg
                self.framer.feed(await self.reader.read(65536))

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(Exception):
            await self.writer.wait_closed()


async def test_rtde_recipes_refuse_unknown_and_in_use_variables():
    async with ur_sim() as sim:
        a, b = await Rtde.open(sim), await Rtde.open(sim)
        try:
            ok = await a.ask(rtde.request_protocol_version(2), rtde.REQUEST_PROTOCOL_VERSION)
            assert ok.payload == b"\x01"
            bad = await a.ask(rtde.setup_outputs(["actual_q", "no_such"], 125), rtde.SETUP_OUTPUTS)
            assert rtde.parse_recipe_reply(bad.payload) == (0, ["VECTOR6D", "NOT_FOUND"])
            # START without an output recipe is refused
            assert (await a.ask(rtde.encode(rtde.START), rtde.START)).payload == b"\x00"
            mine = await a.ask(rtde.setup_inputs(["input_int_register_30"]), rtde.SETUP_INPUTS)
            assert rtde.parse_recipe_reply(mine.payload) == (1, ["INT32"])
            await b.ask(rtde.request_protocol_version(2), rtde.REQUEST_PROTOCOL_VERSION)
            taken = await b.ask(rtde.setup_inputs(["input_int_register_30"]), rtde.SETUP_INPUTS)
            assert rtde.parse_recipe_reply(taken.payload) == (0, ["IN_USE"])
            a.writer.write(rtde.data_package(1, ["INT32"], [77]))
            await eventually(lambda: sim.int_in[30] == 77, 5, what="input applied")
        finally:
            await a.close()
            await b.close()
        # the register is free again once its owner has gone
        c = await Rtde.open(sim)
        try:
            await c.ask(rtde.request_protocol_version(2), rtde.REQUEST_PROTOCOL_VERSION)
            await eventually(lambda: not any(not s.closed for s in sim._input_owners.values()),
                             5, what="owner released")
            again = await c.ask(rtde.setup_inputs(["input_int_register_30"]), rtde.SETUP_INPUTS)
            assert rtde.parse_recipe_reply(again.payload)[0] == 1
        finally:
            await c.close()


async def test_rtde_streams_the_recipe_and_pause_stops_it():
    async with ur_sim() as sim:
        c = await Rtde.open(sim)
        try:
            await c.ask(rtde.request_protocol_version(2), rtde.REQUEST_PROTOCOL_VERSION)
            names = ["actual_q", "robot_mode", "runtime_state", "output_int_register_24"]
            rep = await c.ask(rtde.setup_outputs(names, 250.0), rtde.SETUP_OUTPUTS)
            rid, types = rtde.parse_recipe_reply(rep.payload)
            sim.int_out[24] = -5
            assert (await c.ask(rtde.encode(rtde.START), rtde.START)).payload == b"\x01"
            data = await c.ask(b"", rtde.DATA_PACKAGE)
            values = rtde.values_by_name(names, types, data.payload[1:])
            assert data.payload[0] == rid == 1
            assert values["robot_mode"] == 7 and values["runtime_state"] == 1
            assert values["output_int_register_24"] == -5
            assert (await c.ask(rtde.encode(rtde.PAUSE), rtde.PAUSE)).payload == b"\x01"
        finally:
            await c.close()


async def test_dashboard_refuses_in_local_mode_and_answers_unknown_commands():
    async with ur_sim(remote_control=False, start_powered=False) as sim:
        reader, writer = await asyncio.open_connection(sim.host, sim.ports["dashboard"])
        try:
            async with asyncio.timeout(5):
                assert (await reader.readline()).decode().strip() == dash.GREETING
                for cmd, reply in (("power on", "Command is not allowed due to safety reasons"),
                                   ("is in remote control", "false"),
                                   ("fly", "could not understand: 'fly'"),
                                   ("robotmode", "Robotmode: POWER_OFF")):
                    writer.write(dash.encode(cmd))
                    got = (await reader.readline()).decode().strip()
                    assert got.startswith(reply), got
        finally:
            writer.close()


async def test_primary_sends_version_then_state_and_runs_scripts():
    async with ur_sim() as sim:
        reader, writer = await asyncio.open_connection(sim.host, sim.ports["primary"])
        framer = prim.PrimaryFramer()
        seen: list[object] = []

        async def until(pred: object) -> object:
            async with asyncio.timeout(5):
                while True:
                    for mtype, body in framer.messages():
                        msg = prim.decode_message(mtype, body)
                        seen.append(msg)
                        if pred(msg):  # type: ignore[operator]
                            return msg
                    framer.feed(await reader.read(65536))

        try:
            first = await until(lambda m: m is not None)
            assert isinstance(first, prim.VersionMessage) and first.major == 5
            state = await until(lambda m: isinstance(m, prim.RobotState))
            assert isinstance(state, prim.RobotState) and state.kinematics == sim.kinematics()
            # a secondary program may not move the arm
            writer.write(b"sec s():\n  movej([0, 0, 0, 0, 0, 0], a=1, v=1)\nend\n")
            exc = await until(lambda m: isinstance(m, prim.RuntimeException))
            assert "may not move" in exc.text  # type: ignore[union-attr]
            # a program replaces the running one; variables with the prefix persist
            writer.write(b"def p():\n  rc_wp_0 = [1, 2, 3, 4, 5, 6]\n  x = 3\nend\n")
            await eventually(lambda: sim.variables["rc_wp_0"] == [1.0, 2, 3, 4, 5, 6], 5,
                             what="installation variable set")
            assert "x" not in sim.variables
            writer.write(b"write_output_float_register(30, x)\n")
            exc = await until(lambda m: isinstance(m, prim.RuntimeException))
            assert "not defined" in exc.text  # type: ignore[union-attr]
        finally:
            writer.close()


async def test_an_unframeable_rtde_package_drops_only_that_client():
    async with ur_sim() as sim:
        bad = await Rtde.open(sim)
        good = await Rtde.open(sim)
        try:
            bad.writer.write(b"\x00\x01V")  # size 1 < the 3-byte header
            async with asyncio.timeout(5):
                assert await bad.reader.read(100) == b""  # closed by the controller
            ok = await good.ask(rtde.request_protocol_version(2), rtde.REQUEST_PROTOCOL_VERSION)
            assert ok.payload == b"\x01"
        finally:
            await bad.close()
            await good.close()


async def test_rtde_outputs_registers_and_32_bit_register_words():
    async with ur_sim() as sim:
        sim.bool_out[1] = sim.bool_out[33] = sim.bool_in[0] = True
        sim.int_out[3], sim.double_in[2] = 7, 0.5
        names = ["output_bit_registers0_to_31", "output_bit_registers32_to_63",
                 "input_bit_registers0_to_31", "output_int_register_3",
                 "input_double_register_2", "output_bit_register_33", "robot_status_bits"]
        values = sim.output_values(names)
        assert values[:6] == [0b10, 0b10, 0b1, 7, 0.5, True]
        assert values[6] == 0b01  # powered, no program running


async def test_ur_rtde_control_program_runs_its_register_protocol():
    # the program as ur-rtde 1.6 sends it to 30003 (its body is not interpreted), with the
    # upper register range: every register the client and the program share is offset by 24
    body = ("    global reg_offset_float = # float register offset\n24"
            "    global reg_offset_int = # int register offset\n24"
            "    global force_mode_type = 2\n"
            "    while keep_running:\n        sync()\n    end\n")
    async with ur_sim(time_scale=0.05) as sim:
        assert "realtime" in sim.ports
        _, writer = await asyncio.open_connection(sim.host, sim.ports["realtime"])
        try:
            writer.write(f"def rtde_control():\n{body}end\n".encode())
            await eventually(lambda: sim.int_out[24] == 1, 5, what="ready for a command")
            assert not sim.runtime_errors            # one program, split at its own end
            assert sim.runtime_state == rtde.RuntimeState.PLAYING
            progress0 = sim.int_out[26]
            assert progress0 & 32768 == 0                      # no operation running

            async def command(cmd: int, ints: dict[int, int], doubles: list[float]) -> None:
                for i, v in ints.items():
                    sim.int_in[24 + i] = v
                sim.double_in[24:24 + len(doubles)] = doubles
                sim.int_in[24] = cmd
                await eventually(lambda: sim.int_out[24] == 2, 5, what=f"command {cmd} done")
                sim.int_in[24] = 0
                await eventually(lambda: sim.int_out[24] == 1, 5, what="ready again")

            target = [0.3, -1.0, 1.0, -0.5, 0.2, 0.1]
            await command(1, {1: 0}, [*target, 1.0, 1.4])      # moveJ, synchronous
            assert list(sim.world.q_cmd_rad) == pytest.approx(target)
            # asynchronous: done at once, the progress register says it runs, then ends
            back = [0.0, -1.2, 1.1, -0.4, 0.3, 0.2]
            await command(1, {1: 1}, [*back, 0.2, 1.4])
            reg = sim.int_out[26]
            assert reg & 32768 and (reg >> 24) == (progress0 >> 24) + 1
            await eventually(lambda: not sim.int_out[26] & 32768, 10, what="async move ended")
            assert list(sim.world.q_actual_rad) == pytest.approx(back, abs=1e-3)
            # stopJ halts an asynchronous move where it is
            await command(1, {1: 1}, [*target, 0.05, 1.4])
            await command(34, {1: 0}, [2.0])
            q = list(sim.world.q_actual_rad)
            assert q != pytest.approx(target, abs=1e-3) and not sim.int_out[26] & 32768
            # a command the emulation does not know is a runtime exception that ends it
            sim.int_in[24] = 3                                 # moveL
            await eventually(lambda: sim.runtime_state == rtde.RuntimeState.STOPPED, 5,
                             what="program ended")
            assert "command 3 is not simulated" in sim.runtime_errors[-1]
            # uploaded again, command 255 ends it without an error
            sim.int_in[24] = 0
            writer.write(f"def rtde_control():\n{body}end\n".encode())
            await eventually(lambda: sim.runtime_state == rtde.RuntimeState.PLAYING, 5,
                             what="running again")
            errors = len(sim.runtime_errors)
            sim.int_in[24] = 255
            await eventually(lambda: sim.runtime_state == rtde.RuntimeState.STOPPED, 5,
                             what="stopped by command 255")
            assert len(sim.runtime_errors) == errors
            # offsets other than the two ranges are refused, not run into other registers
            writer.write(f"def rtde_control():\n{body.replace('24', '40')}end\n".encode())
            await eventually(lambda: len(sim.runtime_errors) == errors + 1, 5,
                             what="bad offsets refused")
            assert "neither 0" in sim.runtime_errors[-1]
            assert sim.runtime_state == rtde.RuntimeState.STOPPED
        finally:
            writer.close()


async def test_the_controllers_tcp_pose_is_its_dh_tables_forward_kinematics():
    from robocal.kinematics import ErrorModelSpec, KinematicModel, matrix_to_rotvec

    async with ur_sim() as sim:
        robot = sim.world.cell.robot
        model = KinematicModel(robot, ErrorModelSpec(robot.dof, ()), np.eye(4))
        q = np.array([[0.3, -1.0, 1.0, -0.5, 0.2, 0.1], [-2.0, -0.5, 2.2, 1.0, -1.5, 3.0]])
        _, R, o = model.flange_poses(q, model.nominal_params())
        for i in range(len(q)):
            pose = sim.tcp_pose(q[i])
            np.testing.assert_allclose(pose[:3], o[i], atol=1e-12)
            np.testing.assert_allclose(pose[3:], matrix_to_rotvec(R[i]), atol=1e-12)
        # the active TCP shifts the point along the flange axes, not the orientation
        sim.tcp = [0.0, 0.0, 0.1, 0.0, 0.0, 0.0]
        pose = sim.tcp_pose(q[0])
        np.testing.assert_allclose(pose[:3], o[0] + 0.1 * R[0][:, 2], atol=1e-12)
        # a new calibration (set_kinematics) changes what the controller computes
        k = sim.kinematics()
        sim.set_kinematics(k.dh_theta, k.dh_a, [k.dh_d[0] + 0.001, *k.dh_d[1:]], k.dh_alpha)
        assert sim.tcp_pose(q[0])[2] == pytest.approx(pose[2] + 0.001, abs=1e-12)
