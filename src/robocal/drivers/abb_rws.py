"""ABB robot (IRC5 RobotWare 6, OmniCore RobotWare 7) over Robot Web Services.

Protocol as robocal speaks it: ``docs/protocols/abb-rws.md``; decisions in ADR 0029.

The controller runs the RAPID module ``RobocalServer`` (source: ``deploy/abb/
RobocalServer.mod``) in task ``T_ROB1``. A move writes ``rc_target`` (jointtarget, degrees)
and ``rc_speed`` (percent), then ``rc_seq := rc_seq + 1``; the module's loop runs
``MoveAbsJ rc_target`` and sets ``rc_done := rc_seq`` in position (``fine``). The driver polls
``rc_done`` and the execution state; the actual joints come from
``/rw/motionsystem/mechunits/ROB_1/jointtarget`` (measured, not commanded).

Connect: log in (RobotWare 6 digest, 7 basic; then the session cookie), require AUTO, switch
the motors on (optional), stop RAPID, reset the program pointer and start it (``main``
drops any pending command), then wait until the module has taken its start.
Stop: ``execution stop`` (the robot halts on its path at once), then the program pointer to
``main`` and start again, so the next move is taken; a waiting ``move_to`` raises
MotionStopped.

Compensation: ``targets`` and ``joint`` tables go to the persistent jointtarget array
``rc_comp`` (layout in the protocol document), with ``rc_comp_n``, ``rc_comp_kind`` and the
table's checksum in ``rc_comp_sum``; everything is read back and compared.

Controller calibration (ADR 0033): the motion configuration's robot instance
(``/rw/cfg/MOC/ROBOT/instances/<cfg_robot>``; its ``use_robot_calib`` names the robot
calibration in use, ``r1_uncalib`` without Absolute Accuracy) and the motor calibration
offsets (``/rw/cfg/MOC/MOTOR_CALIB/instances``).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import secrets
import ssl as ssl_module
import time
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Literal

import aiohttp
from pydantic import Field

from robocal import errors
from robocal.compensation import CompensationTable, JointCorrection
from robocal.drivers import api
from robocal.drivers._base import CompensatingRobotBase, DriverOptions, RobotOptions
from robocal.drivers._compensation import ControllerSnapshot, snapshot_diff, table_diff
from robocal.protocols import abb_rws as rws

__all__ = ["AbbRwsOptions", "AbbRwsRobot", "RwsRequestError"]

#: Symbols of the RobocalServer module (deploy/abb/RobocalServer.mod).
_SEQ, _DONE, _SPEED, _TARGET = "rc_seq", "rc_done", "rc_speed", "rc_target"
_COMP, _COMP_N, _COMP_KIND, _COMP_SUM = "rc_comp", "rc_comp_n", "rc_comp_kind", "rc_comp_sum"


class RwsRequestError(errors.OperationError):
    """The controller answered a request with an error (``status``, controller ``code``)."""

    def __init__(self, message: str, *, kind: str, status: int, code: int) -> None:
        super().__init__(message, kind=kind)
        self.status, self.rws_code = status, code


class AbbRwsOptions(RobotOptions):
    """Options of :class:`AbbRwsRobot`.

    Attributes
    ----------
    host, port, scheme
        Controller address; the port defaults to 80 (``http``) or 443 (``https``), the scheme
        to ``http`` for RobotWare 6 and ``https`` for 7.
    robotware
        6 (RWS 1.0, digest authentication) or 7 (RWS 2.0, basic authentication).
    username, password
        RWS user (default ``Default User`` on 6, ``Admin`` on 7; password ``robotics``).
    verify_tls, ca_file
        Check the controller's certificate, against the system's CAs or the PEM file
        ``ca_file`` (OmniCore ships a self-signed certificate: export it and name it here, or
        switch checking off on an isolated cell network).
    task, module, mechunit
        Where the RobocalServer module runs and which mechanical unit is read.
    request_timeout_s, poll_interval_s
        Per-request timeout and the polling period while a move runs, seconds.
    motors_on
        Switch the motors on at connect when they are off (AUTO mode only).
    comp_size
        Length of the ``rc_comp`` array as declared in the module.
    verify_tol
        Read-back tolerance, mm and degrees.
    cfg_robot
        Instance of the motion configuration's ``ROBOT`` type read for the controller's own
        calibration.
    """

    host: str = "127.0.0.1"
    port: int | None = Field(default=None, ge=1, le=65535)
    scheme: Literal["http", "https"] | None = None
    robotware: Literal[6, 7] = 6
    username: str | None = None
    password: str = "robotics"
    verify_tls: bool = True
    ca_file: str | None = None
    task: str = "T_ROB1"
    module: str = "RobocalServer"
    mechunit: str = "ROB_1"
    request_timeout_s: float = Field(default=5.0, gt=0.0)
    poll_interval_s: float = Field(default=0.05, gt=0.0, le=5.0)
    motors_on: bool = True
    comp_size: int = Field(default=500, ge=1, le=5000)
    verify_tol: float = Field(default=1e-3, ge=0.0)
    cfg_robot: str = Field(default="ROB_1", pattern=r"^[A-Za-z][A-Za-z0-9_]{0,63}$")


class AbbRwsRobot(CompensatingRobotBase, api.ControllerCalibrationReadable):
    """ABB controller through Robot Web Services and the RobocalServer RAPID module.

    Parameters
    ----------
    options : AbbRwsOptions or mapping
        Validated options (``joint_limits_deg`` is required; at most 6 joints).
    """

    kind: ClassVar[str] = "abb_rws"
    Options: ClassVar[type[DriverOptions]] = AbbRwsOptions
    options: AbbRwsOptions
    supported_compensation: ClassVar[frozenset[str]] = frozenset({"targets", "joint"})

    def __init__(self, options: AbbRwsOptions | Mapping[str, Any] | None = None) -> None:
        super().__init__(options)
        o = self.options
        if self.dof > 6:
            raise errors.ConfigError("a jointtarget holds at most 6 robot axes", source=self.kind,
                                     key="joint_limits_deg")
        self.dialect: rws.Dialect = "rws1" if o.robotware == 6 else "rws2"
        scheme = o.scheme or ("http" if o.robotware == 6 else "https")
        port = o.port or (80 if scheme == "http" else 443)
        self.base_url = f"{scheme}://{o.host}:{port}"
        self.user = o.username or ("Default User" if o.robotware == 6 else "Admin")
        self._http: aiohttp.ClientSession | None = None
        self._challenge: rws.DigestChallenge | None = None
        self._nc = 0
        self._seq = 0
        self._stop_gen = 0
        self._cmd_lock = asyncio.Lock()
        self._last_table: CompensationTable | None = None
        self.requests_sent = 0

    # --- HTTP ----------------------------------------------------------------------------------
    def _authorization(self, req: rws.Request) -> str:
        if self.dialect == "rws2":
            return rws.basic_authorization(self.user, self.options.password)
        assert self._challenge is not None
        self._nc += 1
        return rws.digest_authorization(
            self._challenge, username=self.user, password=self.options.password,
            method=req.method, uri=req.target, nc=self._nc, cnonce=secrets.token_hex(8))

    async def _call(self, req: rws.Request) -> tuple[int, str, bytes]:
        """Send ``req`` (logging in on a 401), return status, content type and body.

        Raises
        ------
        ConnectFailed
            Not connected, no connection, or the credentials are refused.
        DriverTimeout
            No answer within ``request_timeout_s``.
        RwsRequestError
            An error answer (4xx/5xx other than 401).
        """
        http = self._http
        if http is None:
            raise errors.ConnectFailed("not connected; call connect() first", kind=self.kind)
        headers = dict(req.headers)
        for attempt in range(2):
            if attempt:
                headers["Authorization"] = self._authorization(req)
            self.requests_sent += 1
            try:
                async with http.request(
                    req.method, self.base_url + req.target, headers=headers,
                    data=dict(req.form) if req.method == "POST" else None,
                ) as resp:
                    body = await resp.read()
                    status, ctype = resp.status, resp.headers.get("Content-Type", "")
                    www = resp.headers.get("WWW-Authenticate", "")
            except TimeoutError as err:
                raise errors.DriverTimeout(
                    f"{req.method} {req.path}: no answer within "
                    f"{self.options.request_timeout_s} s", kind=self.kind) from err
            except aiohttp.ClientError as err:
                raise errors.ConnectFailed(
                    f"{req.method} {req.path}: {err}", kind=self.kind) from err
            if status != 401:
                break
            if attempt:
                raise errors.ConnectFailed(
                    f"the controller refused user {self.user!r}", kind=self.kind)
            if self.dialect == "rws1":
                try:
                    self._challenge = rws.parse_challenge(www)
                except errors.ProtocolError as err:
                    raise errors.ConnectFailed(
                        f"bad digest challenge: {err}", kind=self.kind) from err
                self._nc = 0
        if status >= 400:
            e = rws.parse_error(status, body, ctype)
            raise RwsRequestError(f"{req.method} {req.path}: {e.message} (HTTP {status}, "
                                  f"code {e.code})", kind=self.kind, status=status, code=e.code)
        return status, ctype, body

    async def _get(self, req: rws.Request) -> list[dict[str, Any]]:
        _, ctype, body = await self._call(req)
        try:
            return rws.parse_states(body, ctype)
        except errors.ProtocolError as err:
            raise errors.UnexpectedReply(f"{req.path}: {err}") from err

    async def _read_var(self, name: str) -> str:
        o = self.options
        items = await self._get(rws.read_symbol(self.dialect, o.task, o.module, name))
        return rws.single(items, "value")

    async def _write_var(self, name: str, value: str) -> None:
        o = self.options
        await self._call(rws.write_symbol(self.dialect, o.task, o.module, name, value))

    async def _read_num(self, name: str) -> float:
        try:
            return rws.parse_num(await self._read_var(name))
        except errors.ProtocolError as err:
            raise errors.UnexpectedReply(f"{name}: {err}") from err

    async def _field(self, req: rws.Request, name: str) -> str:
        return rws.single(await self._get(req), name)

    # --- controller calibration ----------------------------------------------------------------
    async def _cfg(self, cfg_type: str, instance: str | None = None
                   ) -> dict[str, dict[str, str]] | None:
        """Configuration instances (None when the controller has no such resource)."""
        try:
            items = await self._get(rws.cfg_instances(self.dialect, "MOC", cfg_type, instance))
        except RwsRequestError as err:
            if err.status == 404:
                return None
            raise
        return rws.parse_cfg_instances(items)

    async def controller_calibration(self) -> api.ControllerCalibration:
        """The MOC robot instance and motor calibration offsets; Absolute Accuracy is active
        when the robot's ``use_robot_calib`` names a calibration other than ``*uncalib``."""
        robot = await self._cfg("ROBOT", self.options.cfg_robot)
        attrs = None if robot is None else robot.get(self.options.cfg_robot)
        calib = None if attrs is None else attrs.get("use_robot_calib")
        facts = {f"MOC/ROBOT/{self.options.cfg_robot}": attrs,
                 "MOC/MOTOR_CALIB": await self._cfg("MOTOR_CALIB")}
        active = None if calib is None else not calib.lower().endswith("uncalib")
        return api.ControllerCalibration("abb-rws-cfg-moc", facts, absolute_accuracy=active)

    # --- connection ----------------------------------------------------------------------------
    async def _connect_impl(self, timeout: float) -> None:
        o = self.options
        deadline = time.monotonic() + timeout
        ssl: bool | ssl_module.SSLContext = False
        if o.verify_tls and self.base_url.startswith("https:"):
            try:
                ssl = ssl_module.create_default_context(cafile=o.ca_file)
            except (OSError, ssl_module.SSLError) as err:
                raise errors.ConnectFailed(f"cannot load ca_file {o.ca_file}: {err}",
                                           kind=self.kind) from err
        self._http = aiohttp.ClientSession(
            cookie_jar=aiohttp.CookieJar(unsafe=True),
            timeout=aiohttp.ClientTimeout(total=min(o.request_timeout_s, timeout)),
            connector=aiohttp.TCPConnector(ssl=ssl, limit=4),
        )
        self._challenge, self._nc = None, 0
        try:
            async with asyncio.timeout(timeout):
                await self._start_session(deadline)
        except TimeoutError as err:
            raise errors.DriverTimeout(
                f"connect took longer than {timeout} s", kind=self.kind) from err
        except RwsRequestError as err:
            hint = ""
            if err.status == 404:
                hint = (f"; is the {o.module} module (deploy/abb/RobocalServer.mod) loaded "
                        f"in {o.task}?")
            raise errors.ConnectFailed(f"{err}{hint}", kind=self.kind) from err

    async def _start_session(self, deadline: float) -> None:
        o = self.options
        mode = await self._field(rws.opmode(self.dialect), "opmode")
        if mode != "AUTO":
            raise errors.ConnectFailed(
                f"the controller is in {mode}, not AUTO: turn the key to AUTO "
                "(remote start needs it)", kind=self.kind)
        state = await self._field(rws.ctrlstate(self.dialect), "ctrlstate")
        if state != "motoron":
            if not o.motors_on:
                raise errors.ConnectFailed(f"controller state {state}: motors are off",
                                           kind=self.kind)
            await self._call(rws.motors_on(self.dialect))
            state = await self._field(rws.ctrlstate(self.dialect), "ctrlstate")
            if state != "motoron":
                raise errors.ConnectFailed(
                    f"motors did not come on (state {state})", kind=self.kind)
        await self._read_num(_DONE)  # the module is there
        await self._restart_program(deadline)
        self.log.info("rws session", robotware=o.robotware, url=self.base_url,
                      next_seq=self._seq + 1)

    async def _restart_program(self, deadline: float) -> None:
        """Stop RAPID, program pointer to main, start, and wait until main has run its first
        line (``rc_done := rc_seq``): any pending command is dropped."""
        d = self.dialect
        await self._call(rws.stop_execution(d))
        if d == "rws2":  # RobotWare 7 moves the program pointer only with edit mastership
            await self._call(rws.mastership(d, "request"))
            try:
                await self._call(rws.reset_pp(d))
            finally:
                await self._call(rws.mastership(d, "release"))
        else:
            await self._call(rws.reset_pp(d))
        seq = await self._read_num(_SEQ)
        await self._call(rws.start_execution(d))
        while True:
            if await self._read_num(_DONE) == seq:
                break
            if time.monotonic() > deadline:
                raise errors.DriverTimeout("RobocalServer did not start (rc_done never followed "
                                           "rc_seq)", kind=self.kind)
            await asyncio.sleep(self.options.poll_interval_s)
        self._seq = int(seq)

    async def _close_impl(self) -> None:
        http, self._http = self._http, None
        if http is None:
            return
        with contextlib.suppress(Exception):
            async with asyncio.timeout(1.0):
                async with http.get(self.base_url + rws.logout(self.dialect).target):
                    pass
        await http.close()

    # --- motion --------------------------------------------------------------------------------
    async def move_to(self, q_rad: Sequence[float], *, speed_pct: float | None = None,
                      timeout: float = 60.0) -> api.JointReading:
        """Move to ``q_rad`` (radians) with MoveAbsJ, wait in position (``fine``), return the
        actual joints.

        Raises
        ------
        LimitViolation
            Target outside the configured joint limits (nothing is sent).
        MotionStopped
            :meth:`stop` was called during the move.
        MotionRejected
            RAPID execution stopped without a stop request (motion error, pendant stop).
        DriverTimeout
            Not in position within ``timeout`` seconds.
        """
        q = self._check_target(q_rad)
        self._ensure_connected()
        speed = self.options.default_speed_pct if speed_pct is None else float(speed_pct)
        deadline = time.monotonic() + timeout
        gen = self._stop_gen
        async with self._cmd_lock:
            if gen != self._stop_gen:
                raise errors.MotionStopped(
                    "stop requested before the move was sent", kind=self.kind)
            state = await self._field(rws.execution(self.dialect), "ctrlexecstate")
            if gen != self._stop_gen:
                raise errors.MotionStopped(
                    "stop requested before the move was sent", kind=self.kind)
            if state != "running":
                self.log.warning("RAPID was stopped; restarting RobocalServer")
                try:
                    await self._restart_program(deadline)
                except RwsRequestError as err:
                    raise errors.MotionRejected(f"cannot restart RobocalServer: {err}",
                                                kind=self.kind) from err
            await self._write_var(_TARGET, rws.format_jointtarget([math.degrees(v) for v in q]))
            await self._write_var(_SPEED, rws.format_num(max(0.01, min(100.0, speed))))
            if gen != self._stop_gen:
                raise errors.MotionStopped(
                    "stop requested before the move was sent", kind=self.kind)
            seq = self._seq + 1
            await self._write_var(_SEQ, rws.format_num(seq))
            self._seq = seq
        await self._wait_done(seq, gen, deadline, timeout)
        return await self.read_joints()

    async def _wait_done(self, seq: int, gen: int, deadline: float, timeout: float) -> None:
        while True:
            if gen != self._stop_gen:
                raise errors.MotionStopped("motion stopped by request", kind=self.kind)
            if await self._read_num(_DONE) == seq:
                return
            state = await self._field(rws.execution(self.dialect), "ctrlexecstate")
            if gen != self._stop_gen:
                raise errors.MotionStopped("motion stopped by request", kind=self.kind)
            if state != "running":
                if await self._read_num(_DONE) == seq:
                    return
                raise errors.MotionRejected(
                    f"RAPID execution stopped during the move{await self._elog()}",
                    kind=self.kind)
            if time.monotonic() > deadline:
                raise errors.DriverTimeout(f"not in position after {timeout} s", kind=self.kind)
            await asyncio.sleep(self.options.poll_interval_s)

    async def _elog(self) -> str:
        """The newest event-log message, as ``: code title`` (empty if unreadable)."""
        with contextlib.suppress(Exception):
            items = await self._get(rws.elog(self.dialect))
            if items:
                return f": {items[0].get('code', '')} {items[0].get('title', '')}"
        return ""

    async def read_joints(self) -> api.JointReading:
        """The actual joints (``/rw/motionsystem/mechunits/ROB_1/jointtarget``), radians."""
        self._ensure_connected()
        items = await self._get(rws.jointtarget(self.dialect, self.options.mechunit))
        try:
            q_deg = rws.parse_jointtarget_state(items, self.dof)
        except errors.ProtocolError as err:
            raise errors.UnexpectedReply(f"jointtarget: {err}") from err
        return api.JointReading(tuple(math.radians(v) for v in q_deg), time.time())

    async def read_robtarget(self) -> rws.RobTarget:
        """The TCP pose of tool0 in the base frame (mm, quaternion)."""
        self._ensure_connected()
        return rws.parse_robtarget_state(
            await self._get(rws.robtarget(self.dialect, self.options.mechunit)))

    async def stop(self) -> None:
        """Halt at once (``execution stop``), then restart RobocalServer from ``main`` so the
        next move is taken; a waiting :meth:`move_to` raises MotionStopped. A no-op when not
        connected.

        Raises
        ------
        ConnectFailed, DriverTimeout
            The controller cannot be reached to confirm the halt.
        """
        if self.state != "connected":
            return
        self._stop_gen += 1
        await self._call(rws.stop_execution(self.dialect))
        async with self._cmd_lock:
            try:
                await self._restart_program(time.monotonic() + self.options.request_timeout_s)
            except RwsRequestError as err:
                # Halted all the same (e.g. motors off after a guard stop); the next move_to
                # tries the restart again and reports why it fails.
                self.log.warning("stopped; RobocalServer not restarted", error=str(err))
                return
        self.log.info("stopped", next_seq=self._seq + 1)

    # --- compensation --------------------------------------------------------------------------
    def _encode(self, table: CompensationTable) -> list[rws.JointTarget]:
        """Array elements of ``table`` (layout: docs/protocols/abb-rws.md)."""
        out: list[rws.JointTarget] = []
        if table.kind == "targets":
            rows = [r for r in table.targets or [] if r.status == "ok"]
            n = max((r.index + 1 for r in rows), default=0)
            if n > self.options.comp_size:
                raise errors.CompensationError(f"target index {n - 1} does not fit rc_comp"
                                               f"{{{self.options.comp_size}}}")
            out = [rws.JointTarget((0.0,) * 6)] * n
            for r in rows:
                api.check_joint_target([math.radians(v) for v in r.q_deg], self.joint_limits_rad,
                                       kind=self.kind)
                out[r.index] = rws.JointTarget(tuple(r.q_deg) + (0.0,) * (6 - len(r.q_deg)))
        elif table.kind == "joint":
            for e in table.joints or []:
                src = float(e.source_joint or 0)
                for q, dq in zip(e.q_deg, e.dq_deg, strict=True):
                    out.append(rws.JointTarget((float(e.joint), src, q, dq,
                                                e.interpolation_error_bound_deg, 0.0)))
            if len(out) > self.options.comp_size:
                raise errors.CompensationError(f"{len(out)} grid points do not fit rc_comp"
                                               f"{{{self.options.comp_size}}}")
        else:
            raise errors.CompensationError(f"{self.kind} stores 'targets' and 'joint' tables, "
                                           f"not {table.kind!r}")
        return out

    async def write_compensation(self, table: CompensationTable) -> None:
        """Write a ``targets`` or ``joint`` table to ``rc_comp``, read it back and compare.

        Raises
        ------
        CompensationError
            Unsupported kind, or the table does not fit the array.
        LimitViolation
            A target row lies outside the joint limits (nothing written).
        VerificationMismatch
            The controller holds different values afterwards.
        """
        self._ensure_connected()
        items = self._encode(table)
        padded = items + [rws.JointTarget((0.0,) * 6)] * (self.options.comp_size - len(items))
        await self._write_var(_COMP, rws.format_jointtarget_array(padded))
        await self._write_var(_COMP_N, rws.format_num(len(items)))
        await self._write_var(_COMP_KIND, rws.format_string(table.kind))
        await self._write_var(_COMP_SUM, rws.format_string(table.checksum))
        self._last_table = table
        back = await self.read_compensation()
        diff = table_diff(table, back, tol=self.options.verify_tol)
        self._check_read_back(diff, "compensation read back differs")

    async def read_compensation(self) -> CompensationTable | None:
        """The table last written in this session, its numbers re-read from ``rc_comp``; None
        when none was written in this session or the controller's checksum is another's."""
        self._ensure_connected()
        table = self._last_table
        if table is None:
            return None
        held = rws.parse_string(await self._read_var(_COMP_SUM))
        if held != table.checksum:
            return None
        return await self.read_compensation_like(table)

    async def read_compensation_like(self, table: CompensationTable) -> CompensationTable:
        """``table`` with its numbers replaced by what ``rc_comp`` holds."""
        self._ensure_connected()
        kind = rws.parse_string(await self._read_var(_COMP_KIND))
        n = int(await self._read_num(_COMP_N))
        try:
            items = rws.parse_jointtarget_array(await self._read_var(_COMP))[:n]
        except errors.ProtocolError as err:
            raise errors.UnexpectedReply(f"{_COMP}: {err}") from err
        update: dict[str, Any]
        if table.kind == "targets":
            rows = []
            for r in table.targets or []:
                if r.status == "ok" and kind == "targets" and r.index < len(items):
                    q = list(items[r.index].robax[: len(r.q_deg)])
                    rows.append(r.model_copy(update={"q_deg": q}))
                else:
                    rows.append(r if r.status != "ok" else r.model_copy(update={"q_deg": []}))
            update = {"targets": rows}
        elif table.kind == "joint":
            update = {"joints": _decode_joint(items) if kind == "joint" else []}
        else:
            raise errors.CompensationError(f"{self.kind} stores 'targets' and 'joint' tables, "
                                           f"not {table.kind!r}")
        back = table.model_copy(update=update)
        return back.model_copy(update={"checksum": back.compute_checksum()})

    async def snapshot_compensation(self, table: CompensationTable) -> ControllerSnapshot:
        """The four RobocalServer compensation variables verbatim (RAPID literal text)."""
        self._ensure_connected()
        if table.kind not in self.supported_compensation:
            raise errors.CompensationError(f"{self.kind} stores 'targets' and 'joint' tables, "
                                           f"not {table.kind!r}")
        items = {name: await self._read_var(name)
                 for name in (_COMP, _COMP_N, _COMP_KIND, _COMP_SUM)}
        return ControllerSnapshot(driver=self.kind, covers=table.kind, items=items)

    async def restore_snapshot(self, snapshot: ControllerSnapshot) -> None:
        """Write the saved RobocalServer variables back, read them again and compare
        (VerificationMismatch when the controller then holds other values)."""
        self._ensure_connected()
        for name, value in snapshot.items.items():
            if name not in (_COMP, _COMP_N, _COMP_KIND, _COMP_SUM):
                raise errors.CompensationError(f"snapshot slot {name!r} is not a {self.kind} slot")
            await self._write_var(name, str(value))
        self._last_table = None
        back = {name: await self._read_var(name) for name in snapshot.items}
        diff = snapshot_diff(snapshot, ControllerSnapshot(driver=self.kind,
                                                          covers=snapshot.covers, items=back))
        self._check_read_back(diff, "restored values read back differ")


def _decode_joint(items: Sequence[rws.JointTarget]) -> list[JointCorrection]:
    """Joint-correction entries from ``rc_comp`` elements ``[joint, source, q, dq, bound, 0]``
    (a new entry where joint or source changes or q stops increasing)."""
    groups: list[list[rws.JointTarget]] = []
    for t in items:
        prev = groups[-1][-1] if groups else None
        if prev is None or prev.robax[:2] != t.robax[:2] or t.robax[2] <= prev.robax[2]:
            groups.append([t])
        else:
            groups[-1].append(t)
    out = []
    for g in groups:
        joint, src = int(g[0].robax[0]), int(g[0].robax[1])
        try:
            out.append(JointCorrection(
                joint=joint, source_joint=src or None, q_deg=[t.robax[2] for t in g],
                dq_deg=[t.robax[3] for t in g], interpolation_error_bound_deg=g[0].robax[4]))
        except ValueError as err:
            raise errors.UnexpectedReply(f"rc_comp holds no valid joint table: {err}") from err
    return out
