"""LTP/1 codec: golden lines from docs/protocols/ltp1.md, round trips, garbage."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from robocal.errors import FramingError, ProtocolError
from robocal.protocols import ltp


def test_golden_session_lines():
    req = ltp.parse_request(b"3 MEAS id=P0007 n=20 stab_mm=0.010 stab_ms=500 timeout_ms=8000")
    assert req.tag == "3" and req.verb == "MEAS"
    assert dict(req.args) == {
        "id": "P0007",
        "n": "20",
        "stab_mm": "0.010",
        "stab_ms": "500",
        "timeout_ms": "8000",
    }
    ok = ltp.parse_message(
        "3 OK id=P0007 x=1523.40712 y=-210.11930 z=887.00241 sx=0.0021 sy=0.0018 sz=0.0025 "
        "n=20 rms=0.0037 t=2026-01-05T10:11:13.101Z tk=88123456789 temp=20.41 press=1012.6 "
        "hum=41.0 smr=RRR15"
    )
    assert isinstance(ok, ltp.Ok)
    assert ok.values["x"] == "1523.40712" and ok.values["t"] == "2026-01-05T10:11:13.101Z"
    evt = ltp.parse_message(b"* EVT BEAM state=BROKEN t=2026-01-05T10:11:20.002Z")
    assert evt == ltp.Event("BEAM", {"state": "BROKEN", "t": "2026-01-05T10:11:20.002Z"})
    err = ltp.parse_message(b'4 ERR 10 BEAM_BROKEN msg="beam interrupted while settling"')
    assert err == ltp.Err("4", 10, "BEAM_BROKEN", "beam interrupted while settling")
    assert ltp.parse_message("1 OK proto=LTP/1 vendor=sim").values["proto"] == "LTP/1"


def test_format_matches_spec_examples():
    assert (
        ltp.format_request(ltp.Request("1", "HELLO", {"proto": "LTP/1"})) == "1 HELLO proto=LTP/1"
    )
    assert ltp.format_request(ltp.Request("7", "STATUS?")) == "7 STATUS?"
    assert (
        ltp.format_err("4", 10, msg="beam interrupted while settling")
        == '4 ERR 10 BEAM_BROKEN msg="beam interrupted while settling"'
    )
    assert ltp.format_event("BEAM", {"state": "LOCKED"}) == "* EVT BEAM state=LOCKED"
    assert ltp.format_err("9", 12345) == "9 ERR 12345 INTERNAL"


def test_error_code_table():
    assert ltp.ErrorCode.BEAM_BROKEN == 10 and ltp.ErrorCode.UNSTABLE == 12
    assert ltp.ErrorCode.TIMEOUT == 15 and ltp.ErrorCode.BUSY == 14
    assert {c.value for c in ltp.ErrorCode} == {
        1,
        2,
        3,
        10,
        11,
        12,
        13,
        14,
        15,
        16,
        20,
        21,
        30,
        50,
        99,
    }


def test_backslash_in_a_quoted_message_is_an_ordinary_character():
    """A Windows path in msg (item 8): no escapes inside quotes, the value ends at the quote."""
    err = ltp.parse_message(b'4 ERR 50 DEVICE_FAULT msg="cannot open C:\\data\\trk.cfg"')
    assert err == ltp.Err("4", 50, "DEVICE_FAULT", "cannot open C:\\data\\trk.cfg")
    tail = ltp.parse_message(b'5 ERR 50 DEVICE_FAULT msg="ends in \\"')
    assert isinstance(tail, ltp.Err) and tail.msg == "ends in \\"
    ok = ltp.parse_message(b'6 OK path="C:\\x y\\" n=3')
    assert dict(ok.values) == {"path": "C:\\x y\\", "n": "3"}
    line = ltp.format_err("7", 50, msg="C:\\temp\\a b")
    assert line == '7 ERR 50 DEVICE_FAULT msg="C:\\temp\\a b"'
    assert ltp.parse_message(line) == ltp.Err("7", 50, "DEVICE_FAULT", "C:\\temp\\a b")


def test_err_msg_is_always_quoted_and_made_carriable():
    assert ltp.format_err("1", 3, msg="FLY") == '1 ERR 3 BAD_ARG msg="FLY"'
    assert ltp.format_err("1", 3, msg='say "hi"') == "1 ERR 3 BAD_ARG msg=\"say 'hi'\""
    long = ltp.format_err("1", 99, msg="x" * 1000)
    assert len(long) == ltp.MAX_LINE and long.endswith('x"')


def test_a_malformed_msg_does_not_lose_the_error():
    """Lenient on the client's side: code and name survive an embedded quote."""
    err = ltp.parse_message(b'3 ERR 50 DEVICE_FAULT msg="file "a b" missing"')
    assert err == ltp.Err("3", 50, "DEVICE_FAULT", 'file "a b" missing')
    assert ltp.parse_message(b"3 ERR 50 DEVICE_FAULT msg=FLY") == ltp.Err(
        "3", 50, "DEVICE_FAULT", "FLY"
    )


