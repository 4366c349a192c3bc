"""The ABB Robot Web Services codec: requests of both dialects, answers, RAPID literals and
HTTP authentication (property tests for every parser)."""

from __future__ import annotations

import contextlib
import json
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from robocal.errors import FramingError, UnexpectedReply
from robocal.protocols import abb_rws as rws

finite32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
printable = st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=80)


# --- RAPID literals ------------------------------------------------------------------------------
@given(finite32)
def test_num_round_trips_as_single_precision(v):
    text = rws.format_num(v)
    assert len(text) <= 15
    assert rws.single_precision(rws.parse_num(text)) == rws.single_precision(v)


def test_num_text_is_rapid_like():
    assert rws.format_num(9e9) == "9E+09"
    assert rws.format_num(12.5) == "12.5"
    assert rws.format_num(-0.0) == "0"
    assert rws.format_num(0.1) == "0.1"  # shortest text of the single, not 0.100000001
    with pytest.raises(ValueError):
        rws.format_num(float("nan"))


@given(printable)
def test_string_round_trips(text):
    assert rws.parse_string(rws.format_string(text)) == text


def test_string_refusals():
    with pytest.raises(ValueError):
        rws.format_string("x" * 81)
    with pytest.raises(FramingError):
        rws.parse_string('"a"b"')
    with pytest.raises(FramingError):
        rws.parse_string("abc")


@given(st.lists(finite32, min_size=6, max_size=6), st.lists(finite32, min_size=6, max_size=6))
def test_jointtarget_round_trips(robax, extax):
    t = rws.parse_jointtarget(rws.format_jointtarget(robax, extax))
    for got, sent in ((t.robax, robax), (t.extax, extax)):
        assert [rws.single_precision(v) for v in got] == [rws.single_precision(v) for v in sent]


@given(st.lists(st.lists(finite32, min_size=6, max_size=6), max_size=20))
def test_jointtarget_array_round_trips(rows):
    items = [rws.JointTarget(tuple(r)) for r in rows]
    back = rws.parse_jointtarget_array(rws.format_jointtarget_array(items))
    assert len(back) == len(items)
    for a, b in zip(back, items, strict=True):
        assert [rws.single_precision(v) for v in a.robax] == [
            rws.single_precision(v) for v in b.robax]


def test_jointtarget_accepts_controller_spacing_and_refuses_short_records():
    t = rws.parse_jointtarget(" [ [1, 2.5,-3,4E+1, .5, 6.],[9E+09,9E9,9e9,9E+09,9E+09,9E+09] ] ")
    assert t.robax == (1.0, 2.5, -3.0, 40.0, 0.5, 6.0) and t.extax[0] == 9e9
    with pytest.raises(FramingError):
        rws.parse_jointtarget("[[1,2,3,4,5],[9E9,9E9,9E9,9E9,9E9,9E9]]")
    with pytest.raises(FramingError):
        rws.parse_jointtarget_array("[[[1,2,3,4,5,6],[0,0,0,0,0,0]][[1,2,3,4,5,6],[0,0,0,0,0,0]]]")


@given(st.text(max_size=300))
def test_literal_parsers_raise_only_framing_errors(text):
    for parse in (rws.parse_num, rws.parse_string, rws.parse_jointtarget,
                  rws.parse_jointtarget_array):
        with contextlib.suppress(FramingError):
            parse(text)


# --- requests ------------------------------------------------------------------------------------
def test_requests_of_both_dialects():
    r = rws.write_symbol("rws1", "T_ROB1", "RobocalServer", "rc_seq", "3")
    assert r.method == "POST"
    assert r.path == "/rw/rapid/symbol/data/RAPID/T_ROB1/RobocalServer/rc_seq"
    assert r.target.endswith("?action=set&json=1") and r.form == (("value", "3"),)
    r = rws.write_symbol("rws2", "T_ROB1", "RobocalServer", "rc_seq", "3")
    assert r.path == "/rw/rapid/symbol/RAPID/T_ROB1/RobocalServer/rc_seq/data" and not r.query
    assert ("Content-Type", rws.FORM_RWS2) in r.headers and ("Accept", rws.JSON_RWS2) in r.headers
    assert rws.start_execution("rws1").target.startswith("/rw/rapid/execution?action=start")
    assert rws.start_execution("rws2").path == "/rw/rapid/execution/start"
    assert rws.stop_execution("rws2").form[0] == ("stopmode", "stop")
    assert rws.motors_on("rws1").target == "/rw/panel/ctrlstate?action=setctrlstate&json=1"
    assert rws.motors_on("rws2").path == "/rw/panel/ctrl-state"
    assert rws.mastership("rws2", "request").path == "/rw/mastership/edit/request"
    assert "coordinate=Base" in rws.robtarget("rws1").target
    with pytest.raises(ValueError):
        rws.read_symbol("rws1", "T_ROB1", "RobocalServer", "../x")


