"""Modbus codecs: FLOAT32/FLOAT64 word order, CRC-16/MODBUS, register map, table blocks."""

from __future__ import annotations

import contextlib
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from robocal.errors import FramingError, ProtocolError
from robocal.protocols import modbus as mb


def test_float32_golden_words_and_word_order():
    assert mb.encode_f32([1.0]) == [0x3F80, 0x0000]
    assert mb.encode_f32([1.0], "little") == [0x0000, 0x3F80]
    assert mb.encode_f32([-2.5, 10.5]) == [0xC020, 0x0000, 0x4128, 0x0000]
    assert mb.decode_f32([0x0000, 0x3F80], "little") == [1.0]
    with pytest.raises(FramingError):
        mb.encode_f32([float("nan")])
    with pytest.raises(FramingError):
        mb.encode_f32([1e40])
    with pytest.raises(FramingError):
        mb.decode_f32([1, 2, 3])


def test_matches_pymodbus_conversion():
    from pymodbus.client import AsyncModbusTcpClient as C

    for order in ("big", "little"):
        assert mb.encode_f32([123.25], order) == C.convert_to_registers(
            123.25, C.DATATYPE.FLOAT32, word_order=order
        )
        assert mb.encode_f64([-1.125e-3], order) == C.convert_to_registers(
            -1.125e-3, C.DATATYPE.FLOAT64, word_order=order
        )
        assert mb.encode_u32(0x12345678, order) == C.convert_to_registers(
            0x12345678, C.DATATYPE.UINT32, word_order=order
        )


def test_crc16_modbus_known_vector():
    # Request 01 03 00 00 00 0A carries CRC 0xCDC5 (sent low byte first: C5 CD).
    assert mb.crc16_modbus([0x0103, 0x0000, 0x000A]) == 0xCDC5
    assert mb.crc16_modbus([]) == 0xFFFF


def test_default_register_map_is_protocols_md():
    m = mb.RegisterMap()
    assert (m.cmd, m.cmd_seq, m.target, m.speed, m.offset, m.frame, m.client_heartbeat) == (
        0,
        1,
        2,
        14,
        16,
        28,
        40,
    )
    f = m.status_fields()
    assert f["status"] == (0, 1) and f["ack_seq"] == (1, 2) and f["actual"] == (3, 15)
    assert (
        f["actual_ts"] == (15, 17)
        and f["plc_heartbeat"] == (17, 18)
        and f["map_version"] == (18, 19)
    )
    assert m.status_span() == (0, 20)
    assert m.holding_size() == 4100 and m.input_size() == 20


def test_register_map_validation():
    with pytest.raises(ValidationError):
        mb.RegisterMap(cmd=0, cmd_seq=5)
    with pytest.raises(ValidationError):
        mb.RegisterMap(speed=3)  # overlaps TARGET
    with pytest.raises(ValidationError):
        mb.RegisterMap(status_area="holding", status_offset=30)  # overlaps FRAME
    hr_only = mb.RegisterMap(status_area="holding", status_offset=5000)
    assert hr_only.status_span() == (5000, 5020) and hr_only.holding_size() == 5020
    with pytest.raises(ValidationError):
        mb.RegisterMap(bogus=1)


blocks = st.builds(
    mb.TableBlock,
    kind=st.integers(1, 3),
    dof=st.integers(0, 9),
    points=st.integers(0, 100),
    values=st.lists(st.floats(-1e6, 1e6, allow_nan=False), max_size=40).map(tuple),
    meta=st.binary(max_size=60).map(lambda b: bytes(x & 0x7F for x in b)),
    digest=st.binary(min_size=8, max_size=8),
    dtype=st.sampled_from(["float32", "float64"]),
)


@given(blocks, st.sampled_from(["big", "little"]))
def test_table_block_round_trip(block, order):
    words = mb.encode_table_block(block, order)
    assert all(0 <= w <= 0xFFFF for w in words)
    assert mb.table_block_length(words[:16], order) == len(words)
    back = mb.decode_table_block([*words, 7, 7, 7], order)  # trailing registers ignored
    if block.dtype == "float32":
        expect = tuple(
            struct.unpack(
                f">{len(block.values)}f", struct.pack(f">{len(block.values)}f", *block.values)
            )
        )
        assert back == mb.TableBlock(**{**block.__dict__, "values": expect})
    else:
        assert back == block


def test_table_block_detects_corruption_and_truncation():
    block = mb.TableBlock(kind=2, dof=1, points=2, values=(1.0, 2.0, 3.0, 4.0), meta=b'{"a":1}')
    words = mb.encode_table_block(block)
    bad = list(words)
    bad[20] ^= 0x0100
    with pytest.raises(FramingError, match="CRC"):
        mb.decode_table_block(bad)
    with pytest.raises(FramingError, match="truncated"):
        mb.decode_table_block(words[:-1])
    with pytest.raises(FramingError):
        mb.decode_table_block([0] * 16)
    with pytest.raises(FramingError):
        mb.encode_table_block(mb.TableBlock(kind=1, dof=1, points=1, values=(), meta="é".encode()))


@given(st.lists(st.integers(0, 0xFFFF), max_size=80), st.sampled_from(["big", "little"]))
def test_arbitrary_registers_decode_or_raise_protocol_error(words, order):
    with contextlib.suppress(ProtocolError):
        mb.decode_table_block(words, order)


@given(st.lists(st.integers(0, 0xFFFF), max_size=80))
def test_arbitrary_headers_with_magic_raise_only_protocol_errors(words):
    words = [mb.TABLE_MAGIC, 1, *words]
    with contextlib.suppress(ProtocolError):
        mb.decode_table_block(words)
