"""emScon codec: golden bytes from the TPI's layout tables, round trips, and the framer.

The golden packets are built here field by field at the offsets of the Leica TPI structs
(4-byte packing, little-endian; see docs/protocols/emscon.md), independently of the codec's
own format strings.
"""

from __future__ import annotations

import itertools
import json
import math
import struct
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.errors import FramingError, UnexpectedReply
from robocal.protocols import emscon
from robocal.protocols.emscon import Cmd

# --- golden packets from the note's tables -----------------------------------------------------
# (command id, command size, [(offset, code, name)], reply size, [(offset, code, name)])
# code: i = int32, d = float64, S = u16[32] name. Offsets and sizes are the note's.
Fields = list[tuple[int, str, str]]
NOTE_COMMANDS: list[tuple[int, int, Fields, int, Fields]] = [
    (1, 12, [], 56, [(16, "i", "last_result_status"), (20, "i", "tracker_processor_status"),
                     (24, "i", "laser_status"), (28, "i", "adm_status"),
                     (32, "i", "version_major"), (36, "i", "version_minor"),
                     (40, "i", "version_build"), (44, "i", "weather_monitor_status"),
                     (48, "i", "flags_value"), (52, "i", "tracker_serial_number")]),
    (2, 12, [], 20, [(16, "i", "tracker_status")]),
    (5, 32, [(12, "i", "length_unit"), (16, "i", "angle_unit"), (20, "i", "temperature_unit"),
             (24, "i", "pressure_unit"), (28, "i", "humidity_unit")], 16, []),
    (6, 12, [], 36, [(16, "i", "length_unit"), (20, "i", "angle_unit"),
                     (24, "i", "temperature_unit"), (28, "i", "pressure_unit"),
                     (32, "i", "humidity_unit")]),
    (7, 12, [], 16, []),
    (20, 36, [(12, "d", "temperature"), (20, "d", "pressure"), (28, "d", "humidity")], 16, []),
    (21, 12, [], 40, [(16, "d", "temperature"), (24, "d", "pressure"), (32, "d", "humidity")]),
    (22, 28, [(12, "d", "ifm_refraction_index"), (20, "d", "adm_refraction_index")], 16, []),
    (23, 12, [], 32, [(16, "d", "ifm_refraction_index"), (24, "d", "adm_refraction_index")]),
    (24, 16, [(12, "i", "meas_mode")], 16, []),
    (25, 12, [], 20, [(16, "i", "meas_mode")]),
    (26, 16, [(12, "i", "coord_sys_type")], 16, []),
    (27, 12, [], 20, [(16, "i", "coord_sys_type")]),
    (28, 20, [(12, "i", "meas_time"), (16, "i", "use_adm")], 16, []),
    (29, 12, [], 24, [(16, "i", "meas_time"), (20, "i", "use_adm")]),
    (40, 16, [(12, "i", "internal_reflector_id")], 16, []),
    (41, 12, [], 20, [(16, "i", "internal_reflector_id")]),
    (42, 12, [], 100, [(16, "i", "total_reflectors"), (20, "i", "internal_reflector_id"),
                       (24, "i", "target_type"), (28, "d", "surface_offset"),
                       (36, "S", "reflector_name")]),
    (43, 24, [(12, "d", "search_radius"), (20, "i", "timeout")], 16, []),
    (44, 12, [], 28, [(16, "d", "search_radius"), (24, "i", "timeout")]),
    (47, 48, [(12 + 4 * k, "i", n) for k, n in enumerate(emscon.SPECS[47].params.names)], 16,
     []),
    (48, 12, [], 52, [(16 + 4 * k, "i", n) for k, n in enumerate(emscon.SPECS[48].reply.names)]),
    (49, 12, [], 16, []),
    (52, 12, [], 16, []),
    (54, 12, [], 16, []),
    (55, 40, [(12, "d", "val1"), (20, "d", "val2"), (28, "d", "val3"), (36, "i", "use_adm")],
     16, []),
    (56, 40, [(12, "d", "hz_angle"), (20, "d", "vt_angle"), (28, "d", "distance"),
              (36, "i", "use_adm")], 16, []),
    (57, 28, [(12, "d", "hz_val"), (20, "d", "vt_val")], 16, []),
    (63, 20, [(12, "d", "approx_distance")], 16, []),
    (66, 12, [], 32, [(16, "d", "hz_angle"), (24, "d", "vt_angle")]),
    (80, 20, [(12, "i", "stationary_mode"), (16, "i", "continuous_mode")], 16, []),
    (81, 12, [], 24, [(16, "i", "stationary_mode"), (20, "i", "continuous_mode")]),
    (95, 16, [(12, "i", "clockwise")], 16, []),
    (120, 20, [(12, "i", "system_param"), (16, "i", "parameter")], 16, []),
    (121, 16, [(12, "i", "system_param")], 24, [(16, "i", "system_param"),
                                                 (20, "i", "parameter")]),
    (122, 12, [], 24, [(16, "i", "last_result_status"), (20, "i", "measurement_status_info")]),
    (125, 24, [(12, "i", "system_param"), (16, "d", "parameter")], 16, []),
    (126, 16, [(12, "i", "system_param")], 28, [(16, "i", "system_param"),
                                                 (20, "d", "parameter")]),
    (130, 16, [(12, "i", "queue_type")], 16, []),
    (132, 12, [], 164, [(16, "i", "tracker_type"), (20, "S", "tracker_name"),
                        (84, "i", "tracker_serial_number"), (88, "i", "compensation_id"),
                        (92, "i", "has_adm"), (96, "i", "has_overview_camera"),
                        (100, "i", "has_nivel"), (104, "d", "nivel_mount_offset"),
                        (112, "d", "max_distance"), (120, "d", "min_distance"),
                        (128, "i", "max_data_rate"), (132, "i", "number_of_faces"),
                        (136, "d", "hz_angle_range"), (144, "d", "vt_angle_range"),
                        (152, "i", "accuracy_model"), (156, "i", "lcp_firmware_major"),
                        (160, "i", "lcp_firmware_minor")]),
    (142, 12, [], 80, [(16, "S", "version")]),
    # pointing commands the simulator answers for other clients; not in the note: sizes and
    # field order as in MuffinSpawn/Leica CESAPI/packet.py (PyPI CESAPI 1.1.3)
    (10, 12, [], 16, []),
    (53, 12, [], 16, []),
    (58, 36, [(12, "d", "val1"), (20, "d", "val2"), (28, "d", "val3")], 16, []),
    (59, 36, [(12, "d", "hz_angle"), (20, "d", "vt_angle"), (28, "d", "distance")], 16, []),
    (62, 12, [], 16, []),
    (98, 12, [], 20, [(16, "i", "tracker_face")]),
]


