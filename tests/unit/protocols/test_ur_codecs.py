"""Universal Robots codecs: RTDE packages and values, primary-interface messages, URScript
subset, Dashboard replies."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.errors import FramingError, ProtocolError, UnexpectedReply
from robocal.protocols import ur_dashboard as dash
from robocal.protocols import ur_primary as prim
from robocal.protocols import ur_rtde as rtde

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
RTDE_TYPES = ["BOOL", "UINT8", "UINT32", "UINT64", "INT32", "DOUBLE", "VECTOR3D", "VECTOR6D",
              "VECTOR6INT32", "VECTOR6UINT32"]


def _value(t: str) -> st.SearchStrategy[object]:
    return {
        "BOOL": st.booleans(),
        "UINT8": st.integers(0, 255),
        "UINT32": st.integers(0, 2**32 - 1),
        "UINT64": st.integers(0, 2**64 - 1),
        "INT32": st.integers(-(2**31), 2**31 - 1),
        "DOUBLE": finite,
        "VECTOR3D": st.tuples(finite, finite, finite),
        "VECTOR6D": st.tuples(*[finite] * 6),
        "VECTOR6INT32": st.tuples(*[st.integers(-(2**31), 2**31 - 1)] * 6),
        "VECTOR6UINT32": st.tuples(*[st.integers(0, 2**32 - 1)] * 6),
    }[t]


@st.composite
def recipes(draw: st.DrawFn) -> tuple[list[str], list[object]]:
    types = draw(st.lists(st.sampled_from(RTDE_TYPES), min_size=1, max_size=12))
    return types, [draw(_value(t)) for t in types]


@given(recipes(), st.integers(1, 255))
def test_rtde_data_package_round_trip(recipe, recipe_id):
    types, values = recipe
    framer = rtde.RtdeFramer()
    framer.feed(rtde.data_package(recipe_id, types, values))
    (pkg,) = list(framer.packages())
    assert pkg.type == rtde.DATA_PACKAGE and pkg.payload[0] == recipe_id
    assert rtde.decode_values(types, pkg.payload[1:]) == list(values)


@given(st.lists(st.binary(max_size=40), max_size=6), st.data())
def test_rtde_framer_splits_any_chunking(payloads, data):
    stream = b"".join(rtde.encode(ord("U"), p) for p in payloads)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    framer = rtde.RtdeFramer()
    got = []
    last = 0
    for c in [*cuts, len(stream)]:
        framer.feed(stream[last:c])
        last = c
        got += [p.payload for p in framer.packages()]
    assert got == payloads


@given(st.binary(max_size=64))
@settings(max_examples=200)
def test_rtde_framer_never_crashes_on_garbage(blob):
    framer = rtde.RtdeFramer()
    framer.feed(blob)
    try:
        for pkg in framer.packages():
            assert 0 <= pkg.type < 256
    except FramingError:
        pass


def test_rtde_recipe_set_up_messages():
    req = rtde.setup_outputs(["timestamp", "actual_q"], 125.0)
    framer = rtde.RtdeFramer()
    framer.feed(req + rtde.setup_inputs(["input_int_register_18", ""]))
    o, i = list(framer.packages())
    assert rtde.parse_setup_outputs_request(o.payload) == (125.0, ["timestamp", "actual_q"])
    # A trailing comma (ur-rtde sends one) adds no variable.
    assert rtde.parse_names(i.payload) == ["input_int_register_18"]
    assert rtde.output_type("actual_q") == "VECTOR6D"
    assert rtde.output_type("no_such_thing") == "NOT_FOUND"
    assert rtde.input_type("standard_digital_output_mask") == "UINT8"
    reply = rtde.recipe_reply(rtde.SETUP_OUTPUTS, 1, ["DOUBLE", "VECTOR6D"])
    framer.feed(reply)
    (r,) = list(framer.packages())
    assert rtde.parse_recipe_reply(r.payload) == (1, ["DOUBLE", "VECTOR6D"])
    with pytest.raises(ProtocolError):
        rtde.decode_values(["DOUBLE"], b"\x00" * 7)
    with pytest.raises(FramingError):
        rtde.encode(ord("U"), b"\x00" * 70000)


def test_rtde_text_and_version():
    framer = rtde.RtdeFramer()
    framer.feed(rtde.text_message("hello", "RTDE", 1) + rtde.controller_version(5, 12, 2, 7))
    m, v = list(framer.packages())
    assert rtde.parse_text_message(m.payload) == ("hello", "RTDE", 1)
    assert rtde.parse_controller_version(v.payload) == (5, 12, 2, 7)


# --- primary interface -----------------------------------------------------------------------
angles = st.tuples(*[st.floats(-7.0, 7.0)] * 6)


@given(angles, angles, st.integers(-1, 8), st.booleans())
def test_robot_state_round_trip(q, dh, mode, running):
    kin = prim.KinematicsInfo(
        tuple(prim.dh_checksum(t, 0.1, 0.2, 0.3) for t in dh), dh, (0.0,) * 6, (0.1,) * 6,
        (math.pi / 2,) * 6, 1)
    state = prim.RobotState(
        prim.RobotModeData(12, True, True, True, False, False, running, False, mode, 0, 1.0,
                           0.5, 1.0),
        prim.JointData(q, q, (0.0,) * 6, (253,) * 6), kin)
    framer = prim.PrimaryFramer()
    framer.feed(prim.encode_robot_state(state))
    ((mtype, body),) = list(framer.messages())
    back = prim.decode_message(mtype, body)
    assert isinstance(back, prim.RobotState)
    assert back.kinematics == kin
    assert back.joints is not None and back.joints.q_actual == q
    assert back.mode is not None and back.mode.robot_mode == mode
    assert back.mode.program_running is running


def test_kinematics_fingerprint_changes_with_the_dh_table():
    a = prim.dh_checksum(0.0, -0.612, 0.0, 0.0)
    b = prim.dh_checksum(0.0, -0.6121, 0.0, 0.0)
    assert a != b
    info = prim.KinematicsInfo((a,) * 6, (0.0,) * 6, (0.0,) * 6, (0.0,) * 6, (0.0,) * 6, 0)
    assert info.fingerprint().count("-") == 5


def test_version_and_runtime_exception_messages():
    framer = prim.PrimaryFramer()
    framer.feed(prim.encode_version(prim.VersionMessage("URControl", 5, 12, 2, 99, "date"))
                + prim.encode_runtime_exception(prim.RuntimeException(3, 0, "boom")))
    (m1, b1), (m2, b2) = list(framer.messages())
    assert prim.decode_message(m1, b1) == prim.VersionMessage("URControl", 5, 12, 2, 99, "date")
    assert prim.decode_message(m2, b2) == prim.RuntimeException(3, 0, "boom")


def test_unknown_sub_packages_are_skipped():
    unknown = struct.pack(">iB", 9, 77) + b"\x00" * 4
    body = unknown + prim.encode_robot_state(prim.RobotState(
        joints=prim.JointData((1.0,) * 6, (1.0,) * 6, (0.0,) * 6, (253,) * 6)))[5:]
    back = prim.decode_message(prim.ROBOT_STATE, body)
    assert isinstance(back, prim.RobotState) and back.joints is not None
    with pytest.raises(ProtocolError):
        prim.decode_message(prim.ROBOT_STATE, struct.pack(">iB", 99, 1))


@given(st.binary(max_size=80))
@settings(max_examples=200)
def test_primary_decoding_never_crashes_on_garbage(blob):
    framer = prim.PrimaryFramer()
    framer.feed(blob)
    try:
        for mtype, body in framer.messages():
            prim.decode_message(mtype, body)
    except ProtocolError:
        pass


@given(st.lists(st.floats(-10, 10), min_size=6, max_size=6), st.floats(0.01, 3.0))
def test_script_round_trip_of_movej(q, v):
    text = f"def rc_1():\n  movej({prim.script_literal(q)}, a=1.4, v={v!r})\nend\n"
    programs, rest = prim.split_programs(text)
    assert rest == "" and len(programs) == 1
    name, statements = prim.parse_script(programs[0])
    assert name == "rc_1"
    (s,) = statements
    assert s.name == "movej" and s.args[0] == [float(x) for x in q]
    assert s.kwargs == {"a": 1.4, "v": v}


def test_script_subset():
    programs, rest = prim.split_programs(
        "stopj(4.0)\ndef a():\n  global rc_wp_1 = [1, 2.5]\n"
        "  write_output_float_register(24, rc_wp_1[1])\nend\ndef b():\n  x = 1\n")
    assert programs[0] == "stopj(4.0)"
    assert rest.startswith("def b():")  # incomplete: waits for its end
    _, st1 = prim.parse_script(programs[1])
    assert st1[0] == prim.Statement("assign", "rc_wp_1", ([1.0, 2.5],))
    assert st1[1].args == (24, ("ref", "rc_wp_1[1]"))
    with pytest.raises(prim.ScriptError):
        prim.parse_script("movel(p[0.1, 0, 0, 0, 0, 0])")
    with pytest.raises(prim.ScriptError):
        prim.parse_script("if x:")
    with pytest.raises(ValueError):
        prim.script_literal('a "quoted" text')


# --- dashboard -------------------------------------------------------------------------------
def test_dashboard_commands_and_replies():
    assert dash.parse_command("power on\n") == dash.Command("power on", "")
    assert dash.parse_command("PolyscopeVersion") == dash.Command("polyscopeversion", "")
    assert dash.parse_command("load /programs/a b.urp") == dash.Command("load",
                                                                        "/programs/a b.urp")
    assert dash.parse_command("launch rockets") is None
    assert dash.parse_robot_mode("Robotmode: RUNNING") == "RUNNING"
    assert dash.parse_safety("Safetystatus: PROTECTIVE_STOP") == "PROTECTIVE_STOP"
    assert dash.parse_program_state("PLAYING calib.urp") == ("PLAYING", "calib.urp")
    assert dash.parse_true("true") and not dash.parse_true("false")
    with pytest.raises(UnexpectedReply):
        dash.parse_robot_mode("Safetystatus: NORMAL")
    with pytest.raises(UnexpectedReply):
        dash.parse_program_state("nonsense")
    with pytest.raises(ValueError):
        dash.encode("two\nlines")


@given(st.text(max_size=60))
def test_dashboard_parse_command_never_crashes(text):
    cmd = dash.parse_command(text)
    assert cmd is None or isinstance(cmd.word, str)


def test_programs_with_nested_blocks_end_at_their_own_end():
    # ur-rtde's control program: functions, threads, loops and branches inside the program,
    # each closed by an end of its own; elif/else continue a block
    text = ("def rtde_control():\n"
            "    global reg_offset_int = # int register offset\n0\n"
            "    thread move_thread():\n        while (True):\n            sync()\n"
            "        end\n    end\n"
            "    def process_cmd(cmd):\n        if cmd == 1:\n            x = 1\n"
            "        elif cmd == 2:  # a comment: end\n            x = 2\n        else:\n"
            "            x = 3\n        end\n    end\n"
            "    while keep_running:\n        sync()\n    end\nend\nstopj(2)\ndef b():\n"
            "    if x:\n")
    programs, rest = prim.split_programs(text)
    assert len(programs) == 2 and programs[1] == "stopj(2)"
    assert programs[0].startswith("def rtde_control():") and programs[0].endswith("    end\nend")
    assert programs[0] == text[:text.index("\nstopj")]
    assert rest == "def b():\n    if x:\n"      # incomplete: waits for both ends
