"""KUKA KRC4/KRC5 robot through KUKAVARPROXY (KVP) and robocal's KRL loop.

Protocol and program: ``docs/protocols/kuka-kvp.md``, ``deploy/kuka/robocal_loop.src/.dat``.

Connect: open TCP to the proxy (port 7000), read ``$ROBNAME[]`` and ``$PRO_STATE1`` (the
robot interpreter must run: ``#P_ACTIVE``), then ``RC_CMD_SEQ``/``RC_ACK_SEQ`` (an
unknown variable means robocal_loop.dat is not loaded). A move writes ``RC_TARGET`` (an
E6AXIS, degrees), ``RC_SPEED`` (percent) and then the next ``RC_CMD_SEQ``; the loop answers
by copying it to ``RC_ACK_SEQ`` with ``RC_STATUS`` 2 (done), 3 (error, ``RC_ERROR`` says
why) or 4 (stopped). Actual joints come from ``$AXIS_ACT``. :meth:`KukaKvpRobot.stop`
writes ``RC_STOP=TRUE``, which the loop's interrupt brakes on (``BRAKE``, ``RESUME``),
and waits until the interrupt has cleared it. KVP answers one request at a time per
connection; requests are serialised by a lock, and a move polls between them so that a stop
gets through.

Compensation: ``targets`` tables, row ``i`` (its corrected joints) in ``RC_COMP[i+1]``
(a global E6AXIS array), ``RC_COMP_N`` rows, ``RC_COMP_ID[]`` the table's checksum; all read
back and compared.

Controller calibration (ADR 0033): ``$ABS_ACCUR`` (the positionally accurate robot model,
KUKA's absolute-accuracy option), the mastering offsets ``$MAMES[1..dof]`` and the kinematic
machine data named in ``calibration_variables``, as KRL text; a variable the controller does
not know is recorded as None.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from pydantic import Field

from robocal import errors
from robocal.compensation import CompensationTable, TargetRow
from robocal.drivers import api
from robocal.drivers._base import CompensatingRobotBase, DriverOptions, RobotOptions
from robocal.drivers._compensation import ControllerSnapshot, snapshot_diff, table_diff
from robocal.protocols import TcpTransport
from robocal.protocols import kuka_kvp as kvp
from robocal.protocols.session import Request, Window

__all__ = ["KukaKvpOptions", "KukaKvpRobot"]

#: RC_STATUS values of robocal_loop.src.
_DONE, _ERROR, _STOPPED = 2, 3, 4
_ERRORS = {1: "target outside the software limits", 2: "motion fault", 3: "speed not 1..100"}
_MAX_SEQ = 2**31 - 1


class KukaKvpOptions(RobotOptions):
    """Options of :class:`KukaKvpRobot`.

    Attributes
    ----------
    host, port
        KUKAVARPROXY address (port 7000 on the controller).
    request_timeout_s
        Per KVP request, seconds.
    poll_interval_s
        Pause between polls of ``RC_ACK_SEQ`` during a move, seconds.
    stop_timeout_s
        How long the stop interrupt may take to clear ``RC_STOP``, seconds.
    comp_size
        Length of ``RC_COMP`` as declared in robocal_loop.dat.
    verify_tol
        Read-back tolerance, degrees (KRL REAL is a 32-bit float).
    calibration_variables
        System variables and machine data read (with ``$ABS_ACCUR`` and ``$MAMES[i]``) as
        the controller's own calibration.
    """

    host: str = "127.0.0.1"
    port: int = Field(default=kvp.DEFAULT_PORT, ge=1, le=65535)
    request_timeout_s: float = Field(default=2.0, gt=0.0)
    poll_interval_s: float = Field(default=0.005, gt=0.0)
    stop_timeout_s: float = Field(default=2.0, gt=0.0)
    comp_size: int = Field(default=100, ge=1)
    verify_tol: float = Field(default=1e-3, ge=0.0)
    calibration_variables: tuple[str, ...] = ("$LENGTH_A", "$LENGTH_B", "$TIRORO", "$TFLWP",
                                              "$TX3P3")


#: ``$ABS_ACCUR`` texts meaning the positionally accurate model is in use (KSS 8: ENUM; KSS 5:
#: BOOL).
_ABS_ACTIVE = frozenset({"#ACTIVATED", "TRUE"})


class KukaKvpRobot(CompensatingRobotBase, api.ControllerCalibrationReadable):
    """KUKA KRC4/KRC5 running robocal_loop, through KUKAVARPROXY.

    Parameters
    ----------
    options : KukaKvpOptions or mapping
        Validated options (``joint_limits_deg`` is required; joints map to A1..A6, then
        E1..E3).
    """

    kind: ClassVar[str] = "kuka_kvp"
    Options: ClassVar[type[DriverOptions]] = KukaKvpOptions
    options: KukaKvpOptions
    supported_compensation: ClassVar[frozenset[str]] = frozenset({"targets"})

    def __init__(self, options: KukaKvpOptions | Mapping[str, Any] | None = None) -> None:
        super().__init__(options)
        self.robot_name: str | None = None
        self._transport: TcpTransport | None = None
        self._framer = kvp.KvpFramer()
        self._io_lock = asyncio.Lock()
        self._msg_id = 0
        #: One request outstanding, matched by message id (sans-I/O).
        self._window: Window[int] = Window(1)
        self._seq = 0
        self._stop_gen = 0
        self._lost: Exception | None = None
        self._last_table: CompensationTable | None = None
        self._move_pending = False

    # --- KVP requests --------------------------------------------------------------------------
    async def _request(self, name: str, value: str | None = None) -> kvp.Reply:
        """One KVP read (``value`` None) or write; returns the reply (``ok`` not checked)."""
        transport = self._transport
        if self.state not in ("connected", "connecting") or transport is None:
            raise errors.ConnectFailed("not connected; call connect() first", kind=self.kind)
        if self._lost is not None:
            raise self._lost
        timeout = self.options.request_timeout_s
        async with self._io_lock:
            self._msg_id = (self._msg_id + 1) & 0xFFFF
            mode = kvp.MODE_READ if value is None else kvp.MODE_WRITE
            req = kvp.Request(self._msg_id, mode, name, value)
            sent = self._window.open(req.msg_id, name, time.monotonic() + timeout)
            try:
                with self.translate_errors():
                    await transport.write(kvp.encode_request(req))
                    return await self._reply_to(transport, sent)
            except (errors.ConnectFailed, errors.DriverTimeout, errors.TransportError) as err:
                # The stream is out of step (or gone): no later reply can be trusted.
                self._lost = errors.ConnectFailed(f"KVP link lost: {err}", kind=self.kind)
                raise self._lost from err
            finally:
                self._window.drop(sent)

    async def _reply_to(self, transport: TcpTransport, sent: Request[int]) -> kvp.Reply:
        """Read until the reply carrying ``sent``'s message id arrives; skip stale ones."""
        while True:
            msg = self._framer.next_message()
            if msg is not None:
                reply = kvp.decode_reply(msg)
                if self._window.answer(reply.msg_id) is sent:
                    return reply
                self.log.warning("stale KVP reply ignored", msg_id=reply.msg_id)
                continue
            now = time.monotonic()
            if self._window.timeout(now):
                timeout = self.options.request_timeout_s
                raise errors.DriverTimeout(f"no KVP reply for {sent.name} within {timeout} s",
                                           kind=self.kind)
            self._framer.feed(await transport.read(4096, timeout=sent.deadline - now))

    async def _read(self, name: str) -> str:
        reply = await self._request(name)
        if not reply.ok:
            raise errors.OperationError(f"KVP cannot read {name}", kind=self.kind)
        return reply.value

    async def _write(self, name: str, value: str) -> str:
        reply = await self._request(name, value)
        if not reply.ok:
            raise errors.OperationError(f"KVP refused {name}={value[:60]}", kind=self.kind)
        return reply.value

    async def _read_int(self, name: str) -> int:
        return kvp.parse_int(await self._read(name))

    # --- connection ----------------------------------------------------------------------------
    async def _connect_impl(self, timeout: float) -> None:
        o = self.options
        self._lost = None
        self._framer = kvp.KvpFramer()
        self._transport = TcpTransport(o.host, o.port)
        await self._transport.open(timeout=timeout)
        self.robot_name = kvp.parse_string(await self._read("$ROBNAME[]")).strip()
        state = (await self._read("$PRO_STATE1")).strip()
        if state != "#P_ACTIVE":
            raise errors.ConnectFailed(
                f"the robot interpreter is not running ($PRO_STATE1 {state}): select "
                "robocal_loop and start it in AUT or EXT", kind=self.kind)
        try:
            cmd, ack = await self._read_int("RC_CMD_SEQ"), await self._read_int("RC_ACK_SEQ")
        except errors.OperationError as err:
            raise errors.ConnectFailed(
                "RC_CMD_SEQ/RC_ACK_SEQ unknown: robocal_loop.dat is not loaded "
                "(deploy/kuka/)", kind=self.kind) from err
        self._seq = max(cmd, ack)
        if cmd != ack:
            # A move commanded by an earlier session is still running: halt it.
            self.log.warning("a move from an earlier session is pending; stopping it")
            await self._halt()
        self.log.info("kvp session", robot=self.robot_name, seq=self._seq)

    async def _close_impl(self) -> None:
        if self._move_pending and self._lost is None and self._transport is not None:
            # Never leave the robot moving on its own.
            with contextlib.suppress(Exception):
                await self._halt()
        if self._transport is not None:
            await self._transport.close()
        self._transport = None

    # --- controller calibration ----------------------------------------------------------------
    async def controller_calibration(self) -> api.ControllerCalibration:
        """``$ABS_ACCUR``, ``$MAMES[i]`` and the machine data as KRL text (None: unknown)."""
        names = ["$ABS_ACCUR", *(f"$MAMES[{i}]" for i in range(1, self.dof + 1)),
                 *self.options.calibration_variables]
        facts: dict[str, str | None] = {}
        for name in names:
            reply = await self._request(name)
            facts[name] = reply.value.strip() if reply.ok else None
        abs_accur = facts["$ABS_ACCUR"]
        return api.ControllerCalibration(
            "kuka-kvp-system-variables", facts,
            absolute_accuracy=None if abs_accur is None else abs_accur.upper() in _ABS_ACTIVE)

    # --- robot API -----------------------------------------------------------------------------
    def _next_seq(self) -> int:
        self._seq = 1 if self._seq >= _MAX_SEQ else self._seq + 1
        return self._seq

    async def move_to(
        self, q_rad: Sequence[float], *, speed_pct: float | None = None, timeout: float = 60.0
    ) -> api.JointReading:
        """Move to ``q_rad`` (radians) through the RC_* handshake; return the actual joints.

        Raises as :meth:`robocal.drivers.api.JointMover.move_to`; LimitViolation also when the
        loop refuses the target, MotionStopped when :meth:`stop` halted the move,
        DriverTimeout when ``RC_ACK_SEQ`` does not reach ``RC_CMD_SEQ``.
        """
        q, speed = self._move_target(q_rad, speed_pct)
        self._ensure_connected()
        deadline = time.monotonic() + timeout
        gen = self._stop_gen
        await self._write("RC_TARGET", kvp.format_e6axis([math.degrees(v) for v in q]))
        await self._write("RC_SPEED", kvp.format_int(max(1, min(100, round(speed)))))
        if gen != self._stop_gen:
            raise errors.MotionStopped("stop requested before the move was sent", kind=self.kind)
        seq = self._next_seq()
        self._move_pending = True
        await self._write("RC_CMD_SEQ", kvp.format_int(seq))
        while True:
            ack = await self._read_int("RC_ACK_SEQ")
            if ack == seq:
                break
            if time.monotonic() > deadline:
                raise errors.DriverTimeout(
                    f"robocal_loop did not acknowledge move {seq} within {timeout:.3g} s "
                    f"(RC_ACK_SEQ {ack})", kind=self.kind)
            await asyncio.sleep(self.options.poll_interval_s)
        self._move_pending = False
        status = await self._read_int("RC_STATUS")
        if status == _DONE:
            return await self.read_joints()
        if status == _STOPPED:
            raise errors.MotionStopped(f"move {seq} stopped (RC_STOP)", kind=self.kind)
        if status == _ERROR:
            code = await self._read_int("RC_ERROR")
            text = f"robocal_loop refused move {seq}: RC_ERROR {code} ({_ERRORS.get(code, '?')})"
            if code == 1:
                raise errors.LimitViolation(text, kind=self.kind)
            raise errors.MotionRejected(text, kind=self.kind, code=code)
        raise errors.OperationError(
            f"move {seq} acknowledged with RC_STATUS {status}", kind=self.kind)

    async def read_joints(self) -> api.JointReading:
        """Return the actual joint angles from ``$AXIS_ACT`` (radians)."""
        self._ensure_connected()
        q_deg = kvp.parse_e6axis(await self._read("$AXIS_ACT"), components=self.dof)
        return api.JointReading(tuple(math.radians(v) for v in q_deg), time.time())

    async def _halt(self) -> None:
        """Write RC_STOP=TRUE and wait until the loop's interrupt has cleared it."""
        await self._write("RC_STOP", kvp.format_bool(True))
        deadline = time.monotonic() + self.options.stop_timeout_s
        while kvp.parse_bool(await self._read("RC_STOP")):
            if time.monotonic() > deadline:
                raise errors.DriverTimeout(
                    f"RC_STOP not cleared within {self.options.stop_timeout_s} s: is "
                    "robocal_loop running with its interrupt on?", kind=self.kind)
            await asyncio.sleep(self.options.poll_interval_s)
        self._move_pending = False

    async def stop(self) -> None:
        """Halt motion through the loop's stop interrupt (``RC_STOP``); a no-op when not
        connected. A ``move_to`` waiting meanwhile raises MotionStopped.

        Raises
        ------
        ConnectFailed
            The link is gone.
        DriverTimeout
            The interrupt did not confirm the halt in ``stop_timeout_s``.
        """
        if self.state != "connected":
            return
        self._stop_gen += 1
        await self._halt()
        self.log.info("stopped")

    # --- compensation --------------------------------------------------------------------------
    def _rows(self, table: CompensationTable) -> list[TargetRow]:
        if table.kind != "targets":
            raise errors.CompensationError(
                f"{self.kind} stores only 'targets' tables (RC_COMP), not {table.kind!r}")
        rows = [r for r in (table.targets or []) if r.status == "ok"]
        for r in rows:
            if not 0 <= r.index < self.options.comp_size:
                raise errors.CompensationError(
                    f"target index {r.index} does not fit RC_COMP[1..{self.options.comp_size}]")
            if len(r.q_deg) != self.dof:
                raise errors.CompensationError(f"target row {r.index} has {len(r.q_deg)} joints")
            api.check_joint_target([math.radians(v) for v in r.q_deg], self.joint_limits_rad,
                                   kind=self.kind)
        return rows

    async def write_compensation(self, table: CompensationTable) -> None:
        """Write a ``targets`` table into ``RC_COMP``, read it back and compare.

        Raises
        ------
        CompensationError
            Not a targets table, or it does not fit ``RC_COMP``.
        LimitViolation
            A row lies outside the joint limits (nothing is written).
        VerificationMismatch
            The controller holds different values afterwards.
        """
        self._ensure_connected()
        sealed = table if table.checksum else table.sealed()
        rows = self._rows(sealed)
        for r in rows:
            await self._write(f"RC_COMP[{r.index + 1}]", kvp.format_e6axis(r.q_deg))
        n = max((r.index + 1 for r in rows), default=0)
        await self._write("RC_COMP_N", kvp.format_int(n))
        await self._write("RC_COMP_ID[]", kvp.format_string(sealed.checksum[:64]))
        self._last_table = sealed
        back = await self.read_compensation()
        diff = table_diff(sealed, back, tol=self.options.verify_tol)
        if back is not None and kvp.parse_string(await self._read("RC_COMP_ID[]")) != \
                sealed.checksum[:64]:
            diff.append("RC_COMP_ID does not hold the table's checksum")
        self._check_read_back(diff, "compensation read back differs")

    async def read_compensation(self) -> CompensationTable | None:
        """The table written in this session with its rows re-read from ``RC_COMP`` (None
        before one was written: KRL variables hold no table metadata)."""
        self._ensure_connected()
        if self._last_table is None:
            return None
        return await self.read_compensation_like(self._last_table)

    async def read_compensation_like(self, table: CompensationTable) -> CompensationTable:
        """``table`` with each ok row's joints replaced by what ``RC_COMP`` holds there."""
        self._ensure_connected()
        rows = []
        for r in table.targets or []:
            if r.status == "ok":
                q = await self._comp_row(r.index + 1)
                r = r.model_copy(update={"q_deg": q})
            rows.append(r)
        back = table.model_copy(update={"targets": rows})
        return back.model_copy(update={"checksum": back.compute_checksum()})

    async def _comp_row(self, element: int) -> list[float]:
        try:
            return kvp.parse_e6axis(await self._read(f"RC_COMP[{element}]"),
                                    components=self.dof)
        except errors.UnexpectedReply as err:
            raise errors.VerificationMismatch(f"RC_COMP[{element}] unreadable: {err}",
                                              kind=self.kind, diff=[str(err)]) from err

    async def snapshot_compensation(self, table: CompensationTable) -> ControllerSnapshot:
        """What ``RC_COMP`` holds in the rows ``table`` would write, and ``RC_COMP_N``."""
        self._ensure_connected()
        items: dict[str, Any] = {}
        for r in self._rows(table):
            items[f"rc_comp:{r.index + 1}"] = await self._comp_row(r.index + 1)
        items["rc_comp_n"] = await self._read_int("RC_COMP_N")
        return ControllerSnapshot(driver=self.kind, covers="targets", items=items)

    async def restore_snapshot(self, snapshot: ControllerSnapshot) -> None:
        """Write a snapshot's rows and count back, read them again and compare.

        Raises
        ------
        VerificationMismatch
            The controller holds different values afterwards.
        """
        self._ensure_connected()
        back: dict[str, Any] = {}
        for key, value in snapshot.items.items():
            if key == "rc_comp_n":
                await self._write("RC_COMP_N", kvp.format_int(int(value)))
                back[key] = await self._read_int("RC_COMP_N")
            elif key.startswith("rc_comp:"):
                element = int(key.partition(":")[2])
                await self._write(f"RC_COMP[{element}]", kvp.format_e6axis(list(value)))
                back[key] = await self._comp_row(element)
            else:
                raise errors.CompensationError(f"snapshot slot {key!r} is not a {self.kind} slot")
        self._last_table = None
        read = snapshot.model_copy(update={"items": back})
        diff = snapshot_diff(snapshot, read, tol=self.options.verify_tol)
        self._check_read_back(diff, "restored values read back differ")