# --- answers -------------------------------------------------------------------------------------
def test_states_of_rws1_json_rws2_hal_and_xhtml():
    item = {"_type": "rap-data", "_title": "RAPID/T_ROB1/M/x", "value": "[1,2]"}
    rw6 = json.dumps({"_links": {}, "_embedded": {"_state": [item]}}).encode()
    rw7 = json.dumps({"_links": {}, "state": [item]}).encode()
    xhtml = (b'<html xmlns="http://www.w3.org/1999/xhtml"><body><div class="state"><ul>'
             b'<li class="rap-data" title="RAPID/T_ROB1/M/x"><span class="value">[1,2]</span>'
             b"</li></ul></div></body></html>")
    for body, ctype in ((rw6, rws.JSON_RWS1), (rw7, rws.JSON_RWS2), (xhtml, rws.XHTML)):
        items = rws.parse_states(body, ctype)
        assert items[0]["_type"] == "rap-data" and rws.single(items, "value") == "[1,2]"
    with pytest.raises(UnexpectedReply):
        rws.single([], "value")
    with pytest.raises(FramingError):
        rws.parse_states(b'{"other": 1}', rws.JSON_RWS1)


@given(st.binary(max_size=400), st.sampled_from([rws.JSON_RWS1, rws.JSON_RWS2, rws.XHTML]))
def test_answer_parser_raises_only_framing_errors(body, ctype):
    with contextlib.suppress(FramingError):
        rws.parse_states(body, ctype)
    rws.parse_error(400, body, ctype)  # best effort, never raises


def test_error_answers():
    e = rws.parse_error(400, b'{"_embedded":{"status":{"code":-1073445860,"msg":"no"}}}',
                        rws.JSON_RWS1)
    assert (e.status, e.code, e.message) == (400, -1073445860, "no")
    e = rws.parse_error(409, b'{"status":{"code":"-5","msg":"held"}}', rws.JSON_RWS2)
    assert (e.code, e.message) == (-5, "held")
    assert rws.parse_error(503, b"", "text/plain").message == "HTTP 503"


def test_jointtarget_and_robtarget_states():
    jt = {"_type": "ms-jointtarget", **{f"rax_{i}": str(i * 10) for i in range(1, 7)}}
    assert rws.parse_jointtarget_state([jt]) == (10.0, 20.0, 30.0, 40.0, 50.0, 60.0)
    with pytest.raises(UnexpectedReply):
        rws.parse_jointtarget_state([{**jt, "_type": "other"}])
    with pytest.raises(UnexpectedReply):
        rws.parse_jointtarget_state([{**jt, "rax_3": "nan"}])
    rt = {"_type": "ms-robtargets", "x": "1", "y": "2", "z": "3", "q1": "1", "q2": "0",
          "q3": "0", "q4": "0", "cf1": "0", "cf4": "-1", "cf6": "0", "cfx": "1"}
    r = rws.parse_robtarget_state([rt])
    assert r.trans == (1.0, 2.0, 3.0) and r.rot == (1.0, 0.0, 0.0, 0.0) and r.robconf[1] == -1


# --- authentication ------------------------------------------------------------------------------
def test_digest_response_matches_rfc2617_example():
    assert rws.digest_response(
        username="Mufasa", password="Circle Of Life", realm="testrealm@host.com",
        nonce="dcd98b7102dd2f0e8b11d0f600bfb0c093", method="GET", uri="/dir/index.html",
        qop="auth", nc="00000001", cnonce="0a4f113b") == "6629fae49393a05397450978507c4ef1"


