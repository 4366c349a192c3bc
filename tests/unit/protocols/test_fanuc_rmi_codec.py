"""FANUC RMI codec: golden packets (docs/protocols/fanuc-rmi.md), first-key rule, garbage."""

from __future__ import annotations

import contextlib
import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from robocal.errors import FramingError, ProtocolError, UnexpectedReply
from robocal.protocols import fanuc_rmi as rmi


def test_golden_connect_reply():
    p = rmi.decode(
        b'{"Communication":"FRC_Connect","ErrorID":0,"PortNumber":16002,"MajorVersion":7,'
        b'"MinorVersion":0}'
    )
    assert (p.category, p.name, p.error_id) == ("Communication", "FRC_Connect", 0)
    assert p.get_int("PortNumber") == 16002 and p.get_int("MajorVersion") == 7


def test_golden_joint_motion_matches_manual_shape():
    packet = rmi.joint_motion_jrep(7, [10.0, -5.0, 3.0, 0.0, 90.0, 0.0], speed_pct=10)
    assert json.loads(rmi.encode(packet)) == {
        "Instruction": "FRC_JointMotionJRep",
        "SequenceID": 7,
        "JointAngle": {"J1": 10.0, "J2": -5.0, "J3": 3.0, "J4": 0.0, "J5": 90.0, "J6": 0.0},
        "SpeedType": "Percent",
        "Speed": 10,
        "TermType": "FINE",
        "TermValue": 0,
    }
    assert rmi.encode(packet).startswith(b'{"Instruction":"FRC_JointMotionJRep"')


def test_instruction_reply_and_abbreviated_sid():
    p = rmi.decode(b'{"Instruction":"FRC_JointMotionJRep","ErrorID":0,"SequenceID":7}')
    assert p.sequence_id == 7 and p.error_id == 0
    assert rmi.decode(b'{"Instruction":"FRC_WaitTime","SID":3}').sequence_id == 3


def test_read_joint_angles_reply():
    p = rmi.decode(
        b'{"Command":"FRC_ReadJointAngles","ErrorID":0,"TimeTag":123,'
        b'"JointAngle":{"J1":1.5,"J2":2,"J3":3,"J4":4,"J5":5,"J6":6,"J7":0,"J8":0,"J9":0}}'
    )
    assert rmi.joint_angles(p.body, 6) == [1.5, 2.0, 3.0, 4.0, 5.0, 6.0]
    with pytest.raises(UnexpectedReply):
        rmi.joint_angles({"JointAngle": {"J1": 1}}, 2)
    with pytest.raises(UnexpectedReply):
        rmi.joint_angles({"JointAngle": {"J1": "x"}}, 1)
    with pytest.raises(UnexpectedReply):
        rmi.joint_angles({}, 1)