def _value(code: str, k: int) -> object:
    """A distinct, exactly representable value per field."""
    return {"i": 1000 + 7 * k, "d": 0.5 + 0.25 * k, "S": f"N{k}-RRR"}[code]


def _place(buf: bytearray, offset: int, code: str, value: object) -> None:
    if code == "S":
        raw = str(value).encode("utf-16-le")
        buf[offset : offset + len(raw)] = raw
    else:
        struct.pack_into("<" + code, buf, offset, value)


def _golden(size: int, type_: int, head: list[int], fields: list[tuple[int, str, str]]
            ) -> tuple[bytes, dict[str, object]]:
    buf = bytearray(size)
    struct.pack_into("<ii", buf, 0, size, type_)
    for k, v in enumerate(head):
        struct.pack_into("<i", buf, 8 + 4 * k, v)
    values: dict[str, object] = {}
    for k, (offset, code, name) in enumerate(fields):
        values[name] = _value(code, k)
        _place(buf, offset, code, values[name])
    return bytes(buf), values


@pytest.mark.parametrize("row", NOTE_COMMANDS, ids=lambda r: emscon.SPECS[r[0]].name)
def test_command_and_reply_bytes_match_the_note(row):
    cmd, cmd_size, params, reply_size, data = row
    golden, values = _golden(cmd_size, 0, [cmd], params)
    assert emscon.command(cmd, **values) == golden
    assert emscon.decode(golden, direction="from_client") == emscon.Command(cmd, values)
    golden, values = _golden(reply_size, 0, [cmd, 0], data)
    assert emscon.reply(cmd, 0, **values) == golden
    assert emscon.decode(golden) == emscon.Reply(cmd, 0, values)
    spec = emscon.SPECS[cmd]
    assert (spec.command_size, spec.reply_size) == (cmd_size, reply_size)


def test_every_codec_command_is_in_the_golden_table():
    assert {r[0] for r in NOTE_COMMANDS} == set(emscon.SPECS) - {Cmd.EXIT_APPLICATION}