def test_requests_are_strict_about_spacing_and_quotes():
    for line in (b"1  HELLO", b" 1 HELLO", b"1 HELLO ", b"1 HELLO proto=LTP/1  ", b'1 MEAS id=a"b'):
        with pytest.raises(FramingError):
            ltp.parse_request(line)
    assert ltp.parse_message(b"1  OK  a=1 ") == ltp.Ok("1", {"a": "1"})
    assert ltp.parse_request(b'1 FRAME name="x"').args["name"] == "x"


def test_format_refuses_a_double_quote_in_a_value():
    with pytest.raises(FramingError):
        ltp.format_ok("1", {"k": 'a"b'})


@pytest.mark.parametrize(
    ("line", "tag"),
    [
        (b"12 MEAS n=x", "12"),
        (b"abc", "abc"),
        (b"A1 " + b"x" * 40, "A1"),
        (b"123456789 X", None),
        (b"! HELLO", None),
        (b"", None),
        (b"ab\xffc HELLO", None),
    ],
)
def test_readable_tag(line, tag):
    assert ltp.readable_tag(line) == tag


@pytest.mark.parametrize(
    "line",
    [
        b"",
        b"1",
        b"1 NOPE",
        b"123456789 OK",
        b"1 OK novalue",
        b"1 OK a=1 a=2",
        b"1 OK a=\xff",
        b"1 OK a=\x01",
        b'1 OK msg="unterminated',
        b'1 OK a="x"y',
        b'1 OK a=x"y',
        b"1 ERR x BEAM_BROKEN",
        b"1 ERR 10",
        b"1 ERR 10 beam",
        b"1 ERR 10 BEAM x=1",
        b"* EVT",
        b"* FOO BEAM",
        b"1 OK " + b"a" * 600,
        b"1 OK 1a=2",
    ],
)
def test_malformed_messages_raise_framing_error(line):
    with pytest.raises(FramingError):
        ltp.parse_message(line)


@pytest.mark.parametrize("line", [b"1", b"! HELLO", b"1 hello", b"1 MEAS n", b"\xff MEAS"])
def test_malformed_requests_raise_framing_error(line):
    with pytest.raises(FramingError):
        ltp.parse_request(line)


def test_format_refuses_what_cannot_be_parsed():
    with pytest.raises(FramingError):
        ltp.format_request(ltp.Request("bad tag", "HELLO"))
    with pytest.raises(FramingError):
        ltp.format_ok("1", {"k": "caf\u00e9"})
    with pytest.raises(FramingError):
        ltp.format_ok("1", {"x": "v" * 600})


@given(st.binary(max_size=300))
def test_arbitrary_bytes_never_raise_anything_but_protocol_errors(data):
    for parse in (ltp.parse_message, ltp.parse_request):
        with contextlib.suppress(ProtocolError):
            parse(data)


tags = st.text(
    "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789", min_size=1, max_size=8
)
keys = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,8}", fullmatch=True)
values = st.text(
    st.characters(min_codepoint=32, max_codepoint=126, blacklist_characters='"'), max_size=12
)
pairs = st.dictionaries(keys, values, max_size=5)


@given(tags, st.from_regex(r"[A-Z][A-Z0-9_]{0,6}\??", fullmatch=True), pairs)
def test_request_round_trip(tag, verb, args):
    req = ltp.Request(tag, verb, args)
    assert ltp.parse_request(ltp.format_request(req)) == req


@given(tags, pairs)
def test_ok_round_trip(tag, values_):
    assert ltp.parse_message(ltp.format_ok(tag, values_)) == ltp.Ok(tag, values_)


@given(tags, st.sampled_from(list(ltp.ErrorCode)), st.none() | values)
def test_err_round_trip(tag, code, msg):
    parsed = ltp.parse_message(ltp.format_err(tag, code, msg=msg))
    assert parsed == ltp.Err(tag, int(code), code.name, msg)


@given(st.from_regex(r"[A-Z][A-Z_]{0,6}", fullmatch=True), pairs)
def test_event_round_trip(name, values_):
    assert ltp.parse_message(ltp.format_event(name, values_)) == ltp.Event(name, values_)


def test_spaces_inside_quotes_are_not_separators():
    req = ltp.Request("0", "A", {"A": "  "})
    assert ltp.format_request(req) == '0 A A="  "'
    assert ltp.parse_request('0 A A="  "') == req
    with pytest.raises(FramingError, match="single spaces"):
        ltp.parse_request('0 A  A="  "')