@given(st.text(st.characters(min_codepoint=33, max_codepoint=126,
                             exclude_characters='"\\'), min_size=1, max_size=30),
       st.integers(1, 2**32 - 1))
def test_digest_authorization_verifies_on_the_server_side(user, nc):
    ch = rws.parse_challenge(rws.DigestChallenge(rws.REALM, "abc123", "auth", "op").header())
    header = rws.digest_authorization(ch, username=user, password="pw", method="POST",
                                      uri="/rw/rapid/execution?action=stop&json=1", nc=nc,
                                      cnonce="c0ffee")
    scheme, p = rws.parse_authorization(header)
    assert scheme == "digest" and p["username"] == user and p["opaque"] == "op"
    expected = rws.digest_response(username=user, password="pw", realm=p["realm"],
                                   nonce=p["nonce"], method="POST", uri=p["uri"], qop=p["qop"],
                                   nc=p["nc"], cnonce=p["cnonce"])
    assert p["response"] == expected and int(p["nc"], 16) == nc


def test_challenge_refusals_and_basic():
    with pytest.raises(FramingError):
        rws.parse_challenge('Basic realm="x"')
    with pytest.raises(FramingError):
        rws.parse_challenge('Digest realm="x", nonce="n", algorithm=SHA-256')
    with pytest.raises(FramingError):
        rws.parse_challenge('Digest realm="x", nonce="n", qop="auth-int"')
    assert rws.parse_challenge('Digest realm="x", nonce="n"').qop is None
    scheme, p = rws.parse_authorization(rws.basic_authorization("Admin", "robo:tics"))
    assert scheme == "basic" and rws.parse_basic(p["token"]) == ("Admin", "robo:tics")
    with pytest.raises(FramingError):
        rws.parse_basic("!!!")


@given(st.text(max_size=200))
def test_auth_parsers_raise_only_framing_errors(text):
    for parse in (rws.parse_challenge, rws.parse_authorization, rws.parse_basic):
        with contextlib.suppress(FramingError):
            parse(text)


def test_single_precision_is_ieee_single():
    v = 123.456789
    assert rws.single_precision(v) == struct.unpack("<f", struct.pack("<f", v))[0]


_cfg_name = st.from_regex(r"[A-Za-z][A-Za-z0-9_]{0,20}", fullmatch=True)


@given(st.dictionaries(_cfg_name, st.dictionaries(_cfg_name, st.text(max_size=40), max_size=6),
                       max_size=5),
       st.sampled_from(["rws1", "rws2"]))
def test_cfg_instances_round_trip_through_both_json_dialects(instances, dialect):
    items = [{"_type": "cfg-dt-instance-li", "_title": n, "rdonly": "false",
              "attrib": [{"_type": "cfg-ia-t-li", "_title": k, "value": v}
                         for k, v in attrs.items()]} for n, attrs in instances.items()]
    if dialect == "rws1":
        body, ctype = json.dumps({"_embedded": {"_state": items}}), rws.JSON_RWS1
    else:
        body, ctype = json.dumps({"state": items}), rws.JSON_RWS2
    assert rws.parse_cfg_instances(rws.parse_states(body.encode(), ctype)) == instances


_json = st.recursive(st.none() | st.booleans() | st.integers() | st.text(max_size=10),
                     lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c,
                                                                         max_size=4),
                     max_leaves=20)


@given(st.lists(st.dictionaries(st.sampled_from(["_type", "_title", "attrib", "value"]),
                                _json | st.just("cfg-dt-instance-li"), max_size=4),
                max_size=4))
def test_cfg_instances_refuse_malformed_items_with_unexpected_reply(items):
    with contextlib.suppress(UnexpectedReply):
        out = rws.parse_cfg_instances(items)
        assert all(isinstance(v, dict) for v in out.values())


def test_cfg_instances_request_paths():
    assert rws.cfg_instances("rws1", "MOC", "ROBOT", "ROB_1").target == \
        "/rw/cfg/MOC/ROBOT/instances/ROB_1?json=1"
    req = rws.cfg_instances("rws2", "MOC", "MOTOR_CALIB")
    assert req.target == "/rw/cfg/MOC/MOTOR_CALIB/instances"
    assert ("Accept", rws.JSON_RWS2) in req.headers