def test_hex_examples_printed_in_the_note():
    assert emscon.command(Cmd.INITIALIZE).hex(" ") == "0c 00 00 00 00 00 00 00 07 00 00 00"
    assert emscon.reply(Cmd.INITIALIZE).hex(" ") == (
        "10 00 00 00 00 00 00 00 07 00 00 00 00 00 00 00")
    units = emscon.command(Cmd.SET_UNITS, length_unit=1, angle_unit=0, temperature_unit=0,
                           pressure_unit=0, humidity_unit=0)
    assert units == bytes.fromhex(
        "20000000 00000000 05000000 01000000 00000000 00000000 00000000 00000000")


SINGLE = [(20, "val1"), (28, "val2"), (36, "val3"), (44, "std1"), (52, "std2"), (60, "std3"),
          (68, "std_total"), (76, "pointing_error1"), (84, "pointing_error2"),
          (92, "pointing_error3"), (100, "apriori_std1"), (108, "apriori_std2"),
          (116, "apriori_std3"), (124, "apriori_std_total"), (132, "temperature"),
          (140, "pressure"), (148, "humidity")]
SINGLE2 = [(20, "val1"), (28, "val2"), (36, "val3"), (44, "std1"), (52, "std2"), (60, "std3"),
           (68, "std_total"), (76, "covar12"), (84, "covar13"), (92, "covar23"),
           (100, "pointing_error_h"), (108, "pointing_error_v"), (116, "pointing_error_d"),
           (124, "apriori_std1"), (132, "apriori_std2"), (140, "apriori_std3"),
           (148, "apriori_std_total"), (156, "apriori_covar12"), (164, "apriori_covar13"),
           (172, "apriori_covar23"), (180, "temperature"), (188, "pressure"),
           (196, "humidity")]


@pytest.mark.parametrize(
    ("cls", "size", "type_", "ints", "doubles"),
    [
        (emscon.SingleMeasResult, 156, 2, ["status", "meas_mode", "is_try_mode"], SINGLE),
        (emscon.SingleMeasResult2, 204, 9, ["status", "meas_mode", "is_try_mode"], SINGLE2),
        (emscon.ReflectorPosResult, 36, 7, ["status"], [(12, "val1"), (20, "val2"), (28, "val3")]),
        (emscon.NivelResult, 40, 6, ["status", "nivel_status"],
         [(16, "x_tilt"), (24, "y_tilt"), (32, "nivel_temperature")]),
        (emscon.ErrorResponse, 16, 1, ["command", "status"], []),
        (emscon.StatusChange, 12, 8, ["event"], []),
    ],
    ids=lambda v: v.__name__ if isinstance(v, type) else None,
)
def test_result_and_event_packets_match_the_note(cls, size, type_, ints, doubles):
    fields = [(8 + 4 * k, "i", n) for k, n in enumerate(ints)]
    fields += [(off, "d", n) for off, n in doubles]
    golden, values = _golden(size, type_, [], fields)
    packet = cls(**values)
    assert emscon.encode(packet) == golden
    assert emscon.decode(golden) == packet


def test_failed_reply_reads_only_16_bytes_whatever_its_size():
    basic = emscon.reply(Cmd.GET_UNITS, 10004)
    assert len(basic) == 16
    full = struct.pack("<iiii", 36, 0, Cmd.GET_UNITS, 10004) + b"\xff" * 20
    assert emscon.decode(basic) == emscon.Reply(Cmd.GET_UNITS, 10004)
    got = emscon.decode(full)
    assert got == emscon.Reply(Cmd.GET_UNITS, 10004, {}, b"\xff" * 20)
    assert not got.ok and got.data == {}


def test_size_mismatches_are_protocol_errors_not_crashes():
    ok = emscon.reply(Cmd.GET_UNITS, 0, length_unit=1, angle_unit=0, temperature_unit=0,
                      pressure_unit=0, humidity_unit=0)
    short = struct.pack("<ii", len(ok) - 4, 0) + ok[8:-4]
    with pytest.raises(UnexpectedReply, match="GetUnits"):
        emscon.decode(short)
    with pytest.raises(UnexpectedReply, match="SingleMeasResult"):
        emscon.decode(struct.pack("<iii", 12, 2, 0))
    with pytest.raises(FramingError, match="size field"):
        emscon.decode(ok[:-1])


def test_unknown_types_and_commands_are_kept_raw():
    frame = struct.pack("<ii", 20, 77) + b"abcdefghijkl"
    assert emscon.decode(frame) == emscon.UnknownPacket(77, b"abcdefghijkl")
    assert emscon.encode(emscon.UnknownPacket(77, b"abcdefghijkl")) == frame
    odd = struct.pack("<iiii", 20, 0, 64, 0) + b"\x01\x02\x03\x04"
    assert emscon.decode(odd) == emscon.Reply(64, 0, {}, b"\x01\x02\x03\x04")


