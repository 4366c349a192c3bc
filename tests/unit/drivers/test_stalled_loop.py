"""A reply that is waiting when a stalled process runs again is taken, not reported as missing.

After SIGSTOP/SIGCONT Linux interrupts ``epoll_wait``; Python (PEP 475) does not poll again
once the wait's timeout is over, so the event loop sees no ready socket and runs the expired
timers first. :class:`StallingSelector` reproduces that deterministically: armed, its next
blocking ``select`` sleeps longer than the request timeout (the simulators, in their own
thread and loop, answer meanwhile) and returns no events. Each driver's request must still
succeed with the reply that is waiting in the socket.
"""

from __future__ import annotations

import asyncio
import selectors
import threading
import time
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

import pytest

from robocal.drivers.emscon import EmsconTracker
from robocal.drivers.fanuc_rmi import FanucRmiRobot
from robocal.drivers.ltp import LtpTracker
from robocal.drivers.modbus_plc import ModbusPlcRobot
from robocal.drivers.sim import (
    FanucRmiSimulator,
    FanucSimOptions,
    LtpSimOptions,
    LtpTrackerSimulator,
    ModbusPlcSimulator,
    ModbusSimOptions,
    SimWorld,
)
from robocal.drivers.sim.emscon import EmsconSimOptions, EmsconTrackerSimulator
from robocal.protocols import LineStream, open_transport

STALL_S = 0.4
TIMEOUT_S = 0.1


class StallingSelector(selectors.DefaultSelector):  # type: ignore[misc,valid-type]
    """A selector whose next blocking ``select`` after :meth:`arm` stalls and sees nothing."""

    def __init__(self) -> None:
        super().__init__()
        self.armed = False
        self.stalls = 0

    def arm(self) -> None:
        self.armed = True

    def select(self, timeout: float | None = None) -> list[Any]:
        if self.armed and (timeout is None or timeout > 0):
            self.armed = False
            self.stalls += 1
            time.sleep(STALL_S)  # the process is stopped; the peer answers meanwhile
            return []  # epoll_wait interrupted by SIGCONT, not polled again
        return super().select(timeout)


class PeerThread:
    """An event loop in a thread for the simulators (the driver's loop is the one stalled)."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def run(self, coro: Coroutine[Any, Any, Any]) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()


def run_stalled(body: Callable[[StallingSelector], Awaitable[None]]) -> StallingSelector:
    selector = StallingSelector()
    loop = asyncio.SelectorEventLoop(selector)
    try:
        loop.run_until_complete(asyncio.wait_for(body(selector), 20))
    finally:
        loop.close()
    return selector


@pytest.fixture
def peer():
    p = PeerThread()
    yield p
    p.close()


@pytest.fixture
def world() -> SimWorld:
    return SimWorld.create(seed=3)


def test_line_read_takes_a_reply_that_waited_through_a_stall(peer: PeerThread) -> None:
    """The transport and line layers: the reply arrived while the loop was stalled."""

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readline()
        writer.write(b"1 OK\r\n")
        await writer.drain()
        await reader.read()  # until the client closes
        writer.close()

    async def listen() -> asyncio.Server:
        return await asyncio.start_server(serve, "127.0.0.1", 0)

    server = peer.run(listen())
    port = server.sockets[0].getsockname()[1]

    async def body(selector: StallingSelector) -> None:
        t = open_transport(f"tcp://127.0.0.1:{port}")
        await t.open(timeout=2)
        stream = LineStream(t)
        selector.arm()
        await stream.write_line("1 HELLO")
        assert await stream.read_line(timeout=TIMEOUT_S) == b"1 OK"
        await t.close()

    async def close() -> None:
        # in the server's own loop: Server.close() from another thread races its wake-up
        server.close()
        await server.wait_closed()

    try:
        assert run_stalled(body).stalls == 1
    finally:
        peer.run(close())


def test_fanuc_rmi_command_reply_waiting_after_stall(peer: PeerThread, world: SimWorld) -> None:
    sim = FanucRmiSimulator(world, FanucSimOptions(time_scale=0.0))
    peer.run(sim.start())

    async def body(selector: StallingSelector) -> None:
        robot = FanucRmiRobot({"connect_port": sim.connect_port,
                               "joint_limits_deg": world.joint_limits_deg,
                               "reply_timeout_s": TIMEOUT_S})
        await robot.connect(timeout=5)
        try:
            selector.arm()
            reading = await robot.read_joints()
            assert len(reading.q_rad) == world.dof
        finally:
            await robot.close()

    try:
        assert run_stalled(body).stalls == 1
    finally:
        peer.run(sim.stop())


def test_ltp_reply_waiting_after_stall(peer: PeerThread, world: SimWorld) -> None:
    sim = LtpTrackerSimulator(world, LtpSimOptions(time_scale=0.0))
    peer.run(sim.start_tcp())

    async def body(selector: StallingSelector) -> None:
        t = LtpTracker({"url": f"tcp://127.0.0.1:{sim.port}", "reply_margin_s": 0.0,
                        "request_timeout_s": TIMEOUT_S})
        await t.connect(timeout=5)
        try:
            selector.arm()
            status = await t.status()
            assert status["ready"] == "1"
            selector.arm()
            reading = await t.measure(samples=1, timeout=TIMEOUT_S, point_id="P1")
            assert reading.point_id == "P1"
        finally:
            await t.close()

    try:
        assert run_stalled(body).stalls == 2
    finally:
        peer.run(sim.stop())


def test_emscon_reply_waiting_after_stall(peer: PeerThread, world: SimWorld) -> None:
    world.move([0.3] * world.dof)
    sim = EmsconTrackerSimulator(world, EmsconSimOptions(time_scale=0.0))
    peer.run(sim.start())

    async def body(selector: StallingSelector) -> None:
        t = EmsconTracker({"host": "127.0.0.1", "port": sim.port, "request_timeout_s": 2.0})
        await t.connect(timeout=5)
        try:
            t.options = t.options.model_copy(update={"request_timeout_s": TIMEOUT_S})
            selector.arm()
            reading = await t.measure(samples=1, timeout=TIMEOUT_S, point_id="P1")
            assert reading.point_id == "P1"
        finally:
            await t.close()

    try:
        assert run_stalled(body).stalls == 1
    finally:
        peer.run(sim.stop())


def test_modbus_reply_waiting_after_stall(peer: PeerThread, world: SimWorld) -> None:
    sim = ModbusPlcSimulator(world, ModbusSimOptions(time_scale=0.0))
    peer.run(sim.start())

    async def body(selector: StallingSelector) -> None:
        robot = ModbusPlcRobot({"port": sim.port, "joint_limits_deg": world.joint_limits_deg,
                                "register_map": sim.map.model_dump(), "poll_interval_s": 0.001,
                                "request_timeout_s": 0.2, "heartbeat_period_s": 5.0,
                                "heartbeat_timeout_s": 30.0})
        await robot.connect(timeout=5)
        try:
            selector.arm()
            reading = await robot.read_joints()
            assert len(reading.q_rad) == world.dof
        finally:
            await robot.close()

    try:
        assert run_stalled(body).stalls == 1
    finally:
        peer.run(sim.stop())
