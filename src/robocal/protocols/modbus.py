"""Modbus-TCP register map and value codecs (sans-I/O).

The map and handshake robocal speaks are described in ``docs/protocols/modbus-plc.md``.

Nothing here does I/O or imports pymodbus (ADR 0038): the pymodbus client is
:mod:`robocal.drivers._modbus_client`, the pymodbus server of the simulated PLC is
:mod:`robocal.drivers.sim._modbus_server`.

Default register map (0-based wire addresses; FLOAT32 = 2 words, word order configurable)::

    HR  0 CMD              UINT16   0 idle 1 MOVE_JOINT 2 READ_ACTUAL 3 WRITE_JOINT_OFFSETS
                                    4 WRITE_FRAME 5 APPLY_TABLE* 8 RESET 9 ABORT
    HR  1 CMD_SEQ          UINT16   written together with CMD in one FC16 request
    HR  2 TARGET_J1..J6    6xF32    degrees
    HR 14 SPEED_PCT        UINT16
    HR 16 OFFSET_J1..J6    6xF32    payload of CMD 3
    HR 28 FRAME_XYZWPR     6xF32    payload of CMD 4 (mm, deg)
    HR 40 CLIENT_HEARTBEAT UINT16   incremented by the client at 1 Hz
    HR 100.. TABLE*        block    compensation table (header + values + metadata)
    IR  0 STATUS           UINT16   0 idle 1 busy 2 done 3 error
    IR  1 ACK_SEQ          UINT16   = CMD_SEQ once that command finished
    IR  2 ERROR_CODE       UINT16   see :class:`PlcError`
    IR  3 ACTUAL_J1..J6    6xF32    degrees
    IR 15 ACTUAL_TS_MS     UINT32
    IR 17 PLC_HEARTBEAT    UINT16
    IR 18 MAP_VERSION      UINT16   1
    IR 19 TABLE_CRC*       UINT16   CRC-16/MODBUS the PLC computed over the applied table

``*`` marks robocal's extensions of the research map. A PLC that maps only holding registers
uses ``status_area="holding"`` with ``status_offset`` (e.g. 1000).

Table block layout (``TABLE`` base, words)::

    0 MAGIC 0x5243 ("RC")  1 LAYOUT 1  2 KIND (1 targets, 2 joint, 3 frames)  3 DOF  4 POINTS
    5 WORDS_PER_VALUE (2 float32 | 4 float64)  6-7 N_VALUES (UINT32)  8 CRC16 (values + meta)
    9 META_BYTES  10-13 first 8 bytes of the table's SHA-256 checksum  14-15 reserved (0)
    16..  N_VALUES values, then META_BYTES of ASCII JSON metadata padded to whole words
"""

from __future__ import annotations

import itertools
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from robocal.errors import FramingError

__all__ = [
    "MAX_READ",
    "MAX_WRITE",
    "TABLE_HEADER_WORDS",
    "TABLE_MAGIC",
    "Cmd",
    "PlcError",
    "RegisterMap",
    "Status",
    "TableBlock",
    "WordOrder",
    "crc16_modbus",
    "decode_f32",
    "decode_f64",
    "decode_table_block",
    "decode_u32",
    "encode_f32",
    "encode_f64",
    "encode_table_block",
    "encode_u32",
    "table_block_length",
]

WordOrder = Literal["big", "little"]
MAX_WRITE = 123  # FC16 limit, registers per request
MAX_READ = 125  # FC3/FC4 limit


class Cmd(IntEnum):
    """Values of the CMD register."""

    IDLE = 0
    MOVE_JOINT = 1
    READ_ACTUAL = 2
    WRITE_JOINT_OFFSETS = 3
    WRITE_FRAME = 4
    APPLY_TABLE = 5
    RESET = 8
    ABORT = 9


class Status(IntEnum):
    """Values of the STATUS register."""

    IDLE = 0
    BUSY = 1
    DONE = 2
    ERROR = 3