def test_status_names_cover_the_enum_and_surface_unknown_codes():
    assert emscon.status_name(0) == "AllOK"
    assert emscon.status_name(4) == "WrongParameter1"
    assert emscon.status_name(55) == "WrongParameter16"
    assert emscon.status_name(21) == "Parameter6OutOfRangeOK"
    assert emscon.status_name(22) == "Parameter6OutOfRangeNOK"
    assert emscon.status_name(10009) == "NoStationaryResult"
    assert emscon.status_name(705) == "status 705 (not in the enum)"
    assert emscon.event_name(27) == "MEAS_STATUS_READY"
    assert emscon.event_name(4242) == "event 4242"


def test_exit_application_is_never_encoded_and_bad_values_are_refused():
    with pytest.raises(FramingError, match="ExitApplication"):
        emscon.command(Cmd.EXIT_APPLICATION)
    with pytest.raises(FramingError, match="missing"):
        emscon.command(Cmd.SET_REFLECTOR)
    with pytest.raises(FramingError, match="cannot pack"):
        emscon.command(Cmd.SET_REFLECTOR, internal_reflector_id=2**31)
    with pytest.raises(FramingError, match="32 UTF-16"):
        emscon.reply(Cmd.GET_SYSTEM_SOFTWARE_VERSION, version="x" * 33)


# --- round trips ---------------------------------------------------------------------------------
_INT = st.integers(-(2**31), 2**31 - 1)
_DBL = st.floats(allow_nan=False)
_NAME = st.text(st.characters(max_codepoint=0xFFFF, exclude_characters="\x00",
                              exclude_categories=("Cs",)), max_size=32)


def _layout_values(layout: emscon.Layout) -> st.SearchStrategy[dict[str, object]]:
    return st.fixed_dictionaries(
        {n: {"i": _INT, "d": _DBL, "S": _NAME}[c] for n, c in layout.fields})


@pytest.mark.parametrize("cmd", sorted(set(emscon.SPECS) - {0}), ids=lambda c: Cmd(c).name)
@settings(max_examples=15, deadline=None)
@given(data=st.data())
def test_every_command_and_reply_round_trips(cmd, data):
    spec = emscon.SPECS[cmd]
    params = data.draw(_layout_values(spec.params))
    frame = emscon.encode(emscon.Command(cmd, params))
    assert len(frame) == spec.command_size
    assert emscon.decode(frame, direction="from_client") == emscon.Command(cmd, params)
    values = data.draw(_layout_values(spec.reply))
    frame = emscon.encode(emscon.Reply(cmd, 0, values))
    assert len(frame) == spec.reply_size
    assert emscon.decode(frame) == emscon.Reply(cmd, 0, values)


_PACKETS = [emscon.SingleMeasResult, emscon.SingleMeasResult2, emscon.ReflectorPosResult,
            emscon.NivelResult, emscon.ErrorResponse, emscon.StatusChange]


@pytest.mark.parametrize("cls", _PACKETS, ids=lambda c: c.__name__)
@settings(max_examples=15, deadline=None)
@given(data=st.data())
def test_every_result_and_event_packet_round_trips(cls, data):
    values = data.draw(_layout_values(cls.LAYOUT))
    packet = cls(**values)
    assert emscon.decode(emscon.encode(packet)) == packet


# --- framer --------------------------------------------------------------------------------------
def _recorded_stream() -> list[bytes]:
    """A plausible server stream: replies, events, a result, an error, an unknown type."""
    return [
        emscon.reply(Cmd.GET_SYSTEM_STATUS, 0, last_result_status=0, tracker_processor_status=4,
                     laser_status=3, adm_status=2, version_major=3, version_minor=8,
                     version_build=7, weather_monitor_status=2, flags_value=0,
                     tracker_serial_number=390123),
        emscon.reply(Cmd.SET_UNITS),
        emscon.encode(emscon.StatusChange(6)),
        emscon.reply(Cmd.INITIALIZE),
        emscon.encode(emscon.StatusChange(151)),
        emscon.encode(emscon.StatusChange(27)),
        emscon.reply(Cmd.GET_REFLECTORS, 0, total_reflectors=1, internal_reflector_id=1,
                     target_type=5, surface_offset=19.05, reflector_name="RRR15"),
        emscon.reply(Cmd.START_MEASUREMENT),
        emscon.encode(emscon.SingleMeasResult2(val1=1234.5, val2=-20.25, val3=600.0,
                                               std1=0.004, covar12=1e-6, temperature=20.4)),
        emscon.encode(emscon.UnknownPacket(11, b"\x00" * 24)),
        emscon.encode(emscon.ErrorResponse(Cmd.START_MEASUREMENT, 10009)),
        emscon.reply(Cmd.START_MEASUREMENT, 10004),
    ]


