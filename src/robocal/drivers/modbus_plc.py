"""A robot behind a PLC (or a robot's own Modbus server) over Modbus-TCP.

The register map and handshake are those of docs/protocols/modbus-plc.md (see
:mod:`robocal.protocols.modbus`): payload registers first, then ``CMD`` and ``CMD_SEQ`` in one
FC16 write, then poll ``ACK_SEQ`` until it equals ``CMD_SEQ``; ``STATUS`` 2 is success and 3
means ``ERROR_CODE`` says why. :meth:`ModbusPlcRobot.stop` writes ``CMD 9`` (ABORT) with the
next ``CMD_SEQ`` without waiting for a running move, and waits for its ``ACK_SEQ``; the
aborted move is never acknowledged and raises MotionStopped. The client increments
``CLIENT_HEARTBEAT`` every ``heartbeat_period_s``; a ``PLC_HEARTBEAT`` that stops changing
for ``heartbeat_timeout_s`` faults the driver (every later call raises until it reconnects).
Both heartbeat times run on the driver's :class:`~robocal._core.clock.Clock`.

Compensation tables (``targets``, ``joint`` grids, ``frames``) are written as one register
block at ``register_map.table`` (header, values, ASCII metadata), applied with ``CMD 5``
(the PLC checks the CRC), then read back and compared word for word. Values are FLOAT64 by
default so a table reads back bit-identical; ``table_dtype="float32"`` suits PLCs without
LREAL (then compare by registers only).
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

from pydantic import Field, model_validator

from robocal import errors
from robocal._core.clock import SYSTEM_CLOCK, Clock
from robocal.compensation import CompensationTable
from robocal.drivers import api
from robocal.drivers._base import CompensatingRobotBase, DriverOptions, RobotOptions
from robocal.drivers._compensation import ControllerSnapshot, table_diff
from robocal.drivers._modbus_client import ModbusClient
from robocal.protocols import modbus as mb

__all__ = ["ModbusPlcOptions", "ModbusPlcRobot"]

_KIND_CODE = {"targets": 1, "joint": 2, "frames": 3}
_CODE_KIND = {v: k for k, v in _KIND_CODE.items()}


class ModbusPlcOptions(RobotOptions):
    """Options of :class:`ModbusPlcRobot`.

    Attributes
    ----------
    host, port
        Modbus-TCP server.
    register_map
        Addresses, FLOAT32 word order and device id (defaults: docs/protocols/modbus-plc.md).
    request_timeout_s
        Per Modbus request, seconds.
    poll_interval_s
        Pause between ``ACK_SEQ`` polls, seconds.
    heartbeat_period_s, heartbeat_timeout_s
        Client heartbeat period; how long ``PLC_HEARTBEAT`` may stay unchanged.
    map_version
        Expected ``MAP_VERSION`` (None: do not check).
    table_dtype
        Value type of compensation table blocks.
    """

    host: str = "127.0.0.1"
    port: int = Field(default=502, ge=1, le=65535)
    register_map: mb.RegisterMap = Field(default_factory=mb.RegisterMap)
    request_timeout_s: float = Field(default=2.0, gt=0.0)
    poll_interval_s: float = Field(default=0.005, gt=0.0)
    heartbeat_period_s: float = Field(default=1.0, gt=0.0)
    heartbeat_timeout_s: float = Field(default=5.0, gt=0.0)
    map_version: int | None = 1
    table_dtype: Literal["float32", "float64"] = "float64"

    @model_validator(mode="after")
    def _fits_map(self) -> ModbusPlcOptions:
        if len(self.joint_limits_deg) > self.register_map.joints:
            raise ValueError(
                f"{len(self.joint_limits_deg)} joints but the register map has "
                f"{self.register_map.joints} joint slots"
            )
        if self.heartbeat_timeout_s <= self.heartbeat_period_s:
            raise ValueError("heartbeat_timeout_s must exceed heartbeat_period_s")
        return self


@dataclass(frozen=True)
class PlcStatus:
    """Decoded PLC status block."""

    status: int
    ack_seq: int
    error_code: int
    actual_deg: tuple[float, ...]
    actual_ts_ms: int
    plc_heartbeat: int
    map_version: int
    table_crc: int


class ModbusPlcRobot(CompensatingRobotBase):
    """Robot commanded through a Modbus-TCP register handshake.

    Parameters
    ----------
    options : ModbusPlcOptions or mapping
        Validated options (``joint_limits_deg`` and ``port`` are usually needed).
    clock : Clock, optional
        Time source of the heartbeat period and timeout (default: the system clock).
    """

    kind: ClassVar[str] = "modbus_plc"
    Options: ClassVar[type[DriverOptions]] = ModbusPlcOptions
    options: ModbusPlcOptions
    supported_compensation: ClassVar[frozenset[str]] = frozenset({"targets", "joint", "frames"})

    def __init__(
        self,
        options: ModbusPlcOptions | Mapping[str, Any] | None = None,
        *,
        clock: Clock = SYSTEM_CLOCK,
    ) -> None:
        super().__init__(options)
        self.clock = clock
        self._client: ModbusClient | None = None
        self._op_lock = asyncio.Lock()
        self._seq = 0
        self._heartbeat_task: asyncio.Task[None] | None = None
        self._heartbeat_stop = asyncio.Event()
        self._client_hb = 0
        self._plc_hb: int | None = None
        self._plc_hb_time = 0.0
        self._fault: Exception | None = None
        self._stop_lock = asyncio.Lock()
        self._stop_gen = 0
        self._move_unacked = False  # a MOVE_JOINT went out and its ACK was not seen yet
        self.last_status: PlcStatus | None = None

    # --- connection ----------------------------------------------------------------------------
    async def _connect_impl(self, timeout: float) -> None:
        o, m = self.options, self.options.register_map
        self._fault = None
        client = ModbusClient(
            o.host, o.port, device_id=m.device_id, timeout=min(o.request_timeout_s, timeout)
        )
        self._client = client
        await client.connect(timeout=timeout)
        st = await self._read_status()
        if o.map_version is not None and st.map_version != o.map_version:
            raise errors.ConnectFailed(
                f"PLC reports MAP_VERSION {st.map_version}, expected {o.map_version}",
                kind=self.kind,
            )
        self._seq = st.ack_seq
        self._plc_hb, self._plc_hb_time = st.plc_heartbeat, self.clock.monotonic()
        self._heartbeat_stop = asyncio.Event()
        self._heartbeat_task = asyncio.create_task(self._heartbeat(), name="modbus-heartbeat")

    async def _close_impl(self) -> None:
        if self._move_unacked and self._client is not None:
            # Like RMI's FRC_Abort on disconnect: never leave a PLC robot moving on its own.
            try:
                async with asyncio.timeout(self.options.request_timeout_s * 2):
                    await self.stop()
            except Exception as err:
                # Closing goes on (the link is going away), but a robot that may still be
                # moving must never be a silent outcome.
                self.log.error("motion stop on close failed; the robot may still be moving",
                               error=repr(err))
        await self._stop_heartbeat()
        if self._client is not None:
            await self._client.close()
            self._client = None

    def _live_client(self) -> ModbusClient:
        self._ensure_connected()
        if self._fault is not None:
            raise self._fault
        assert self._client is not None
        return self._client

    # --- heartbeats ----------------------------------------------------------------------------
    async def _stop_heartbeat(self) -> None:
        """End the client heartbeat (bounded: at most one request timeout and a bit)."""
        task, self._heartbeat_task = self._heartbeat_task, None
        if task is None:
            return
        # The flag ends the loop even if a cancellation is lost on the way.
        self._heartbeat_stop.set()
        task.cancel()
        done, _ = await asyncio.wait({task}, timeout=self.options.request_timeout_s + 1.0)
        if not done:
            self.log.error("heartbeat task did not stop")
            return
        if not task.cancelled() and task.exception() is not None:
            self.log.warning("heartbeat task failed", error=repr(task.exception()))

    def _note_plc_heartbeat(self, hb: int) -> None:
        now = self.clock.monotonic()
        if hb != self._plc_hb:
            self._plc_hb, self._plc_hb_time = hb, now
        elif now - self._plc_hb_time > self.options.heartbeat_timeout_s and self._fault is None:
            self._fault = errors.OperationError(
                f"PLC heartbeat unchanged for {now - self._plc_hb_time:.1f} s; PLC program "
                "stopped or link frozen",
                kind=self.kind,
            )
            self.log.error("plc heartbeat stale", value=hb)

    async def _heartbeat(self) -> None:
        o, m = self.options, self.options.register_map
        stop = self._heartbeat_stop
        while not stop.is_set():
            try:
                client = self._client
                if client is None:
                    return
                self._client_hb = (self._client_hb + 1) & 0xFFFF
                await client.write_register(m.client_heartbeat, self._client_hb)
                if stop.is_set():
                    return
                st = await self._read_status()
                self._note_plc_heartbeat(st.plc_heartbeat)
            except (errors.TransportError, errors.ConnectFailed) as err:
                self._fault = errors.ConnectFailed(f"connection lost: {err}", kind=self.kind)
                self.log.error("modbus link lost", error=str(err))
                return
            except Exception as err:
                self.log.warning("heartbeat failed", error=repr(err))
            await self.clock.sleep(o.heartbeat_period_s)

    # --- handshake -----------------------------------------------------------------------------
    async def _read_status(self) -> PlcStatus:
        m = self.options.register_map
        client = self._client
        if client is None:
            raise errors.ConnectFailed("not connected", kind=self.kind)
        s0, s1 = m.status_span()
        with self.translate_errors():
            if m.status_area == "input":
                words = await client.read_input(s0, s1 - s0)
            else:
                words = await client.read_holding(s0, s1 - s0)

        def field(name: str) -> list[int]:
            a, b = m.status_fields()[name]
            i = a + m.status_offset - s0
            return words[i : i + b - a]

        wo = m.word_order
        st = PlcStatus(
            status=field("status")[0],
            ack_seq=field("ack_seq")[0],
            error_code=field("error_code")[0],
            actual_deg=tuple(mb.decode_f32(field("actual"), wo)),
            actual_ts_ms=mb.decode_u32(field("actual_ts"), wo),
            plc_heartbeat=field("plc_heartbeat")[0],
            map_version=field("map_version")[0],
            table_crc=field("table_crc")[0],
        )
        self.last_status = st
        return st

    def _next_seq(self) -> int:
        self._seq = 1 if self._seq >= 0xFFFF else self._seq + 1
        return self._seq

    async def _start(self, client: ModbusClient, cmd: mb.Cmd) -> int:
        """Write ``CMD`` and a fresh ``CMD_SEQ`` in one request; return the sequence number."""
        m = self.options.register_map
        seq = self._next_seq()
        pair = [int(cmd), seq] if m.cmd < m.cmd_seq else [seq, int(cmd)]
        await client.write_registers(min(m.cmd, m.cmd_seq), pair)
        return seq

    async def _await_ack(
        self,
        cmd: mb.Cmd,
        seq: int,
        deadline: float,
        timeout: float,
        watch: Callable[[PlcStatus], None] | None = None,
    ) -> PlcStatus:
        """Poll the status block until ``ACK_SEQ`` reaches ``seq``; ``watch`` sees every
        status read first and may raise."""
        while True:
            st = await self._read_status()
            if watch is not None:
                watch(st)
            if st.ack_seq == seq:
                return st
            if time.monotonic() > deadline:
                raise errors.DriverTimeout(
                    f"PLC did not acknowledge {cmd.name} (CMD_SEQ {seq}) within "
                    f"{timeout:.3g} s (STATUS {st.status}, ACK_SEQ {st.ack_seq})",
                    kind=self.kind,
                )
            await asyncio.sleep(self.options.poll_interval_s)

    async def _command(
        self, cmd: mb.Cmd, writes: Sequence[tuple[int, list[int]]], timeout: float
    ) -> PlcStatus:
        """Write payloads, start ``cmd``, poll ``ACK_SEQ``; return the final status block."""
        client = self._live_client()
        deadline = time.monotonic() + timeout
        gen = self._stop_gen
        async with self._op_lock:
            with self.translate_errors():
                for address, words in writes:
                    await client.write_registers(address, words)
                if gen != self._stop_gen and cmd == mb.Cmd.MOVE_JOINT:
                    raise errors.MotionStopped(
                        "stop requested before the move started", kind=self.kind)
                if cmd == mb.Cmd.MOVE_JOINT:
                    self._move_unacked = True
                seq = await self._start(client, cmd)

                def watch(st: PlcStatus) -> None:
                    self._note_plc_heartbeat(st.plc_heartbeat)
                    if self._fault is not None:
                        raise self._fault
                    if st.ack_seq != seq and gen != self._stop_gen:
                        # ABORT took over CMD_SEQ; stop() waits for its acknowledgement.
                        raise errors.MotionStopped(
                            f"{cmd.name} (CMD_SEQ {seq}) aborted by stop()", kind=self.kind
                        )

                st = await self._await_ack(cmd, seq, deadline, timeout, watch)
                if cmd == mb.Cmd.MOVE_JOINT:
                    self._move_unacked = False
        if st.status == mb.Status.ERROR:
            self._raise(cmd, st.error_code)
        if st.status != mb.Status.DONE:
            raise errors.OperationError(
                f"{cmd.name} acknowledged with STATUS {st.status}, expected 2 (done)",
                kind=self.kind,
            )
        return st

    def _raise(self, cmd: mb.Cmd, code: int) -> None:
        try:
            name = mb.PlcError(code).name
        except ValueError:
            name = f"code {code}"
        text = f"PLC refused {cmd.name}: ERROR_CODE {code} ({name})"
        if code == mb.PlcError.LIMIT:
            raise errors.LimitViolation(text, kind=self.kind)
        if code in (mb.PlcError.TABLE_CRC, mb.PlcError.TABLE_HEADER):
            raise errors.VerificationMismatch(text, kind=self.kind, diff=[name])
        if cmd == mb.Cmd.MOVE_JOINT:
            raise errors.MotionRejected(text, kind=self.kind, code=code)
        raise errors.OperationError(text, kind=self.kind)

    def _joints(self, st: PlcStatus) -> api.JointReading:
        q = st.actual_deg[: self.dof]
        return api.JointReading(tuple(math.radians(v) for v in q), time.time())

    # --- robot API -----------------------------------------------------------------------------
    async def move_to(
        self, q_rad: Sequence[float], *, speed_pct: float | None = None, timeout: float = 60.0
    ) -> api.JointReading:
        """Move to ``q_rad`` (radians) through the handshake; return the actual joints.

        Raises as :meth:`robocal.drivers.api.JointMover.move_to`; LimitViolation also when the
        PLC refuses the target, DriverTimeout when ``ACK_SEQ`` does not reach ``CMD_SEQ``.
        """
        q, speed = self._move_target(q_rad, speed_pct)
        m = self.options.register_map
        q_deg = [math.degrees(v) for v in q] + [0.0] * (m.joints - len(q))
        try:
            target = mb.encode_f32(q_deg, m.word_order)
        except errors.FramingError as err:
            raise errors.LimitViolation(str(err), kind=self.kind) from err
        speed_word = max(1, min(100, round(speed)))
        if m.speed == m.target + len(target):
            writes = [(m.target, [*target, speed_word])]
        else:
            writes = [(m.target, target), (m.speed, [speed_word])]
        st = await self._command(mb.Cmd.MOVE_JOINT, writes, timeout)
        return self._joints(st)

    async def read_joints(self) -> api.JointReading:
        """Ask the PLC to publish the actual joints (``READ_ACTUAL``); return them (radians)."""
        st = await self._command(mb.Cmd.READ_ACTUAL, [], self.options.request_timeout_s * 2)
        return self._joints(st)

    async def stop(self) -> None:
        """Write ``ABORT`` at once (not queued behind a running move) and wait for its ACK.

        A no-op when not connected. Sent even when the driver is faulted (stale heartbeat),
        because halting is always worth trying.

        Raises
        ------
        ConnectFailed
            The link is gone.
        DriverTimeout
            The PLC did not acknowledge ABORT within ``2 * request_timeout_s``.
        OperationError
            The PLC answered ABORT with an error.
        """
        client = self._client
        if self.state != "connected" or client is None:
            return
        timeout = self.options.request_timeout_s * 2
        async with self._stop_lock:
            self._stop_gen += 1
            deadline = time.monotonic() + timeout
            with self.translate_errors():
                seq = await self._start(client, mb.Cmd.ABORT)
                st = await self._await_ack(mb.Cmd.ABORT, seq, deadline, timeout)
                self._move_unacked = False
        if st.status == mb.Status.ERROR:
            self._raise(mb.Cmd.ABORT, st.error_code)
        self.log.info("stopped", cmd_seq=seq, actual_deg=[round(v, 4) for v in st.actual_deg])

    async def reset(self) -> None:
        """Send ``RESET`` (clears a latched PLC error)."""
        await self._command(mb.Cmd.RESET, [], self.options.request_timeout_s * 2)

    # --- compensation --------------------------------------------------------------------------
    def _block(self, table: CompensationTable) -> mb.TableBlock:
        sealed = table if table.checksum else table.sealed()
        meta = sealed.model_dump(mode="json")
        values: list[float] = []
        if sealed.kind == "joint":
            joints = sealed.joints or []
            points = {len(j.q_deg) for j in joints} | {len(j.dq_deg) for j in joints}
            if len(points) != 1:
                raise errors.CompensationError(
                    "joint tables need the same grid length for every joint")
            for j in joints:
                values += [*j.q_deg, *j.dq_deg]
            for jm in meta["joints"]:
                del jm["q_deg"], jm["dq_deg"]
            dof, n_points = len(joints), points.pop()
        elif sealed.kind == "targets":
            rows = sealed.targets or []
            dofs = {len(r.q_deg) for r in rows}
            if len(dofs) > 1:
                raise errors.CompensationError("target rows have different joint counts")
            for r in rows:
                if r.status == "ok":
                    api.check_joint_target(
                        [math.radians(v) for v in r.q_deg], self.joint_limits_rad, kind=self.kind
                    )
                values += r.q_deg
            for rm in meta["targets"]:
                del rm["q_deg"]
            dof, n_points = (dofs.pop() if dofs else self.dof), len(rows)
        else:
            if sealed.frames is None:
                raise errors.CompensationError("frames table without a frames payload")
            for f in (sealed.frames.base, sealed.frames.tool):
                values += [f.x, f.y, f.z, f.w, f.p, f.r]
            del meta["frames"]
            dof, n_points = 6, 2
        blob = json.dumps(meta, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
        return mb.TableBlock(
            kind=_KIND_CODE[sealed.kind],
            dof=dof,
            points=n_points,
            values=tuple(values),
            meta=blob.encode("ascii"),
            digest=bytes.fromhex(sealed.checksum[:16]),
            dtype=self.options.table_dtype,
        )

    @staticmethod
    def _table_from_block(block: mb.TableBlock) -> CompensationTable:
        try:
            meta = json.loads(block.meta.decode("ascii"))
            kind = _CODE_KIND[block.kind]
        except (ValueError, KeyError) as err:
            raise errors.FramingError(f"table block metadata unreadable: {err}") from err
        v = list(block.values)
        if kind == "joint":
            p = block.points
            for i, jm in enumerate(meta.get("joints") or []):
                jm["q_deg"] = v[2 * i * p : 2 * i * p + p]
                jm["dq_deg"] = v[2 * i * p + p : 2 * (i + 1) * p]
        elif kind == "targets":
            d = block.dof
            for i, rm in enumerate(meta.get("targets") or []):
                rm["q_deg"] = v[i * d : (i + 1) * d]
        else:
            keys = "xyzwpr"
            meta["frames"] = {
                "base": dict(zip(keys, v[0:6], strict=True)),
                "tool": dict(zip(keys, v[6:12], strict=True)),
            }
        try:
            table = CompensationTable.model_validate(meta)
        except ValueError as err:
            raise errors.FramingError(f"table block does not hold a valid table: {err}") from err
        if block.dtype == "float32":
            # Values were rounded to FLOAT32 on the way: reseal the table as stored.
            table = table.sealed()
        return table

    async def write_compensation(self, table: CompensationTable) -> None:
        """Write ``table`` as a register block, apply it, read it back and compare.

        Raises
        ------
        CompensationError
            The table does not fit the configured block or is malformed.
        LimitViolation
            A target row lies outside the joint limits (nothing written).
        VerificationMismatch
            The PLC's CRC check failed or the registers read back differ.
        """
        m = self.options.register_map
        sealed = table if table.checksum else table.sealed()
        try:
            words = mb.encode_table_block(self._block(sealed), m.word_order)
        except errors.FramingError as err:
            raise errors.CompensationError(f"table cannot be encoded: {err}") from err
        if len(words) > m.table_words:
            raise errors.CompensationError(
                f"table needs {len(words)} registers, the map reserves {m.table_words}"
            )
        st = await self._command(
            mb.Cmd.APPLY_TABLE, [(m.table, words)], self.options.request_timeout_s * 4
        )
        client = self._live_client()
        async with self._op_lock:
            with self.translate_errors():
                back = await client.read_holding(m.table, len(words))
        diff = [
            f"register {m.table + i}: wrote {a}, read {b}"
            for i, (a, b) in enumerate(zip(words, back, strict=True))
            if a != b
        ]
        if st.table_crc != words[8]:
            diff.append(f"PLC computed CRC {st.table_crc:#06x}, block has {words[8]:#06x}")
        if not diff and self.options.table_dtype == "float64":
            diff = table_diff(
                sealed, self._table_from_block(mb.decode_table_block(back, m.word_order))
            )
        self._check_read_back(diff, "compensation read back differs")

    async def read_compensation(self) -> CompensationTable | None:
        """Return the table stored in the PLC's table block, or None if the block is empty.

        Raises
        ------
        FramingError
            The block holds a corrupt table.
        """
        words = await self._table_words(strict=True)
        if words[0] != mb.TABLE_MAGIC:
            return None
        return self._table_from_block(
            mb.decode_table_block(words, self.options.register_map.word_order)
        )

    async def read_compensation_like(self, table: CompensationTable) -> CompensationTable | None:
        """The table in the PLC's block (the block carries the whole table)."""
        return await self.read_compensation()

    async def _table_words(self, *, strict: bool) -> list[int]:
        """The table block's registers: the whole block, or its header when there is none.

        ``strict``: a header that cannot be read or claims more registers than the map has
        raises FramingError (otherwise the header alone, or as many registers as fit).
        """
        client = self._live_client()
        m = self.options.register_map
        async with self._op_lock:
            with self.translate_errors():
                header = await client.read_holding(m.table, mb.TABLE_HEADER_WORDS)
                if header[0] != mb.TABLE_MAGIC:
                    return header
                try:
                    total = mb.table_block_length(header, m.word_order)
                except errors.FramingError:
                    if strict:
                        raise
                    return header
                if strict and total > m.table_words:
                    raise errors.FramingError(
                        f"table block claims {total} registers, the map has {m.table_words}"
                    )
                total = min(max(total, mb.TABLE_HEADER_WORDS), m.table_words)
                return await client.read_holding(m.table, total)

    async def snapshot_compensation(self, table: CompensationTable) -> ControllerSnapshot:
        """The PLC's table registers as they are, before robocal writes its block there."""
        words = await self._table_words(strict=False)
        m = self.options.register_map
        return ControllerSnapshot(driver=self.kind, covers=table.kind,
                                  items={f"hr:{m.table}": words})

    async def restore_snapshot(self, snapshot: ControllerSnapshot) -> None:
        """Write the saved registers back (applied again when they hold a table block).

        A PLC block without robocal's magic word is restored as raw registers: the PLC
        program then finds no table there, as before the first push.

        Raises
        ------
        VerificationMismatch
            The registers read back differ, or the PLC refuses the restored block.
        """
        m = self.options.register_map
        words = [int(w) for w in snapshot.items.get(f"hr:{m.table}", [])]
        if not words or len(words) > m.table_words:
            raise errors.CompensationError(f"snapshot holds no {self.kind} table registers")
        if words[0] == mb.TABLE_MAGIC:
            await self._command(
                mb.Cmd.APPLY_TABLE, [(m.table, words)], self.options.request_timeout_s * 4
            )
        else:
            client = self._live_client()
            async with self._op_lock:
                with self.translate_errors():
                    await client.write_registers(m.table, words)
        client = self._live_client()
        async with self._op_lock:
            with self.translate_errors():
                back = await client.read_holding(m.table, len(words))
        diff = [f"register {m.table + i}: wrote {a}, read {b}"
                for i, (a, b) in enumerate(zip(words, back, strict=True)) if a != b]
        self._check_read_back(diff, "restored registers differ")