def test_frames():
    f = rmi.frame_fields(1, 2, 3, 4, 5, 6)
    assert f == {"X": 1.0, "Y": 2.0, "Z": 3.0, "W": 4.0, "P": 5.0, "R": 6.0}
    assert rmi.parse_frame({"Frame": f}) == (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
    with pytest.raises(UnexpectedReply):
        rmi.parse_frame({"Frame": {**f, "Z": True}})


def test_position_configuration_wire_object():
    packet = {"Command": "FRC_WritePositionRegister", "RegisterNumber": 11,
              "Configuration": rmi.Configuration(utool_number=3).fields()}
    assert rmi.encode(packet) == (
        b'{"Command":"FRC_WritePositionRegister","RegisterNumber":11,"Configuration":'
        b'{"UToolNumber":3,"UFrameNumber":0,"Front":1,"Up":1,"Left":0,"Flip":0,'
        b'"Turn4":0,"Turn5":0,"Turn6":0}}'
    )
    assert rmi.Configuration(flip=1, turn6=-1).fields()["Flip"] == 1
    assert rmi.Configuration(flip=1, turn6=-1).fields()["Turn6"] == -1


@pytest.mark.parametrize(
    "line",
    [
        b"",
        b"not json",
        b"[1,2]",
        b'"FRC_Connect"',
        b'{"ErrorID":0,"Command":"FRC_GetStatus"}',  # first key rule
        b'{"Command":5}',
        b'{"Command":"FRC_A","Command":"FRC_B"}',
        b'{"Command":"FRC_A","X":NaN}',
        b'{"Command":"FRC_A"',
        b"\xff\xfe",
        b"{" * 5000,
    ],
)
def test_malformed_lines_raise_framing_error(line):
    with pytest.raises(FramingError):
        rmi.decode(line)


@pytest.mark.parametrize(
    "line",
    [b'{"Command":"FRC_A","ErrorID":"0"}', b'{"Instruction":"FRC_A","SequenceID":true}'],
)
def test_wrongly_typed_routing_fields_raise_unexpected_reply(line):
    with pytest.raises(UnexpectedReply):
        rmi.decode(line)


def test_encode_enforces_first_key_and_finiteness():
    with pytest.raises(FramingError):
        rmi.encode({"ErrorID": 0, "Command": "FRC_A"})
    with pytest.raises(FramingError):
        rmi.encode({"Command": "FRC_A", "X": float("nan")})
    with pytest.raises(FramingError):
        rmi.joint_motion_jrep(1, [float("inf")] * 6, speed_pct=10)


def test_error_table_and_numbering():
    assert rmi.rmit(29) == 2556957 and rmi.rmit(28) == 2556956
    assert rmi.describe_error(2556957).startswith("RMIT-029")
    assert rmi.describe_error(7015).startswith("MEMO-015")
    assert rmi.next_sequence_id(1) == 2 and rmi.next_sequence_id(2**31 - 1) == 1


def test_error_table_is_complete_and_unknown_codes_are_explicit():
    """Item 7: every RMIT-001..057 has a text; anything else says it is not in the table."""
    for n in range(1, 58):
        text = rmi.describe_error(2556928 + n)
        assert text.startswith(f"RMIT-{n:03d} ") and "not in" not in text, text
    assert rmi.describe_error(rmi.rmit(10)) == "RMIT-010 TP program is not paused"
    assert rmi.describe_error(rmi.rmit(43)) == "RMIT-043 robot in single step mode"
    unknown = rmi.describe_error(rmi.rmit(999))
    assert unknown.startswith("RMIT-999") and "not in robocal's RMIT table" in unknown
    assert rmi.describe_error(42) == (
        "unknown ErrorID 42 (not an RMIT alarm; see the controller's alarm history)"
    )


#: Replies as controllers write them (number forms seen in public RMI client logs).
RECORDED = [
    (
        b'{"Command":"FRC_ReadJointAngles","ErrorID":0,"TimeTag":10552,"JointAngle":'
        b'{"J1":-.0123,"J2": .0456,"J3":-90.,"J4":0,"J5":+45.5,"J6":180.000,"J7":0.000,'
        b'"J8":0.000,"J9":0.000}}',
        [-0.0123, 0.0456, -90.0, 0.0, 45.5, 180.0],
    ),
    (
        b'{"Command": "FRC_ReadJointAngles", "ErrorID": 0, "TimeTag": 7,  "JointAngles": '
        b'{"J1": 12.5, "J2": -.5, "J3": .75, "J4": -0.0, "J5": 1.e1, "J6": 003.25}}',
        [12.5, -0.5, 0.75, 0.0, 10.0, 3.25],
    ),
]


@pytest.mark.parametrize(("line", "q_deg"), RECORDED)
def test_recorded_style_packets_decode(line, q_deg):
    """Items 1 and 3: numbers without a leading zero, and the plural key of older firmware."""
    packet = rmi.decode(line)
    assert rmi.joint_angles(packet.body, 6) == pytest.approx(q_deg)


def test_number_normalising_leaves_strings_alone():
    text = '{"Command":"FRC_ReadError","ErrorID":0,"ErrorData":"SRVO-002 at -.5 \\"x\\" 1."}'
    assert rmi.normalise_numbers(text) == text
    assert rmi.decode(text.encode()).body["ErrorData"] == 'SRVO-002 at -.5 "x" 1.'
    with pytest.raises(FramingError):
        rmi.decode(b'{"Command":"X","A":1.2.3}')


@given(st.floats(allow_nan=False, allow_infinity=False))
def test_controller_number_forms_parse_to_the_same_value(x):
    for form in (repr(x), f"{x:.6f}", f"{x:e}", f"{x:.3f}".replace("0.", ".", 1)):
        line = f'{{"Command":"FRC_ReadTCPSpeed","ErrorID":0,"Speed":{form}}}'
        assert rmi.decode(line.encode()).body["Speed"] == pytest.approx(float(form), rel=1e-12)
    assert rmi.next_sequence_id(1) == 2 and rmi.next_sequence_id(2**31 - 1) == 1


@given(st.binary(max_size=200))
def test_arbitrary_bytes_raise_only_protocol_errors(data):
    with contextlib.suppress(ProtocolError):
        rmi.decode(data)


json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=10),
    lambda children: (
        st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=5), children, max_size=3)
    ),
    max_leaves=10,
)