@settings(max_examples=300, deadline=None)
@given(cuts=st.lists(st.integers(0, 10_000), max_size=40))
def test_framer_survives_every_split_and_merge(cuts):
    packets = _recorded_stream()
    stream = b"".join(packets)
    bounds = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    framer = emscon.PacketFramer()
    frames: list[bytes] = []
    for a, b in itertools.pairwise(bounds):
        framer.feed(stream[a:b])
        frames.extend(framer.frames())
    assert frames == packets
    assert framer.buffered == 0
    assert [emscon.decode(f) for f in frames][8].val1 == 1234.5


def test_framer_every_single_cut_point_and_byte_by_byte():
    packets = _recorded_stream()
    stream = b"".join(packets)
    for cut in range(len(stream) + 1):
        framer = emscon.PacketFramer()
        framer.feed(stream[:cut])
        got = list(framer.frames())
        framer.feed(stream[cut:])
        got.extend(framer.frames())
        assert got == packets
    framer = emscon.PacketFramer()
    got = []
    for i in range(len(stream)):
        framer.feed(stream[i : i + 1])
        got.extend(framer.frames())
    assert got == packets


@pytest.mark.parametrize("size", [0, 3, 8, 11, 65537, -12, 2**31 - 1])
def test_framer_bad_size_is_unrecoverable_until_reset(size):
    framer = emscon.PacketFramer()
    framer.feed(emscon.reply(Cmd.SET_UNITS) + struct.pack("<ii", size, 0) + b"\x00" * 8)
    assert framer.next_frame() == emscon.reply(Cmd.SET_UNITS)
    for _ in range(2):
        with pytest.raises(FramingError, match="reconnect"):
            framer.next_frame()
    assert framer.broken
    framer.reset()
    framer.feed(emscon.reply(Cmd.INITIALIZE))
    assert framer.next_frame() == emscon.reply(Cmd.INITIALIZE)


def test_name_fields_are_utf16_nul_padded():
    frame = emscon.reply(Cmd.GET_SYSTEM_SOFTWARE_VERSION, version="3.8 µ")
    raw = frame[16:]
    assert raw[:10] == "3.8 µ".encode("utf-16-le") and raw[10:] == b"\x00" * 54
    assert emscon.decode(frame).data["version"] == "3.8 µ"
    assert math.isclose(emscon.decode(emscon.encode(emscon.NivelResult(x_tilt=1e-5))).x_tilt,
                        1e-5)


# --- a stream recorded by the relay (simulator session, SCC, result-first, unknown types) -------
RECORDING = Path(__file__).parent / "data" / "emscon_sim_session.jsonl"


def _recorded(direction: str) -> tuple[bytes, int]:
    """The recorded bytes of one direction and the number of packets the relay decoded."""
    chunks, count = [], 0
    for line in RECORDING.read_text().splitlines()[1:]:
        rec = json.loads(line)
        if rec["dir"] == direction:
            chunks.append(bytes.fromhex(rec["hex"]))
            count += len(rec["packets"])
    return b"".join(chunks), count


@pytest.mark.parametrize(("direction", "peer"), [("s2c", "from_server"), ("c2s", "from_client")])
@settings(max_examples=100, deadline=None)
@given(cuts=st.lists(st.integers(0, 100_000), max_size=60))
def test_framer_on_every_split_of_the_recorded_session(direction, peer, cuts):
    stream, count = _recorded(direction)
    bounds = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    framer = emscon.PacketFramer()
    frames: list[bytes] = []
    for a, b in itertools.pairwise(bounds):
        framer.feed(stream[a:b])
        frames.extend(framer.frames())
    assert len(frames) == count and b"".join(frames) == stream
    packets = [emscon.decode(f, direction=peer) for f in frames]
    assert all(emscon.encode(p) == f for p, f in zip(packets, frames, strict=True)
               if not isinstance(p, emscon.Reply) or p.ok)
    if direction == "s2c":
        kinds = {type(p).__name__ for p in packets}
        assert {"Reply", "StatusChange", "SingleMeasResult2", "ErrorResponse",
                "UnknownPacket"} <= kinds
