"""The third-party PyPI client ``py-openshowvar`` drives the KUKA simulator through a session.

The client speaks KUKAVARPROXY as other people wrote it: plain reads and writes of KRL
variables, one blocking request at a time. The session does what a cell integrator would do
by hand: identify the controller, read the actual axes and position, command a move through
robocal_loop's handshake (docs/protocols/kuka-kvp.md), read back, stop a move with
``RC_STOP``, use the compensation array, and see refusals.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import py_openshowvar  # a test dependency: missing, the test errors rather than skips
from tests._peer import run_steps, session_in_thread

from robocal.drivers.sim import KukaKvpSimulator, KukaSimOptions, SimWorld
from robocal.protocols import kuka_kvp as kvp


def _wait(pred: Callable[[], Any], timeout: float = 10.0) -> Any:
    """Poll ``pred`` (blocking, in the client's thread) until truthy or ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(0.002)
    return None


class _Client:
    """The cell integrator's session: ``py-openshowvar`` requests, one step per method."""

    def __init__(self, sim: KukaKvpSimulator, world: SimWorld) -> None:
        self.sim, self.world, self.dof = sim, world, world.dof
        self.client = py_openshowvar.openshowvar("127.0.0.1", sim.port)
        self.client.sock.settimeout(5.0)
        self.target = [10.0, -20.0, 15.0, 5.0, -30.0, 45.0][: self.dof]
        self.seq = 0

    def read(self, name: str) -> str | None:
        value = self.client.read(name, debug=False)
        return None if value is None else value.decode("latin-1")

    def write(self, name: str, value: str) -> str | None:
        back = self.client.write(name, value, debug=False)
        return None if back is None else back.decode("latin-1")

    def axis_act(self) -> bool:
        q = kvp.parse_e6axis(self.read("$AXIS_ACT") or "", components=self.dof)
        return np.allclose(q, np.degrees(self.world.q_actual_rad), atol=1e-3)

    def pos_act(self) -> bool:
        kind, fields = kvp.parse_struct(self.read("$POS_ACT") or "")
        return kind == "E6POS" and {"X", "Y", "Z", "A", "B", "C", "S", "T"} <= set(fields)

    def soft_limits(self) -> bool:
        lo = kvp.parse_real(self.read("$SOFTN_END[1]") or "")
        hi = kvp.parse_real(self.read("$SOFTP_END[1]") or "")
        return np.allclose([lo, hi], self.world.joint_limits_deg[0], atol=1e-3)

    def handshake_state(self) -> bool:
        cmd, ack = self.read("RC_CMD_SEQ"), self.read("RC_ACK_SEQ")
        self.seq = kvp.parse_int(ack or "")
        return cmd == ack and self.read("RC_STATUS") == "0"

    def write_target(self) -> bool:
        dof, target = self.dof, self.target
        back = self.write("RC_TARGET", kvp.format_e6axis([0.0] * dof))
        back2 = self.write("RC_TARGET", "{A1 " + str(target[0]) + "}")  # KRL partial aggregate
        full = self.write("RC_TARGET", kvp.format_e6axis(target))
        return back is not None and back2 is not None and full is not None and np.allclose(
            kvp.parse_e6axis(back2, components=1), target[:1]) and np.allclose(
            kvp.parse_e6axis(full, components=dof), target, atol=1e-4)

    def command_move(self) -> bool:
        self.seq += 1
        if self.write("RC_SPEED", "30") != "30":
            return False
        return self.write("RC_CMD_SEQ", str(self.seq)) == str(self.seq)

    def move_acknowledged(self) -> bool:
        done = _wait(lambda: self.read("RC_ACK_SEQ") == str(self.seq))
        return bool(done) and self.read("RC_STATUS") == "2"

    def read_back_position(self) -> bool:
        q = kvp.parse_e6axis(self.read("$AXIS_ACT") or "", components=self.dof)
        return np.allclose(q, self.target, atol=1e-2)

    def stop_mid_move(self) -> bool:
        world = self.world
        far = [lo + 0.2 * (hi - lo) for lo, hi in world.joint_limits_deg]
        self.write("RC_TARGET", kvp.format_e6axis(far))
        self.write("RC_SPEED", "1")
        self.seq += 1
        self.write("RC_CMD_SEQ", str(self.seq))
        if not _wait(lambda: self.read("RC_STATUS") == "1" and world.moving):
            return False
        if self.write("RC_STOP", "TRUE") is None:
            return False
        cleared = _wait(lambda: self.read("RC_STOP") == "FALSE")
        q = kvp.parse_e6axis(self.read("$AXIS_ACT") or "", components=self.dof)
        return bool(cleared) and self.read("RC_STATUS") == "4" and not world.moving and (
            self.read("RC_ACK_SEQ") == str(self.seq) and not np.allclose(q, far, atol=1e-2))

    def compensation_array(self) -> bool:
        row = [1.25, -2.5, 3.75, 0.125, -0.5, 0.0625][: self.dof]
        self.write("RC_COMP[3]", kvp.format_e6axis(row))
        back = kvp.parse_e6axis(self.read("RC_COMP[3]") or "", components=self.dof)
        return np.allclose(back, row, atol=1e-5) and self.write("RC_COMP_N", "3") == "3"

    def comp_id(self) -> bool:
        return self.write("RC_COMP_ID[]", '"ab12cd"') == '"ab12cd"' and self.read(
            "RC_COMP_ID[]") == '"ab12cd"'

    def steps(self) -> list[tuple[str, Callable[[], Any]]]:
        client, sim, read, write = self.client, self.sim, self.read, self.write
        return [
            # (not the client's can_connect: it opens a second socket and never closes it)
            ("connected", lambda: client.sock.getpeername()[1] == sim.port),
            ("read $ROBNAME[]", lambda: read("$ROBNAME[]") == f'"{sim.options.robot_name}"'),
            ("read $PRO_STATE1", lambda: read("$PRO_STATE1") == "#P_ACTIVE"),
            ("read $MODE_OP", lambda: read("$MODE_OP") == "#AUT"),
            ("read $AXIS_ACT", self.axis_act),
            ("read $POS_ACT", self.pos_act),
            ("read $SOFTN_END/$SOFTP_END", self.soft_limits),
            ("write $OV_PRO", lambda: write("$OV_PRO", "100") == "100"
             and read("$OV_PRO") == "100"),
            ("read handshake state", self.handshake_state),
            ("write RC_TARGET (whole and partial)", self.write_target),
            ("command a move (RC_SPEED, RC_CMD_SEQ)", self.command_move),
            ("RC_ACK_SEQ acknowledges, RC_STATUS done", self.move_acknowledged),
            ("read back $AXIS_ACT at the target", self.read_back_position),
            ("RC_STOP halts a move", self.stop_mid_move),
            ("RC_COMP[3] written and read back", self.compensation_array),
            ("RC_COMP_ID[] written and read back", self.comp_id),
            ("unknown variable refused", lambda: read("NO_SUCH_VAR") is None),
            ("$AXIS_ACT is read-only", lambda: write("$AXIS_ACT", "{A1 0.0}") is None),
            ("bad value for an INT refused", lambda: write("RC_SPEED", "fast") is None
             and read("RC_SPEED") == "1"),
            ("close", lambda: client.close() or True),
        ]


def _session(sim: KukaKvpSimulator, world: SimWorld) -> tuple[int, int, list[str]]:
    steps = _Client(sim, world).steps()
    return run_steps(steps)


async def test_py_openshowvar_session_passes_every_step(capsys):
    world = SimWorld.create(seed=14)
    sim = KukaKvpSimulator(world, KukaSimOptions(time_scale=0.05))
    await sim.start()
    passed, tried, failures = await session_in_thread(sim, "py-openshowvar", capsys, _session,
                                                      sim, world)
    assert not failures, failures
    assert passed == tried == 20
    assert sim.moves == 2 and sim.stops == 1
    assert math.isclose(sim.override, 100)