@given(json_values)
def test_arbitrary_json_raises_only_protocol_errors(value):
    with contextlib.suppress(ProtocolError):
        rmi.decode(json.dumps(value).encode())


@given(
    st.sampled_from(rmi.CATEGORIES),
    st.text(st.characters(min_codepoint=32, max_codepoint=126), min_size=1, max_size=20),
    st.dictionaries(
        st.text("ABCDEFGHIJKLMNOPQRSTUVWXYZ", min_size=1, max_size=8),
        st.integers(-(2**31), 2**31)
        | st.text(max_size=8)
        | st.floats(allow_nan=False, allow_infinity=False),
        max_size=5,
    ),
)
def test_encode_decode_round_trip(category, name, fields):
    fields.pop(category, None)
    fields.pop("ErrorID", None)
    fields.pop("SequenceID", None)
    fields.pop("SID", None)
    packet = {category: name, **fields}
    decoded = rmi.decode(rmi.encode(packet))
    assert (decoded.category, decoded.name, dict(decoded.body)) == (category, name, packet)


def test_golden_linear_and_relative_instructions():
    pos = {"X": 400.0, "Y": 0.5, "Z": 300.0, "W": 180.0, "P": 0.0, "R": -90.0}
    config = rmi.Configuration(utool_number=1, uframe_number=0)
    packet = json.loads(rmi.encode(rmi.linear_motion(3, pos, config, speed_mm_s=200)))
    assert packet == {
        "Instruction": "FRC_LinearMotion", "SequenceID": 3,
        "Configuration": {"UToolNumber": 1, "UFrameNumber": 0, "Front": 1, "Up": 1, "Left": 0,
                          "Flip": 0, "Turn4": 0, "Turn5": 0, "Turn6": 0},
        "Position": pos, "SpeedType": "mmSec", "Speed": 200.0, "TermType": "FINE",
        "TermValue": 0,
    }
    rel = rmi.linear_motion(4, pos, config, speed_mm_s=50, relative=True)
    assert rel["Instruction"] == "FRC_LinearRelative"
    jrel = rmi.joint_motion_jrep(5, [1.0] * 6, speed_pct=20, relative=True)
    assert jrel["Instruction"] == "FRC_JointRelativeJRep" and jrel["JointAngle"]["J6"] == 1.0
    with pytest.raises(FramingError):
        rmi.linear_motion(6, pos, config, speed_mm_s=0.0)


def test_port_value_forms():
    assert rmi.port_value({"PortValue": "ON"}) is True
    assert rmi.port_value({"PortValue": "off"}) is False
    assert rmi.port_value({"PortValue": 1}) is True
    for bad in ({}, {"PortValue": "HIGH"}, {"PortValue": 2}, {"PortValue": None}):
        with pytest.raises(UnexpectedReply):
            rmi.port_value(bad)


@given(st.one_of(st.none(), st.booleans(), st.integers(), st.floats(allow_nan=False),
                 st.text(max_size=5)))
def test_port_value_accepts_only_on_off_or_bit(value):
    try:
        on = rmi.port_value({"PortValue": value})
    except UnexpectedReply:
        assert not (isinstance(value, str) and value.upper() in ("ON", "OFF")) and not (
            type(value) in (int, float) and value in (0, 1))
    else:
        assert on is (value.upper() == "ON" if isinstance(value, str) else bool(value))
