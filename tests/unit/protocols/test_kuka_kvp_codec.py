"""KUKAVARPROXY codec: golden bytes (docs/protocols/kuka-kvp.md), framing, KRL value text."""

from __future__ import annotations

import contextlib
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from robocal.errors import FramingError, UnexpectedReply
from robocal.protocols import kuka_kvp as kvp


def test_golden_read_and_write_requests():
    assert kvp.encode_request(kvp.Request(7, kvp.MODE_READ, "$OV_PRO")) == (
        b"\x00\x07" b"\x00\x0a" b"\x00" b"\x00\x07" b"$OV_PRO")
    assert kvp.encode_request(kvp.Request(0x1234, kvp.MODE_WRITE, "RC_SPEED", "30")) == (
        b"\x12\x34" b"\x00\x0f" b"\x01" b"\x00\x08" b"RC_SPEED" b"\x00\x02" b"30")


def test_golden_replies():
    ok = kvp.encode_reply(kvp.Reply(9, kvp.MODE_READ, "100", True))
    assert ok == b"\x00\x09" b"\x00\x09" b"\x00" b"\x00\x03" b"100" b"\x00\x01\x01"
    assert kvp.decode_reply(ok) == kvp.Reply(9, 0, "100", True)
    fail = kvp.encode_reply(kvp.Reply(9, kvp.MODE_WRITE, "", False))
    assert fail.endswith(b"\x00\x01\x00") and kvp.decode_reply(fail).ok is False


def test_request_matches_what_py_openshowvar_packs():
    """py-openshowvar's read layout: '!HHBH' + name, length = name + 3."""
    name = b"$AXIS_ACT"
    theirs = struct.pack("!HHBH9s", 42, len(name) + 3, 0, len(name), name)
    assert kvp.encode_request(kvp.Request(42, kvp.MODE_READ, "$AXIS_ACT")) == theirs
    assert kvp.decode_request(theirs) == kvp.Request(42, 0, "$AXIS_ACT", None)


@pytest.mark.parametrize("bad", [
    b"\x00\x01\x00\x05\x00\x00\x03AB",        # name overruns
    b"\x00\x01\x00\x04\x00\x00\x00X",         # length field disagrees
    b"\x00\x01\x00\x03\x02\x00\x00",          # mode 2, empty name
    b"\x00\x01\x00\x06\x00\x00\x01AX",        # trailing byte
    b"\x00\x01",                               # too short
])
def test_malformed_requests_raise_framing_error(bad):
    with pytest.raises(FramingError):
        kvp.decode_request(bad)


def test_encode_refuses_what_the_wire_cannot_carry():
    for req in (kvp.Request(70000, 0, "X"), kvp.Request(1, 0, ""), kvp.Request(1, 0, "Ä"),
                kvp.Request(1, 1, "X"), kvp.Request(1, 0, "X", "1"), kvp.Request(1, 5, "X")):
        with pytest.raises(FramingError):
            kvp.encode_request(req)


names = st.text(st.characters(min_codepoint=33, max_codepoint=126), min_size=1, max_size=60)
values = st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=300)


@given(st.integers(0, 0xFFFF), names, st.none() | values)
def test_request_round_trip(msg_id, name, value):
    req = kvp.Request(msg_id, kvp.MODE_READ if value is None else kvp.MODE_WRITE, name, value)
    assert kvp.decode_request(kvp.encode_request(req)) == req


@given(st.lists(st.tuples(st.integers(0, 0xFFFF), values, st.booleans()), max_size=6),
       st.integers(1, 7))
def test_framer_reassembles_any_split(replies, chunk):
    wire = b"".join(kvp.encode_reply(kvp.Reply(i, 0, v, ok)) for i, v, ok in replies)
    framer = kvp.KvpFramer()
    out = []
    for i in range(0, len(wire), chunk):
        framer.feed(wire[i:i + chunk])
        while (msg := framer.next_message()) is not None:
            out.append(kvp.decode_reply(msg))
    assert [(r.msg_id, r.value, r.ok) for r in out] == replies
    assert framer.buffered == 0


@given(st.binary(max_size=64))
def test_garbage_never_escapes_as_another_error(data):
    framer = kvp.KvpFramer()
    framer.feed(data)
    try:
        while (msg := framer.next_message()) is not None:
            for decode in (kvp.decode_request, kvp.decode_reply):
                with contextlib.suppress(FramingError):
                    decode(msg)
    except FramingError:
        pass


def test_framer_refuses_an_impossible_length():
    framer = kvp.KvpFramer()
    framer.feed(b"\x00\x01\x00\x02\x00\x00")
    with pytest.raises(FramingError):
        framer.next_message()


def test_krl_values():
    assert kvp.format_e6axis([10.0, -90.5]) == "{E6AXIS: A1 10.0, A2 -90.5}"
    assert kvp.format_e6axis({"E1": 1.0, "A3": 2.25}) == "{E6AXIS: A3 2.25, E1 1.0}"
    text = "{E6AXIS: A1 1.5,A2 -2.0, A3 3, A4 0.0, A5 .5, A6 6.0, E1 0.0, E2 0.0, E3 0.0, " \
           "E4 0.0, E5 0.0, E6 0.0}"
    assert kvp.parse_e6axis(text) == [1.5, -2.0, 3.0, 0.0, 0.5, 6.0]
    assert kvp.parse_struct("{X 1.0, S 2}") == (None, {"X": "1.0", "S": "2"})
    assert kvp.parse_int("'H1F'") == 31 and kvp.parse_int(" -4 ") == -4
    assert kvp.parse_bool("true") and not kvp.parse_bool("FALSE")
    assert kvp.parse_string('"KR6"') == "KR6" and kvp.format_string("KR6") == '"KR6"'
    assert kvp.format_real(-0.0) == "0.0" and kvp.format_real(1e-9) == "0.0"
    for bad, parse in (("{A1 1.0}", lambda t: kvp.parse_e6axis(t, components=2)),
                       ("{E6POS: X 1}", kvp.parse_e6axis), ("{A1 {A2 1}}", kvp.parse_struct),
                       ("{A1 1, A1 2}", kvp.parse_struct), ("1.5", kvp.parse_int),
                       ("nan", kvp.parse_real), ("YES", kvp.parse_bool),
                       ('"a"b"', kvp.parse_string)):
        with pytest.raises(UnexpectedReply):
            parse(bad)
    for bad_format in (lambda: kvp.format_real(float("inf")), lambda: kvp.format_int(2**31),
                       lambda: kvp.format_string('a"b'), lambda: kvp.format_e6axis({"A7": 1}),
                       lambda: kvp.format_e6axis([0.0] * 13)):
        with pytest.raises(FramingError):
            bad_format()


@given(st.lists(st.floats(-1e4, 1e4, allow_nan=False), min_size=1, max_size=12))
def test_e6axis_text_round_trip(values):
    back = kvp.parse_e6axis(kvp.format_e6axis(values), components=len(values))
    assert all(abs(a - b) <= 5e-7 for a, b in zip(back, values, strict=True))


@given(st.text(max_size=80))
def test_struct_parser_raises_only_unexpected_reply(text):
    try:
        kind, fields = kvp.parse_struct(text)
    except UnexpectedReply:
        return
    assert kind is None or (kind == kind.upper() and kind in text.upper())
    assert all(k == k.upper() and v for k, v in fields.items())