class PlcError(IntEnum):
    """ERROR_CODE values of the default PLC program (the simulator implements them)."""

    NONE = 0
    UNKNOWN_CMD = 1
    BAD_ARGUMENT = 2
    LIMIT = 10
    MOTION_FAULT = 11
    ABORTED = 12
    TABLE_CRC = 20
    TABLE_HEADER = 21
    HEARTBEAT_LOST = 30


class RegisterMap(BaseModel):
    """Addresses of every field (0-based wire addresses) and the FLOAT32 word order."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    word_order: WordOrder = "big"
    device_id: int = Field(default=1, ge=0, le=247)
    joints: int = Field(default=6, ge=1, le=6)
    cmd: int = Field(default=0, ge=0)
    cmd_seq: int = Field(default=1, ge=0)
    target: int = Field(default=2, ge=0)
    speed: int = Field(default=14, ge=0)
    offset: int = Field(default=16, ge=0)
    frame: int = Field(default=28, ge=0)
    client_heartbeat: int = Field(default=40, ge=0)
    table: int = Field(default=100, ge=0)
    table_words: int = Field(default=4000, ge=16, le=60000)
    status_area: Literal["input", "holding"] = "input"
    status_offset: int = Field(default=0, ge=0)
    status: int = Field(default=0, ge=0)
    ack_seq: int = Field(default=1, ge=0)
    error_code: int = Field(default=2, ge=0)
    actual: int = Field(default=3, ge=0)
    actual_ts: int = Field(default=15, ge=0)
    plc_heartbeat: int = Field(default=17, ge=0)
    map_version: int = Field(default=18, ge=0)
    table_crc: int = Field(default=19, ge=0)

    @model_validator(mode="after")
    def _check(self) -> RegisterMap:
        if abs(self.cmd - self.cmd_seq) != 1:
            raise ValueError("cmd and cmd_seq must be adjacent (written in one FC16 request)")
        hr = self.holding_fields()
        spans = sorted(hr.values())
        for (a0, a1), (b0, _) in itertools.pairwise(spans):
            if b0 < a1:
                raise ValueError(f"holding-register fields overlap at {b0} (span {a0}..{a1 - 1})")
        if self.status_area == "holding":
            s0, s1 = self.status_span()
            for name, (a0, a1) in hr.items():
                if a0 < s1 and s0 < a1:
                    raise ValueError(f"status block {s0}..{s1 - 1} overlaps HR field {name}")
        return self

    def holding_fields(self) -> dict[str, tuple[int, int]]:
        """Return ``name -> (first, end)`` of every client-written holding-register field."""
        n = 2 * self.joints
        return {
            "cmd": (self.cmd, self.cmd + 1),
            "cmd_seq": (self.cmd_seq, self.cmd_seq + 1),
            "target": (self.target, self.target + n),
            "speed": (self.speed, self.speed + 1),
            "offset": (self.offset, self.offset + n),
            "frame": (self.frame, self.frame + 12),
            "client_heartbeat": (self.client_heartbeat, self.client_heartbeat + 1),
            "table": (self.table, self.table + self.table_words),
        }

    def status_fields(self) -> dict[str, tuple[int, int]]:
        """Return ``name -> (first, end)`` of the PLC-written fields, relative addresses."""
        return {
            "status": (self.status, self.status + 1),
            "ack_seq": (self.ack_seq, self.ack_seq + 1),
            "error_code": (self.error_code, self.error_code + 1),
            "actual": (self.actual, self.actual + 2 * self.joints),
            "actual_ts": (self.actual_ts, self.actual_ts + 2),
            "plc_heartbeat": (self.plc_heartbeat, self.plc_heartbeat + 1),
            "map_version": (self.map_version, self.map_version + 1),
            "table_crc": (self.table_crc, self.table_crc + 1),
        }

    def status_span(self) -> tuple[int, int]:
        """Return the wire address range ``[first, end)`` covering all PLC-written fields."""
        spans = self.status_fields().values()
        first = min(a for a, _ in spans)
        end = max(b for _, b in spans)
        return first + self.status_offset, end + self.status_offset

    def holding_size(self) -> int:
        """Return how many holding registers a server must provide (from address 0)."""
        end = max(b for _, b in self.holding_fields().values())
        if self.status_area == "holding":
            end = max(end, self.status_span()[1])
        return end

    def input_size(self) -> int:
        """Return how many input registers a server must provide (from address 0)."""
        return self.status_span()[1] if self.status_area == "input" else 1


# --- value codecs ------------------------------------------------------------------------------
def _words(data: bytes, width: int, word_order: WordOrder) -> list[int]:
    out: list[int] = []
    for i in range(0, len(data), width):
        chunk = [int.from_bytes(data[j : j + 2], "big") for j in range(i, i + width, 2)]
        if word_order == "little":
            chunk.reverse()
        out.extend(chunk)
    return out


def _bytes(words: Sequence[int], width: int, word_order: WordOrder) -> bytes:
    n = width // 2
    if len(words) % n:
        raise FramingError(f"{len(words)} registers is not a multiple of {n}")
    out = bytearray()
    for i in range(0, len(words), n):
        chunk = list(words[i : i + n])
        if word_order == "little":
            chunk.reverse()
        for w in chunk:
            if not 0 <= w <= 0xFFFF:
                raise FramingError(f"register value {w} outside 0..65535")
            out += w.to_bytes(2, "big")
    return bytes(out)


def encode_f32(values: Sequence[float], word_order: WordOrder = "big") -> list[int]:
    """Encode floats as IEEE-754 FLOAT32, two registers each.

    Raises
    ------
    FramingError
        If a value is not finite or overflows FLOAT32.
    """
    for v in values:
        if not math.isfinite(v):
            raise FramingError(f"cannot encode non-finite value {v!r}")
    try:
        data = struct.pack(f">{len(values)}f", *values)
    except (OverflowError, struct.error) as err:
        raise FramingError(f"value does not fit FLOAT32: {err}") from err
    return _words(data, 4, word_order)


def decode_f32(words: Sequence[int], word_order: WordOrder = "big") -> list[float]:
    """Decode registers (two per value) as FLOAT32."""
    data = _bytes(words, 4, word_order)
    return list(struct.unpack(f">{len(data) // 4}f", data))


def encode_f64(values: Sequence[float], word_order: WordOrder = "big") -> list[int]:
    """Encode floats as IEEE-754 FLOAT64, four registers each."""
    for v in values:
        if not math.isfinite(v):
            raise FramingError(f"cannot encode non-finite value {v!r}")
    return _words(struct.pack(f">{len(values)}d", *values), 8, word_order)


def decode_f64(words: Sequence[int], word_order: WordOrder = "big") -> list[float]:
    """Decode registers (four per value) as FLOAT64."""
    data = _bytes(words, 8, word_order)
    return list(struct.unpack(f">{len(data) // 8}d", data))


def encode_u32(value: int, word_order: WordOrder = "big") -> list[int]:
    """Encode an unsigned 32-bit integer as two registers."""
    if not 0 <= value <= 0xFFFFFFFF:
        raise FramingError(f"{value} does not fit UINT32")
    return _words(value.to_bytes(4, "big"), 4, word_order)


def decode_u32(words: Sequence[int], word_order: WordOrder = "big") -> int:
    """Decode two registers as an unsigned 32-bit integer."""
    if len(words) != 2:
        raise FramingError("UINT32 needs exactly two registers")
    return int.from_bytes(_bytes(words, 4, word_order), "big")


def crc16_modbus(words: Sequence[int]) -> int:
    """Return the CRC-16/MODBUS of the registers, each taken as two big-endian bytes."""
    crc = 0xFFFF
    for w in words:
        for byte in ((w >> 8) & 0xFF, w & 0xFF):
            crc ^= byte
            for _ in range(8):
                crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


# --- compensation table block ------------------------------------------------------------------
TABLE_MAGIC = 0x5243
TABLE_LAYOUT = 1
TABLE_HEADER_WORDS = 16


@dataclass(frozen=True)
class TableBlock:
    """A compensation table as the PLC sees it: numbers, plus opaque metadata bytes.

    ``values`` are in the table's units (mm, degrees); ``digest`` is 8 bytes of the
    table's SHA-256 checksum; ``meta`` is ASCII JSON that the PLC stores but ignores.
    """

    kind: int
    dof: int
    points: int
    values: tuple[float, ...]
    meta: bytes = b""
    digest: bytes = b"\x00" * 8
    dtype: Literal["float32", "float64"] = "float64"


def encode_table_block(block: TableBlock, word_order: WordOrder = "big") -> list[int]:
    """Return the registers of a table block (header, values, metadata).

    Raises
    ------
    FramingError
        If a field does not fit its register or the metadata is not ASCII.
    """
    if len(block.digest) != 8:
        raise FramingError("table digest must be 8 bytes")
    try:
        block.meta.decode("ascii")
    except UnicodeDecodeError as err:
        raise FramingError("table metadata must be ASCII") from err
    for name, v in (("kind", block.kind), ("dof", block.dof), ("points", block.points)):
        if not 0 <= v <= 0xFFFF:
            raise FramingError(f"table {name} {v} does not fit a register")
    if len(block.meta) > 0xFFFF:
        raise FramingError("table metadata longer than 65535 bytes")
    enc = encode_f32 if block.dtype == "float32" else encode_f64
    body = enc(block.values, word_order)
    meta = block.meta + (b"\x00" if len(block.meta) % 2 else b"")
    body += [int.from_bytes(meta[i : i + 2], "big") for i in range(0, len(meta), 2)]
    header = [
        TABLE_MAGIC,
        TABLE_LAYOUT,
        block.kind,
        block.dof,
        block.points,
        2 if block.dtype == "float32" else 4,
        *encode_u32(len(block.values), word_order),
        crc16_modbus(body),
        len(block.meta),
        *(int.from_bytes(block.digest[i : i + 2], "big") for i in range(0, 8, 2)),
        0,
        0,
    ]
    return header + body


def table_block_length(header: Sequence[int], word_order: WordOrder = "big") -> int:
    """Return the total register count of a block from its 16 header words.

    Raises
    ------
    FramingError
        If the header is not a table header.
    """
    if len(header) < TABLE_HEADER_WORDS:
        raise FramingError("table header truncated")
    if header[0] != TABLE_MAGIC or header[1] != TABLE_LAYOUT:
        raise FramingError(f"no table block here (magic {header[0]:#06x}, layout {header[1]})")
    wpv = header[5]
    if wpv not in (2, 4):
        raise FramingError(f"bad words-per-value {wpv}")
    n_values = decode_u32(header[6:8], word_order)
    return TABLE_HEADER_WORDS + n_values * wpv + (header[9] + 1) // 2


def decode_table_block(words: Sequence[int], word_order: WordOrder = "big") -> TableBlock:
    """Decode a table block (extra trailing registers are ignored).

    Raises
    ------
    FramingError
        If the header is invalid, the block is truncated or the CRC does not match.
    """
    total = table_block_length(words[:TABLE_HEADER_WORDS], word_order)
    if len(words) < total:
        raise FramingError(f"table block truncated: {len(words)} of {total} registers")
    body = list(words[TABLE_HEADER_WORDS:total])
    if crc16_modbus(body) != words[8]:
        raise FramingError("table block CRC mismatch")
    wpv = words[5]
    n_values = decode_u32(words[6:8], word_order)
    dec = decode_f32 if wpv == 2 else decode_f64
    values = dec(body[: n_values * wpv], word_order)
    meta = b"".join(w.to_bytes(2, "big") for w in body[n_values * wpv :])[: words[9]]
    digest = b"".join(w.to_bytes(2, "big") for w in words[10:14])
    return TableBlock(
        kind=words[2],
        dof=words[3],
        points=words[4],
        values=tuple(values),
        meta=meta,
        digest=digest,
        dtype="float32" if wpv == 2 else "float64",
    )
