"""FANUC robot over RMI (Remote Motion Interface, option R912): JSON lines over TCP.

Protocol as robocal speaks it: ``docs/protocols/fanuc-rmi.md``.

Session: ``FRC_Connect`` on the connect port (16001) names the session port (connected with
bounded retries: it may not listen at once); on it ``FRC_GetStatus``, ``FRC_Reset``,
``FRC_GetStatus``, ``FRC_Initialize`` (FANUC's reference sequence, so a resettable alarm does
not stop the connection), then ``FRC_GetStatus`` for NextSequenceID, which newer controllers
keep across ``FRC_Initialize``; instructions carry consecutive SequenceIDs from it, at most 8
in flight. Motions are ``FRC_JointMotionJRep`` with ``TermType FINE``, whose reply
arrives when the robot is in position; actual joints come from ``FRC_ReadJointAngles``,
which returns encoder positions only from RMI MajorVersion 6 on, so older controllers are
refused. A HOLD (SequenceID gap, buffer overrun, system fault) is recovered with
``FRC_GetStatus`` (NextSequenceID) and ``FRC_Reset`` before the next motion.

Compensation: ``frames`` tables go to ``FRC_WriteUFrameData``/``FRC_WriteUToolData``;
``targets`` tables to two position registers per row: J1..J3 in X, Y, Z of
PR[pr_base + 2 index] and J4..J6 in X, Y, Z of PR[pr_base + 2 index + 1], W/P/R zero. RMI
writes PRs only in Cartesian form, whose W/P/R the controller keeps in canonical ranges (a
J6 of 270 or a J5 of 100 degrees would not read back), while X, Y, Z are stored as written;
a TP helper program copies the values element-wise with ``PR[i,j]`` into a joint PR. The PR
configuration names UFrame 0 (world) and the configured UTool (never 0, which has no
documented meaning). Everything is read back and compared.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar

from pydantic import Field

from robocal import errors
from robocal.compensation import CompensationTable, Frame, FramesPayload, TargetRow
from robocal.drivers import api
from robocal.drivers._base import CompensatingRobotBase, DriverOptions, RobotOptions
from robocal.drivers._compensation import ControllerSnapshot, snapshot_diff, table_diff
from robocal.protocols import LineStream, TcpTransport, await_reply
from robocal.protocols import fanuc_rmi as rmi
from robocal.protocols.session import Request, RmiSession, Window

__all__ = ["FanucRmiOptions", "FanucRmiRobot"]

MIN_MAJOR_VERSION = 6
#: Packets still read (non-blocking) once a deadline has passed (a reply already waiting is
#: taken; a controller that talks without end is not waited for).
_LATE_PACKETS = 32
_SEQUENCE_ERRORS = frozenset({rmi.rmit(24), rmi.rmit(28), rmi.rmit(29)})
#: Connection attempts on the session port (back-off 20 ms doubling to 0.5 s, within the
#: connect timeout).
_SESSION_PORT_ATTEMPTS = 8


class FanucRmiOptions(RobotOptions):
    """Options of :class:`FanucRmiRobot`.

    Attributes
    ----------
    host, connect_port
        Controller address; the session port comes from the ``FRC_Connect`` reply.
    group
        Motion group (1 or 2).
    reply_timeout_s
        Timeout for command replies, seconds.
    min_major_version
        Oldest accepted RMI MajorVersion (never below 6: older ones report commanded joints).
    uframe_number, utool_number
        Frames written by a ``frames`` compensation table.
    pr_base, pr_count
        Position registers available to a ``targets`` table: PR[pr_base] to
        PR[pr_base + pr_count - 1], two per row (row ``i`` uses ``pr_base + 2i`` and
        ``pr_base + 2i + 1``).
    verify_tol
        Read-back tolerance, mm and degrees.
    override_pct
        Speed override set after connecting (None leaves it).
    """

    host: str = "127.0.0.1"
    connect_port: int = Field(default=rmi.DEFAULT_CONNECT_PORT, ge=1, le=65535)
    group: int = Field(default=1, ge=1, le=2)
    reply_timeout_s: float = Field(default=5.0, gt=0.0)
    min_major_version: int = Field(default=MIN_MAJOR_VERSION, ge=MIN_MAJOR_VERSION)
    uframe_number: int = Field(default=1, ge=1, le=9)
    utool_number: int = Field(default=1, ge=1, le=10)
    pr_base: int = Field(default=1, ge=1)
    pr_count: int = Field(default=100, ge=1)
    verify_tol: float = Field(default=1e-3, ge=0.0)
    override_pct: int | None = Field(default=None, ge=1, le=100)


class FanucRmiRobot(CompensatingRobotBase):
    """FANUC R-30iB Plus controller through RMI.

    Parameters
    ----------
    options : FanucRmiOptions or mapping
        Validated options (``joint_limits_deg`` is required).
    """

    kind: ClassVar[str] = "fanuc_rmi"
    Options: ClassVar[type[DriverOptions]] = FanucRmiOptions
    options: FanucRmiOptions
    supported_compensation: ClassVar[frozenset[str]] = frozenset({"frames", "targets"})

    def __init__(self, options: FanucRmiOptions | Mapping[str, Any] | None = None) -> None:
        super().__init__(options)
        self.controller_version: tuple[int, int] | None = None
        self.session_port: int | None = None
        self.bad_packets = 0
        self._stream: LineStream | None = None
        self._reader: asyncio.Task[None] | None = None
        self._cmd_lock = asyncio.Lock()
        #: Request matching (sans-I/O); the driver keeps one future per outstanding request.
        self._session = RmiSession()
        self._waiters: dict[Request[str] | Request[int], asyncio.Future[rmi.Packet]] = {}
        self._in_flight = asyncio.Semaphore(rmi.MAX_IN_FLIGHT)
        self._seq_lock = asyncio.Lock()
        self._lost: Exception | None = None
        self._disconnected: asyncio.Future[None] | None = None
        self._last_table: CompensationTable | None = None
        self._stop_gen = 0

    # --- connection ----------------------------------------------------------------------------
    async def _connect_impl(self, timeout: float) -> None:
        o = self.options
        deadline = time.monotonic() + timeout
        self._lost = None
        self._session = RmiSession()
        conn = TcpTransport(o.host, o.connect_port)
        await conn.open(timeout=timeout)
        try:
            stream = LineStream(conn, max_length=rmi.MAX_LINE)
            await stream.write_line(rmi.encode({"Communication": "FRC_Connect"}))
            reply = await self._read_packet(stream, "FRC_Connect", deadline)
        finally:
            await conn.close()
        if reply.error_id:
            raise errors.ConnectFailed(
                f"FRC_Connect refused: {rmi.describe_error(reply.error_id)}", kind=self.kind
            )
        major = reply.get_int("MajorVersion")
        minor = _int_or(reply.body.get("MinorVersion"), 0)
        self.controller_version = (major, minor)
        if major < o.min_major_version:
            raise errors.ConnectFailed(
                f"controller runs RMI MajorVersion {major}; robocal needs {o.min_major_version} "
                "or later because older versions make FRC_ReadJointAngles return commanded, "
                "not actual (encoder) joint angles, which is useless for calibration",
                kind=self.kind,
            )
        self.session_port = reply.get_int("PortNumber")
        main = await self._open_session_port(self.session_port, deadline)
        self._stream = LineStream(main, max_length=rmi.MAX_LINE)
        self._reader = asyncio.create_task(self._read_loop(self._stream), name="rmi-reader")
        # FANUC's reference sequence: GetStatus, Reset (clears a resettable alarm and HOLD),
        # GetStatus again, then Initialize.
        status = await self._command("FRC_GetStatus")
        if _int_or(status.body.get("RMIMotionStatus"), 0):
            # An earlier session left RMI running: abort it first.
            await self._command("FRC_Abort", check=False)
        reset = await self._command("FRC_Reset", check=False)
        if reset.error_id:
            self.log.warning("FRC_Reset refused", error=rmi.describe_error(reset.error_id))
        status = await self._command("FRC_GetStatus")
        self.log.info(
            "rmi session",
            version=f"{major}.{minor}",
            port=self.session_port,
            servo_ready=status.body.get("ServoReady"),
            tp_mode=status.body.get("TPMode"),
        )
        if _int_or(status.body.get("TPMode"), 0):
            raise errors.ConnectFailed(
                "the teach pendant is enabled: disable it (AUTO mode) and connect again",
                kind=self.kind,
            )
        init = await self._command("FRC_Initialize", check=False, GroupMask=1 << (o.group - 1))
        if init.error_id == rmi.rmit(15):
            # An earlier session left RMI running: abort it and initialise afresh.
            await self._command("FRC_Abort", check=False)
            init = await self._command("FRC_Initialize", check=False, GroupMask=1 << (o.group - 1))
        if init.error_id in (7004, 7015):
            raise errors.ConnectFailed(
                "FRC_Initialize refused: RMI_MOVE is the selected TP program; select another "
                "program on the teach pendant and connect again",
                kind=self.kind,
            )
        if init.error_id:
            alarm = ""
            with contextlib.suppress(Exception):
                alarm = f"; controller alarm: {await self.read_error()}"
            raise errors.ConnectFailed(
                f"FRC_Initialize refused: {rmi.describe_error(init.error_id)}{alarm}",
                kind=self.kind,
            )
        # Newer controllers keep NextSequenceID across FRC_Initialize and drop stale IDs
        # silently, so continue from what the controller expects rather than from 1.
        after = await self._command("FRC_GetStatus")
        self._session.resync(_int_or(after.body.get("NextSequenceID"), 0))
        if o.override_pct is not None:
            await self._command("FRC_SetOverRide", Value=o.override_pct)

    async def _open_session_port(self, port: int, deadline: float) -> TcpTransport:
        """Connect to the session port, retrying with back-off: it may not listen at once."""
        delay = 0.02
        for attempt in range(1, _SESSION_PORT_ATTEMPTS + 1):
            main = TcpTransport(self.options.host, port)
            try:
                await main.open(timeout=max(0.1, deadline - time.monotonic()))
                return main
            except errors.TransportError as err:
                remaining = deadline - time.monotonic()
                if attempt == _SESSION_PORT_ATTEMPTS or remaining <= delay:
                    raise errors.ConnectFailed(
                        f"session port {port} not listening after {attempt} attempts: {err}",
                        kind=self.kind,
                    ) from err
                self.log.info("session port not listening yet; retrying", delay_s=delay)
                await asyncio.sleep(delay)
                delay = min(delay * 2, 0.5)
        raise AssertionError("unreachable")  # pragma: no cover

    async def _read_packet(self, stream: LineStream, name: str, deadline: float) -> rmi.Packet:
        """Read until the packet ``name`` arrives, skipping garbage; bounded by ``deadline``."""
        late = 0
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                # Past the deadline only packets already waiting are taken (non-blocking).
                late += 1
                if late > _LATE_PACKETS:
                    raise errors.DriverTimeout(f"no {name} reply in time", kind=self.kind)
            try:
                packet = rmi.decode(await stream.read_line(timeout=max(0.0, remaining)))
            except errors.TransportTimeout as err:
                raise errors.DriverTimeout(f"no {name} reply in time", kind=self.kind) from err
            except (errors.FramingError, errors.ProtocolError) as err:
                if isinstance(err, errors.TransportError):
                    raise
                self.bad_packets += 1
                self.log.warning("malformed RMI line ignored", error=str(err)[:120])
                continue
            if packet.name == name:
                return packet
            self.log.warning("unexpected RMI packet ignored", packet=packet.name)

    async def _close_impl(self) -> None:
        stream = self._stream
        if stream is not None and stream.transport.is_open and self._lost is None:
            try:
                await self._command("FRC_Abort", check=False, timeout=0.5)
            except Exception as err:
                self.log.error("FRC_Abort on close failed; the robot may still be moving",
                               error=repr(err))
            with contextlib.suppress(Exception):
                self._disconnected = asyncio.get_running_loop().create_future()
                await stream.write_line(rmi.encode({"Communication": "FRC_Disconnect"}))
                async with asyncio.timeout(0.5):
                    await self._disconnected
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader
            self._reader = None
        if stream is not None:
            await stream.transport.close()
        self._stream = None
        self._fail_pending(errors.ConnectFailed("driver closed", kind=self.kind))

    @property
    def _next_seq(self) -> int:
        """SequenceID of the next instruction (kept by the session)."""
        return self._session.next_seq

    @_next_seq.setter
    def _next_seq(self, seq: int) -> None:
        self._session.next_seq = seq

    def _fail_pending(self, exc: Exception) -> None:
        self._session.clear()
        for req in list(self._waiters):
            self._settle(req, exc)

    def _settle(self, req: Request[str] | Request[int], outcome: rmi.Packet | Exception) -> None:
        """Resolve the waiter of ``req`` with a reply packet or an exception."""
        fut = self._waiters.get(req)
        if fut is None or fut.done():
            return
        if isinstance(outcome, Exception):
            fut.set_exception(outcome)
            # Mark retrieved: nobody may be awaiting any more.
            fut.exception()
        else:
            fut.set_result(outcome)

    def _expire(self) -> None:
        """A wait ran out: the session closes every overdue request (late replies are then
        discarded by SequenceID) and their waiters time out."""
        for req in self._session.timeout(time.monotonic()):
            self._settle(req, TimeoutError())

    # --- reader --------------------------------------------------------------------------------
    async def _read_loop(self, stream: LineStream) -> None:
        while True:
            try:
                line = await stream.read_line(timeout=3600.0)
            except errors.TransportTimeout:
                continue
            except errors.TransportError as err:
                if self._lost is None:
                    self._lost = errors.ConnectFailed(f"connection lost: {err}", kind=self.kind)
                self._fail_pending(self._lost)
                return
            except errors.FramingError as err:
                self.bad_packets += 1
                self.log.warning("over-long RMI line skipped", error=str(err)[:120])
                continue
            try:
                packet = rmi.decode(line)
            except errors.ProtocolError as err:
                self.bad_packets += 1
                self.log.warning(
                    "malformed RMI packet ignored", error=str(err)[:120], line=line[:80].hex()
                )
                continue
            self._dispatch(packet)

    def _dispatch(self, packet: rmi.Packet) -> None:
        receipt = self._session.receive(packet)
        if receipt.kind == "reply":
            assert receipt.request is not None
            self._settle(receipt.request, packet)
        elif receipt.kind == "unmatched" and packet.category == "Command":
            self.log.warning("unexpected command reply ignored", packet=packet.name)
        elif receipt.kind == "unmatched":
            self.log.warning("reply for unknown SequenceID ignored",
                             sequence_id=packet.sequence_id)
        elif receipt.kind == "fault":
            seq = packet.sequence_id
            self.log.warning("controller system fault", sequence_id=seq)
            exc = errors.MotionRejected(
                f"controller system fault while executing SequenceID {seq}; "
                "the controller holds until reset",
                kind=self.kind,
                code="FRC_SystemFault",
            )
            for req in receipt.failed:
                self._settle(req, exc)
        elif receipt.kind == "terminate":
            self._lost = errors.ConnectFailed(
                "controller terminated the RMI session", kind=self.kind)
            self._fail_pending(self._lost)
        elif receipt.kind == "disconnect":
            if self._disconnected is not None and not self._disconnected.done():
                self._disconnected.set_result(None)
        else:
            self.log.warning("unexpected communication packet ignored", packet=packet.name)

    # --- requests ------------------------------------------------------------------------------
    def _live_stream(self) -> LineStream:
        self._ensure_connected()
        if self._lost is not None:
            raise self._lost
        assert self._stream is not None
        return self._stream

    async def _command(
        self, name: str, *, check: bool = True, timeout: float | None = None, **fields: Any
    ) -> rmi.Packet:
        """Send one command and wait for its reply (commands are strictly one at a time)."""
        stream = self._stream
        if stream is None or self._lost is not None:
            raise self._lost or errors.ConnectFailed("not connected", kind=self.kind)
        wait = self.options.reply_timeout_s if timeout is None else timeout
        async with self._cmd_lock:
            req = self._session.command(name, time.monotonic() + wait)
            fut = self._waiters[req] = asyncio.get_running_loop().create_future()
            try:
                with self.translate_errors():
                    await stream.write_line(rmi.encode({"Command": name, **fields}))
            except BaseException:
                self._forget(self._session.commands, req)
                raise
            packet = await self._reply(self._session.commands, req, fut,
                                       f"no reply to {name} within {wait:.3g} s")
        if packet.name == "Unknown":
            raise errors.OperationError(
                f"controller could not parse {name}: {rmi.describe_error(packet.error_id or 0)}",
                kind=self.kind,
            )
        if check and packet.error_id:
            raise errors.OperationError(
                f"{name} refused: {rmi.describe_error(packet.error_id)}", kind=self.kind
            )
        return packet

    async def _recover(self) -> None:
        """Leave HOLD: resynchronise the SequenceID from FRC_GetStatus, then FRC_Reset."""
        status = await self._command("FRC_GetStatus")
        nxt = _int_or(status.body.get("NextSequenceID"), 0)
        await self._command("FRC_Reset")
        if nxt >= 1:
            self._session.resync(nxt)
        self._session.hold = False
        self.log.info("recovered from HOLD", next_sequence_id=self._session.next_seq)

    async def _instruction(
        self, build: Callable[[int], dict[str, Any]], deadline: float
    ) -> rmi.Packet:
        """Send one instruction built by ``build(seq)``; wait for its completion reply."""
        stream = self._live_stream()
        async with self._in_flight:
            async with self._seq_lock:
                if self._session.hold:
                    await self._recover()
                payload = build(self._session.next_seq)
                req = self._session.instruction(str(payload.get("Instruction")), deadline)
                fut = self._waiters[req] = asyncio.get_running_loop().create_future()
                try:
                    with self.translate_errors():
                        await stream.write_line(rmi.encode(payload))
                except BaseException:
                    self._session.withdraw(req)
                    self._waiters.pop(req, None)
                    raise
            return await self._reply(self._session.instructions, req, fut,
                                     f"instruction SequenceID {req.key} not completed in time")

    def _forget(self, window: Window[Any], req: Request[Any]) -> None:
        window.drop(req)
        self._waiters.pop(req, None)

    async def _reply(self, window: Window[Any], req: Request[Any],
                     fut: asyncio.Future[rmi.Packet], late: str) -> rmi.Packet:
        """Await the reply to ``req`` until its deadline (DriverTimeout ``late``); then drop it."""
        try:
            return await await_reply(fut, req.deadline - time.monotonic())
        except TimeoutError as err:
            self._expire()
            raise errors.DriverTimeout(late, kind=self.kind) from err
        finally:
            self._forget(window, req)

    # --- robot API -----------------------------------------------------------------------------
    async def move_to(
        self, q_rad: Sequence[float], *, speed_pct: float | None = None, timeout: float = 60.0
    ) -> api.JointReading:
        """Move to ``q_rad`` (radians) with FINE termination; return the actual joints.

        Raises as :meth:`robocal.drivers.api.JointMover.move_to`; MotionRejected when the
        controller refuses the motion or faults while executing it.
        """
        q, speed = self._move_target(q_rad, speed_pct)
        self._live_stream()
        q_deg = [math.degrees(v) for v in q]
        deadline = time.monotonic() + timeout
        gen = self._stop_gen

        def build(seq: int) -> dict[str, Any]:
            # Called just before sending: a stop() since move_to began cancels the move.
            if gen != self._stop_gen:
                raise errors.MotionStopped(
                    "stop requested before the move was sent", kind=self.kind)
            return rmi.joint_motion_jrep(seq, q_deg, speed_pct=speed)

        for attempt in range(3):
            packet = await self._instruction(build, deadline)
            eid = packet.error_id or 0
            if eid == 0:
                return await self.read_joints()
            if eid in _SEQUENCE_ERRORS and attempt < 2:
                self.log.warning(
                    "instruction refused; resynchronising", error=rmi.describe_error(eid)
                )
                self._session.hold = True
                continue
            raise errors.MotionRejected(
                f"FRC_JointMotionJRep refused: {rmi.describe_error(eid)}", kind=self.kind, code=eid
            )
        raise errors.MotionRejected("motion refused after recovery", kind=self.kind)

    async def read_joints(self) -> api.JointReading:
        """Return the actual joint angles from ``FRC_ReadJointAngles`` (radians)."""
        self._live_stream()
        packet = await self._command("FRC_ReadJointAngles", Group=self.options.group)
        q_deg = rmi.joint_angles(packet.body, self.dof)
        return api.JointReading(tuple(math.radians(v) for v in q_deg), time.time())

    async def stop(self) -> None:
        """Halt motion with ``FRC_Abort``, then ``FRC_Initialize`` again for the next move.

        After FRC_Abort the controller drops the queued instructions without replies and RMI
        stops running (RMI_MOVE is aborted), so the driver fails the waiting ``move_to`` with
        MotionStopped and initialises afresh, taking the next SequenceID from
        ``FRC_GetStatus`` (controllers differ in whether it restarts at 1). Instructions are
        held back meanwhile. A no-op when not connected.

        Raises
        ------
        ConnectFailed
            The session is lost.
        DriverTimeout
            The controller did not answer in time.
        OperationError
            FRC_Abort or the re-initialisation was refused.
        """
        if self.state != "connected":
            return
        if self._lost is not None:
            raise self._lost
        async with self._seq_lock:
            self._stop_gen += 1
            abort = await self._command("FRC_Abort", check=False)
            stopped = errors.MotionStopped("motion stopped by request (FRC_Abort)", kind=self.kind)
            for req in self._session.instructions.clear():
                self._settle(req, stopped)
            # RMIT-009 "RMI is not running": nothing was running, which is a stop too.
            if abort.error_id and abort.error_id != rmi.rmit(9):
                raise errors.OperationError(
                    f"FRC_Abort refused: {rmi.describe_error(abort.error_id)}", kind=self.kind
                )
            group_mask = 1 << (self.options.group - 1)
            init = await self._command("FRC_Initialize", check=False, GroupMask=group_mask)
            if init.error_id:
                raise errors.OperationError(
                    f"FRC_Initialize after FRC_Abort refused: "
                    f"{rmi.describe_error(init.error_id)}",
                    kind=self.kind,
                )
            status = await self._command("FRC_GetStatus")
            self._session.resync(_int_or(status.body.get("NextSequenceID"), 0))
            self._session.hold = False
        self.log.info("stopped", next_sequence_id=self._session.next_seq)

    async def read_error(self) -> str:
        """Return the controller's most recent alarm text (``FRC_ReadError``)."""
        packet = await self._command("FRC_ReadError", Count=1)
        return str(packet.body.get("ErrorData", ""))

    # --- compensation --------------------------------------------------------------------------
    async def write_compensation(self, table: CompensationTable) -> None:
        """Write a ``frames`` or ``targets`` table, read it back and compare.

        Raises
        ------
        CompensationError
            The table kind is not supported or does not fit the configured registers.
        LimitViolation
            A target row lies outside the joint limits (nothing is written).
        VerificationMismatch
            The controller holds different values after writing.
        """
        self._live_stream()
        if table.kind == "frames":
            await self._write_frames(table)
        elif table.kind == "targets":
            await self._write_targets(table)
        else:
            raise errors.CompensationError(
                f"{self.kind} stores only 'frames' and 'targets' tables, not {table.kind!r}"
            )
        self._last_table = table
        back = await self.read_compensation()
        diff = table_diff(table, back, tol=self.options.verify_tol)
        self._check_read_back(diff, "compensation read back differs")

    async def _write_frames(self, table: CompensationTable) -> None:
        if table.frames is None:
            raise errors.CompensationError("frames table without a frames payload")
        o = self.options
        base, tool = table.frames.base, table.frames.tool
        await self._command(
            "FRC_WriteUFrameData",
            FrameNumber=o.uframe_number,
            Frame=rmi.frame_fields(base.x, base.y, base.z, base.w, base.p, base.r),
            Group=o.group,
        )
        await self._command(
            "FRC_WriteUToolData",
            ToolNumber=o.utool_number,
            Frame=rmi.frame_fields(tool.x, tool.y, tool.z, tool.w, tool.p, tool.r),
            Group=o.group,
        )

    def _pr_rows(self, table: CompensationTable) -> list[TargetRow]:
        rows = [r for r in (table.targets or []) if r.status == "ok"]
        if self.dof > 6:
            raise errors.CompensationError("targets tables through PRs support at most 6 joints")
        for r in rows:
            self._pr_numbers(r.index)
            api.check_joint_target(
                [math.radians(v) for v in r.q_deg], self.joint_limits_rad, kind=self.kind
            )
        return rows

    def _pr_numbers(self, index: int) -> tuple[int, int]:
        """Return the two PRs of target row ``index`` (J1..J3, then J4..J6, in X, Y, Z).

        Raises
        ------
        CompensationError
            If they lie outside the configured registers.
        """
        o = self.options
        if not 0 <= 2 * index + 1 < o.pr_count:
            raise errors.CompensationError(
                f"target index {index} needs PR[{o.pr_base + 2 * index}] and "
                f"PR[{o.pr_base + 2 * index + 1}], outside the configured "
                f"PR[{o.pr_base}..{o.pr_base + o.pr_count - 1}]"
            )
        return o.pr_base + 2 * index, o.pr_base + 2 * index + 1

    async def _write_targets(self, table: CompensationTable) -> None:
        rows = self._pr_rows(table)  # every row checked before anything is written
        o = self.options
        config = rmi.Configuration(utool_number=o.utool_number).fields()
        for r in rows:
            q = [*r.q_deg, *([0.0] * (6 - len(r.q_deg)))]
            for n, xyz in zip(self._pr_numbers(r.index), (q[:3], q[3:6]), strict=True):
                await self._command(
                    "FRC_WritePositionRegister",
                    RegisterNumber=n,
                    Configuration=config,
                    Position=rmi.frame_fields(xyz[0], xyz[1], xyz[2], 0.0, 0.0, 0.0),
                    Group=o.group,
                )

    async def read_compensation(self) -> CompensationTable | None:
        """Return the last table written in this session, its numbers re-read from the controller.

        RMI has nowhere to keep a table's metadata, so without a table written in this session
        there is nothing to read and the result is None (see :meth:`read_compensation_like`).
        """
        self._live_stream()
        table = self._last_table
        if table is None:
            return None
        return await self.read_compensation_like(table)

    async def snapshot_compensation(self, table: CompensationTable) -> ControllerSnapshot:
        """Read what the controller holds in the frames / registers ``table`` would write.

        Kept by the daemon before its first write, so a rollback restores the controller's
        own values (position registers with their configuration, user and tool frames).
        """
        self._live_stream()
        o = self.options
        items: dict[str, Any] = {}
        if table.kind == "frames":
            uf = await self._command(
                "FRC_ReadUFrameData", FrameNumber=o.uframe_number, Group=o.group
            )
            ut = await self._command("FRC_ReadUToolData", ToolNumber=o.utool_number, Group=o.group)
            items[f"uframe:{o.uframe_number}"] = list(rmi.parse_frame(uf.body))
            items[f"utool:{o.utool_number}"] = list(rmi.parse_frame(ut.body))
        elif table.kind == "targets":
            for r in table.targets or []:
                if r.status != "ok":
                    continue
                for n in self._pr_numbers(r.index):
                    pr = await self._command("FRC_ReadPositionRegister", RegisterNumber=n,
                                             Group=o.group)
                    config = pr.body.get("Configuration")
                    items[f"pr:{n}"] = {
                        "position": list(rmi.parse_frame(pr.body, "Position")),
                        "configuration": dict(config) if isinstance(config, Mapping) else {},
                    }
        else:
            raise errors.CompensationError(
                f"{self.kind} stores only 'frames' and 'targets' tables, not {table.kind!r}"
            )
        return ControllerSnapshot(driver=self.kind, covers=table.kind, items=items)

    async def restore_snapshot(self, snapshot: ControllerSnapshot) -> None:
        """Write the saved frames or position registers back, read them again and compare
        (VerificationMismatch when the controller then holds other values)."""
        self._live_stream()
        o = self.options
        for key, value in snapshot.items.items():
            slot, _, num = key.partition(":")
            n = int(num)
            if slot in ("uframe", "utool"):
                frame = rmi.frame_fields(*value)
                if slot == "uframe":
                    await self._command("FRC_WriteUFrameData", FrameNumber=n, Frame=frame,
                                        Group=o.group)
                else:
                    await self._command("FRC_WriteUToolData", ToolNumber=n, Frame=frame,
                                        Group=o.group)
            elif slot == "pr":
                await self._command(
                    "FRC_WritePositionRegister", RegisterNumber=n,
                    Configuration=dict(value["configuration"]),
                    Position=rmi.frame_fields(*value["position"]), Group=o.group,
                )
            else:
                raise errors.CompensationError(f"snapshot slot {key!r} is not a {self.kind} slot")
        self._last_table = None
        dummy = _snapshot_template(snapshot, o.pr_base)
        back = await self.snapshot_compensation(dummy)
        diff = snapshot_diff(snapshot, back, tol=self.options.verify_tol)
        self._check_read_back(diff, "restored values read back differ")

    async def read_compensation_like(self, table: CompensationTable) -> CompensationTable:
        """``table`` with its numbers replaced by what the controller holds in its slots."""
        self._live_stream()
        o = self.options
        if table.kind == "frames":
            uf = await self._command(
                "FRC_ReadUFrameData", FrameNumber=o.uframe_number, Group=o.group
            )
            ut = await self._command("FRC_ReadUToolData", ToolNumber=o.utool_number, Group=o.group)
            base = Frame(**dict(zip("xyzwpr", rmi.parse_frame(uf.body), strict=True)))
            tool = Frame(**dict(zip("xyzwpr", rmi.parse_frame(ut.body), strict=True)))
            update: dict[str, Any] = {"frames": FramesPayload(base=base, tool=tool)}
        else:
            rows = []
            for r in table.targets or []:
                if r.status != "ok":
                    rows.append(r)
                    continue
                q: list[float] = []
                for n in self._pr_numbers(r.index):
                    pr = await self._command(
                        "FRC_ReadPositionRegister", RegisterNumber=n, Group=o.group
                    )
                    q.extend(rmi.parse_frame(pr.body, "Position")[:3])
                rows.append(r.model_copy(update={"q_deg": q[: len(r.q_deg)]}))
            update = {"targets": rows}
        back = table.model_copy(update=update)
        return back.model_copy(update={"checksum": back.compute_checksum()})


def _snapshot_template(snapshot: ControllerSnapshot, pr_base: int) -> CompensationTable:
    """A table whose slots are the snapshot's (to read the same slots again)."""
    common: dict[str, Any] = {"model_id": "snapshot", "robot": "", "valid_range_deg": [],
                              "predicted_residual_mm": 0.0}
    if snapshot.covers == "frames":
        zero = Frame(x=0.0, y=0.0, z=0.0, w=0.0, p=0.0, r=0.0)
        return CompensationTable(kind="frames", frames=FramesPayload(base=zero, tool=zero),
                                 **common)
    # Row i owns PR[pr_base + 2i] and PR[pr_base + 2i + 1].
    indices = sorted({(int(k.partition(":")[2]) - pr_base) // 2 for k in snapshot.items})
    rows = [TargetRow(index=i, q_deg=[0.0], status="ok", model_residual_mm=0.0)
            for i in indices]
    return CompensationTable(kind="targets", targets=rows, **common)


def _int_or(value: Any, default: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        return default
    return value
