"""Sans-I/O codec of the Leica emScon Tracker Programming Interface (binary C-API over TCP).

Facts (sizes, offsets, IDs, codes) are those of the Leica emScon TPI/SDK 3.6 and 3.8
headers as used by public client code; ``docs/protocols/emscon.md`` says what this codec
covers and which points are still open.

Wire layout: every packet, both directions, is a little-endian C struct packed to 4 bytes::

    offset 0  int32 lPacketSize   total length, header included
    offset 4  int32 type          ES_DataType (0 command/reply, 1 error, 2/9 results, 8 events)
    offset 8  ...                 command:  int32 command [, parameters from offset 12]
                                  reply:    int32 command, int32 status [, data from offset 16]
                                  result:   int32 status, ...

Every field is 4 (``i``) or 8 (``d``) bytes, or a 64-byte UTF-16LE name, so Python's
standard-size ``<`` formats reproduce ``#pragma pack(4)`` exactly (doubles at offsets that are
multiples of 4, not 8). There is no sequence number: a reply echoes the command ID only.

:class:`PacketFramer` cuts a byte stream that may split or merge packets into frames;
:func:`decode` turns a frame into a packet object; :func:`encode` does the reverse.
Nothing here does I/O.
"""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass, field, fields
from enum import IntEnum
from typing import Any, ClassVar, Literal

from robocal.errors import FramingError, UnexpectedReply
from robocal.protocols.framing import StreamBuffer

__all__ = [
    "DEFAULT_PORT",
    "HEADER",
    "MAX_PACKET",
    "MIN_PACKET",
    "MSI_INITIALIZED",
    "MSI_REFLECTOR_FOUND",
    "SPECS",
    "STATUS_NAMES",
    "Cmd",
    "Command",
    "CommandSpec",
    "CoordSys",
    "DataType",
    "Direction",
    "ErrorResponse",
    "Event",
    "Layout",
    "MeasMode",
    "NivelResult",
    "Packet",
    "PacketFramer",
    "ReflectorPosResult",
    "Reply",
    "SingleMeasResult",
    "SingleMeasResult2",
    "Status",
    "StatusChange",
    "UnknownPacket",
    "as_dict",
    "command",
    "decode",
    "encode",
    "event_name",
    "reply",
    "status_name",
]

DEFAULT_PORT = 700
HEADER = struct.Struct("<ii")
#: Smallest packet that can exist (header plus one int32); the sanity limit of the ROS client.
MIN_PACKET = 12
MAX_PACKET = 65536
MSI_REFLECTOR_FOUND = 2048
MSI_INITIALIZED = 65536

Direction = Literal["from_server", "from_client"]


class DataType(IntEnum):
    """``ES_DataType``: the ``type`` field of the header."""

    COMMAND = 0
    ERROR = 1
    SINGLE_MEAS_RESULT = 2
    MULTI_MEAS_RESULT = 3
    STATIONARY_PROBE_MEAS_RESULT = 4
    CONTINUOUS_PROBE_MEAS_RESULT = 5
    NIVEL_RESULT = 6
    REFLECTOR_POS_RESULT = 7
    SYSTEM_STATUS_CHANGE = 8
    SINGLE_MEAS_RESULT2 = 9
    MULTI_MEAS_RESULT2 = 10
    PROBE_POS_RESULT = 11


class Cmd(IntEnum):
    """``ES_Command`` IDs a calibration campaign uses (and ExitApplication, never sent), and
    the pointing commands the simulator answers for other clients (Park, ChangeFace,
    PointLaser, PointLaserHVD, GoLastMeasuredPoint, GetFace)."""

    EXIT_APPLICATION = 0
    GET_SYSTEM_STATUS = 1
    GET_TRACKER_STATUS = 2
    PARK = 10
    SET_UNITS = 5
    GET_UNITS = 6
    INITIALIZE = 7
    SET_ENVIRONMENT_PARAMS = 20
    GET_ENVIRONMENT_PARAMS = 21
    SET_REFRACTION_PARAMS = 22
    GET_REFRACTION_PARAMS = 23
    SET_MEASUREMENT_MODE = 24
    GET_MEASUREMENT_MODE = 25
    SET_COORDINATE_SYSTEM_TYPE = 26
    GET_COORDINATE_SYSTEM_TYPE = 27
    SET_STATIONARY_MODE_PARAMS = 28
    GET_STATIONARY_MODE_PARAMS = 29
    SET_REFLECTOR = 40
    GET_REFLECTOR = 41
    GET_REFLECTORS = 42
    SET_SEARCH_PARAMS = 43
    GET_SEARCH_PARAMS = 44
    SET_SYSTEM_SETTINGS = 47
    GET_SYSTEM_SETTINGS = 48
    START_MEASUREMENT = 49
    STOP_MEASUREMENT = 52
    CHANGE_FACE = 53
    GO_BIRD_BATH = 54
    GO_POSITION = 55
    GO_POSITION_HVD = 56
    POSITION_RELATIVE_HV = 57
    POINT_LASER = 58
    POINT_LASER_HVD = 59
    GO_LAST_MEASURED_POINT = 62
    FIND_REFLECTOR = 63
    GET_DIRECTION = 66
    SET_STATISTIC_MODE = 80
    GET_STATISTIC_MODE = 81
    GO_BIRD_BATH2 = 95
    GET_FACE = 98
    SET_LONG_SYSTEM_PARAMETER = 120
    GET_LONG_SYSTEM_PARAMETER = 121
    GET_MEASUREMENT_STATUS_INFO = 122
    SET_DOUBLE_SYSTEM_PARAMETER = 125
    GET_DOUBLE_SYSTEM_PARAMETER = 126
    CLEAR_COMMAND_QUEUE = 130
    GET_TRACKER_INFO = 132
    GET_SYSTEM_SOFTWARE_VERSION = 142


class Status(IntEnum):
    """The ``ES_ResultStatus`` codes a campaign reacts to (see :func:`status_name` for all)."""

    ALL_OK = 0
    SERVER_BUSY = 1
    NOT_IMPLEMENTED = 2
    WRONG_PARAMETER = 3
    NO_DISTANCE_SET = 37
    TRACKER_NOT_INITIALIZED = 39
    MODULE_TIMED_OUT = 41
    METEO_DATA_OUT_OF_RANGE = 57
    MEASUREMENT_STATUS_NOT_READY = 10004
    NO_STATIONARY_RESULT = 10009
    SENSOR_NOT_LEVELED = 10010
    MULTI_CONNECTIONS_NOT_ALLOWED = 10011
    SENSOR_NOT_STABLE = 10013
    SYSTEM_NOT_READY_FOR_MEASUREMENT = 10014
    NOT_LEVELED_FOR_INITIALIZATION = 10019
    INVALID_MEASUREMENT_PROFILE = 10023


def _status_names() -> dict[int, str]:
    names = {
        0: "AllOK", 1: "ServerBusy", 2: "NotImplemented", 3: "WrongParameter",
        23: "WrongCurrentReflector", 26: "NoTPFound", 27: "NoWeathermonitorFound",
        28: "NoLastMeasuredPoint", 30: "NoAdm", 31: "NoNivel", 35: "UsageConflict",
        36: "Unknown", 37: "NoDistanceSet", 38: "NoTrackerConnected",
        39: "TrackerNotInitialized", 40: "ModuleNotStarted", 41: "ModuleTimedOut",
        56: "NoSuchCompensation", 57: "MeteoDataOutOfRange", 94: "NoTemperatureFromWM",
        95: "NoPressureFromWM", 96: "NoHumidityFromWM", 98: "InvalidInputData",
        10002: "NoValidADMCompensation", 10003: "PressureSensorProblem",
        10004: "MeasurementStatusNotReady", 10005: "ADMStartUpBusy", 10007: "NoAtr",
        10008: "NoOVC", 10009: "NoStationaryResult", 10010: "SensorNotLeveled",
        10011: "MultiConnectionsNotAllowed", 10012: "SensorNotWarmedUp",
        10013: "SensorNotStable", 10014: "SystemNotReadyForMeasurement",
        10015: "CommunicationWithSensorFailed", 10016: "No_Sensor_Battery",
        10017: "CompensatorNotAllowed", 10018: "WarmedUpStateReached",
        10019: "NotLeveledForInitialization", 10020: "ADMHardwareProblem",
        10021: "ATRHardwareProblem", 10022: "MaxEntriesExceeded",
        10023: "InvalidMeasurementProfile", 10024: "6DoFModeSettingFailed",
        10025: "ItemSelectionFailed",
    }
    for n in range(1, 8):  # WrongParameter1..7 = 4..10
        names[3 + n] = f"WrongParameter{n}"
    for n in range(8, 17):  # WrongParameter8..16 = 47..55
        names[39 + n] = f"WrongParameter{n}"
    for n in range(1, 7):  # Parameter<n>OutOfRangeOK/NOK = 11/12, 13/14, ... 21/22
        names[9 + 2 * n] = f"Parameter{n}OutOfRangeOK"
        names[10 + 2 * n] = f"Parameter{n}OutOfRangeNOK"
    return names


STATUS_NAMES: dict[int, str] = _status_names()


def status_name(code: int) -> str:
    """Return the ``ES_RS_`` name of ``code``, or ``"status <code> (not in the enum)"``.

    Real trackers return codes outside the published enum (e.g. 705); they are reported raw.
    """
    name = STATUS_NAMES.get(code)
    return name if name is not None else f"status {code} (not in the enum)"


class Event(IntEnum):
    """``ES_SystemStatusChange`` values of type-8 packets used by robocal."""

    ENVIRONMENT_PARAMS_CHANGED = 2
    UNITS_CHANGED = 6
    REFLECTOR_CHANGED = 7
    SYSTEM_SETTINGS_CHANGED = 8
    COORDINATE_SYSTEM_TYPE_CHANGED = 12
    MEASUREMENT_MODE_CHANGED = 17
    STATIONARY_MODE_PARAMS_CHANGED = 18
    STATISTIC_MODE_CHANGED = 24
    MEAS_STATUS_NOT_READY = 25
    MEAS_STATUS_BUSY = 26
    MEAS_STATUS_READY = 27
    INITIALIZATION_STATUS_CHANGED = 151
    TP_CONNECTION_CLOSING = 997
    SERVER_CLOSING = 998
    SERVER_STARTED = 999


def event_name(code: int) -> str:
    """Return the name of a system-status-change event, or ``"event <code>"``."""
    try:
        return Event(code).name
    except ValueError:
        return f"event {code}"


class CoordSys(IntEnum):
    """``ES_CoordinateSystemType``."""

    RHR = 0
    LHRX = 1
    LHRY = 2
    LHRZ = 3
    CCW = 4
    CCC = 5
    SCW = 6
    SCC = 7


class MeasMode(IntEnum):
    """``ES_MeasMode`` values for single points (20-23: AT4xx firmware >= 2.0 profiles)."""

    STATIONARY = 0
    FAST = 20
    STANDARD = 21
    PRECISE = 22
    OUTDOOR = 23


# --- struct layouts ----------------------------------------------------------------------------
_NAME_BYTES = 64  # unsigned short[32]


def _encode_name(text: str) -> bytes:
    raw = text.encode("utf-16-le")
    if len(raw) > _NAME_BYTES or "\x00" in text:
        raise FramingError(f"name {text[:40]!r} does not fit 32 UTF-16 units without NUL")
    return raw.ljust(_NAME_BYTES, b"\x00")


def _decode_name(raw: bytes) -> str:
    units = [raw[i : i + 2] for i in range(0, len(raw), 2)]
    end = next((i for i, u in enumerate(units) if u == b"\x00\x00"), len(units))
    return b"".join(units[:end]).decode("utf-16-le", "replace")


@dataclass(frozen=True)
class Layout:
    """A packed run of fields: ``(name, code)`` with code ``i`` (int32), ``d`` (f64) or ``S``.

    ``S`` is a 64-byte UTF-16LE name (``unsigned short[32]``), NUL-padded.
    """

    fields: tuple[tuple[str, str], ...] = ()

    @property
    def fmt(self) -> str:
        """The ``struct`` format (standard sizes, no padding)."""
        return "<" + "".join("64s" if c == "S" else c for _, c in self.fields)

    @property
    def size(self) -> int:
        """Bytes taken on the wire."""
        return struct.calcsize(self.fmt)

    @property
    def names(self) -> tuple[str, ...]:
        """Field names in wire order."""
        return tuple(n for n, _ in self.fields)

    def pack(self, values: Mapping[str, Any]) -> bytes:
        """Pack ``values`` (every field by name; names as str)."""
        missing = [n for n in self.names if n not in values]
        unknown = [k for k in values if k not in self.names]
        if missing or unknown:
            raise FramingError(f"fields missing {missing} or unknown {unknown}")
        out = []
        for name, code in self.fields:
            v = values[name]
            out.append(_encode_name(str(v)) if code == "S" else v)
        try:
            return struct.pack(self.fmt, *out)
        except struct.error as err:
            raise FramingError(f"cannot pack {dict(values)}: {err}") from err

    def unpack(self, data: bytes) -> dict[str, Any]:
        """Unpack exactly :attr:`size` bytes into a dict by field name."""
        values = struct.unpack(self.fmt, data)
        return {
            name: _decode_name(v) if code == "S" else v
            for (name, code), v in zip(self.fields, values, strict=True)
        }


def _L(*spec: str) -> Layout:
    """Build a layout from ``"name:code"`` strings."""
    return Layout(tuple((s.split(":")[0], s.split(":")[1]) for s in spec))


@dataclass(frozen=True)
class CommandSpec:
    """A command's parameters (from offset 12) and its OK reply's data (from offset 16)."""

    id: int
    name: str
    params: Layout = Layout()
    reply: Layout = Layout()

    @property
    def command_size(self) -> int:
        """Total command packet size, bytes."""
        return 12 + self.params.size

    @property
    def reply_size(self) -> int:
        """Total size of a successful reply, bytes."""
        return 16 + self.reply.size


_UNITS = _L("length_unit:i", "angle_unit:i", "temperature_unit:i", "pressure_unit:i",
            "humidity_unit:i")
_ENV = _L("temperature:d", "pressure:d", "humidity:d")
_REFR = _L("ifm_refraction_index:d", "adm_refraction_index:d")
_SETTINGS = _L("weather_monitor_status:i", "apply_transformation_params:i",
               "apply_station_orientation_params:i", "keep_last_position:i",
               "send_unsolicited_messages:i", "send_reflector_position_data:i",
               "try_measurement_mode:i", "has_nivel:i", "has_video_camera:i")

SPECS: dict[int, CommandSpec] = {
    s.id: s
    for s in (
        CommandSpec(Cmd.EXIT_APPLICATION, "ExitApplication"),
        CommandSpec(Cmd.GET_SYSTEM_STATUS, "GetSystemStatus", reply=_L(
            "last_result_status:i", "tracker_processor_status:i", "laser_status:i",
            "adm_status:i", "version_major:i", "version_minor:i", "version_build:i",
            "weather_monitor_status:i", "flags_value:i", "tracker_serial_number:i")),
        CommandSpec(Cmd.GET_TRACKER_STATUS, "GetTrackerStatus", reply=_L("tracker_status:i")),
        CommandSpec(Cmd.SET_UNITS, "SetUnits", params=_UNITS),
        CommandSpec(Cmd.GET_UNITS, "GetUnits", reply=_UNITS),
        CommandSpec(Cmd.INITIALIZE, "Initialize"),
        CommandSpec(Cmd.SET_ENVIRONMENT_PARAMS, "SetEnvironmentParams", params=_ENV),
        CommandSpec(Cmd.GET_ENVIRONMENT_PARAMS, "GetEnvironmentParams", reply=_ENV),
        CommandSpec(Cmd.SET_REFRACTION_PARAMS, "SetRefractionParams", params=_REFR),
        CommandSpec(Cmd.GET_REFRACTION_PARAMS, "GetRefractionParams", reply=_REFR),
        CommandSpec(Cmd.SET_MEASUREMENT_MODE, "SetMeasurementMode", params=_L("meas_mode:i")),
        CommandSpec(Cmd.GET_MEASUREMENT_MODE, "GetMeasurementMode", reply=_L("meas_mode:i")),
        CommandSpec(Cmd.SET_COORDINATE_SYSTEM_TYPE, "SetCoordinateSystemType",
                    params=_L("coord_sys_type:i")),
        CommandSpec(Cmd.GET_COORDINATE_SYSTEM_TYPE, "GetCoordinateSystemType",
                    reply=_L("coord_sys_type:i")),
        CommandSpec(Cmd.SET_STATIONARY_MODE_PARAMS, "SetStationaryModeParams",
                    params=_L("meas_time:i", "use_adm:i")),
        CommandSpec(Cmd.GET_STATIONARY_MODE_PARAMS, "GetStationaryModeParams",
                    reply=_L("meas_time:i", "use_adm:i")),
        CommandSpec(Cmd.SET_REFLECTOR, "SetReflector", params=_L("internal_reflector_id:i")),
        CommandSpec(Cmd.GET_REFLECTOR, "GetReflector", reply=_L("internal_reflector_id:i")),
        CommandSpec(Cmd.GET_REFLECTORS, "GetReflectors", reply=_L(
            "total_reflectors:i", "internal_reflector_id:i", "target_type:i",
            "surface_offset:d", "reflector_name:S")),
        CommandSpec(Cmd.SET_SEARCH_PARAMS, "SetSearchParams",
                    params=_L("search_radius:d", "timeout:i")),
        CommandSpec(Cmd.GET_SEARCH_PARAMS, "GetSearchParams",
                    reply=_L("search_radius:d", "timeout:i")),
        CommandSpec(Cmd.SET_SYSTEM_SETTINGS, "SetSystemSettings", params=_SETTINGS),
        CommandSpec(Cmd.GET_SYSTEM_SETTINGS, "GetSystemSettings", reply=_SETTINGS),
        CommandSpec(Cmd.START_MEASUREMENT, "StartMeasurement"),
        CommandSpec(Cmd.STOP_MEASUREMENT, "StopMeasurement"),
        CommandSpec(Cmd.GO_BIRD_BATH, "GoBirdBath"),
        CommandSpec(Cmd.GO_POSITION, "GoPosition",
                    params=_L("val1:d", "val2:d", "val3:d", "use_adm:i")),
        CommandSpec(Cmd.GO_POSITION_HVD, "GoPositionHVD",
                    params=_L("hz_angle:d", "vt_angle:d", "distance:d", "use_adm:i")),
        CommandSpec(Cmd.POSITION_RELATIVE_HV, "PositionRelativeHV",
                    params=_L("hz_val:d", "vt_val:d")),
        CommandSpec(Cmd.FIND_REFLECTOR, "FindReflector", params=_L("approx_distance:d")),
        CommandSpec(Cmd.PARK, "Park"),
        CommandSpec(Cmd.CHANGE_FACE, "ChangeFace"),
        CommandSpec(Cmd.POINT_LASER, "PointLaser", params=_L("val1:d", "val2:d", "val3:d")),
        CommandSpec(Cmd.POINT_LASER_HVD, "PointLaserHVD",
                    params=_L("hz_angle:d", "vt_angle:d", "distance:d")),
        CommandSpec(Cmd.GO_LAST_MEASURED_POINT, "GoLastMeasuredPoint"),
        CommandSpec(Cmd.GET_FACE, "GetFace", reply=_L("tracker_face:i")),
        CommandSpec(Cmd.GET_DIRECTION, "GetDirection", reply=_L("hz_angle:d", "vt_angle:d")),
        CommandSpec(Cmd.SET_STATISTIC_MODE, "SetStatisticMode",
                    params=_L("stationary_mode:i", "continuous_mode:i")),
        CommandSpec(Cmd.GET_STATISTIC_MODE, "GetStatisticMode",
                    reply=_L("stationary_mode:i", "continuous_mode:i")),
        CommandSpec(Cmd.GO_BIRD_BATH2, "GoBirdBath2", params=_L("clockwise:i")),
        CommandSpec(Cmd.SET_LONG_SYSTEM_PARAMETER, "SetLongSystemParameter",
                    params=_L("system_param:i", "parameter:i")),
        CommandSpec(Cmd.GET_LONG_SYSTEM_PARAMETER, "GetLongSystemParameter",
                    params=_L("system_param:i"), reply=_L("system_param:i", "parameter:i")),
        CommandSpec(Cmd.GET_MEASUREMENT_STATUS_INFO, "GetMeasurementStatusInfo",
                    reply=_L("last_result_status:i", "measurement_status_info:i")),
        CommandSpec(Cmd.SET_DOUBLE_SYSTEM_PARAMETER, "SetDoubleSystemParameter",
                    params=_L("system_param:i", "parameter:d")),
        CommandSpec(Cmd.GET_DOUBLE_SYSTEM_PARAMETER, "GetDoubleSystemParameter",
                    params=_L("system_param:i"), reply=_L("system_param:i", "parameter:d")),
        CommandSpec(Cmd.CLEAR_COMMAND_QUEUE, "ClearCommandQueue", params=_L("queue_type:i")),
        CommandSpec(Cmd.GET_TRACKER_INFO, "GetTrackerInfo", reply=_L(
            "tracker_type:i", "tracker_name:S", "tracker_serial_number:i",
            "compensation_id:i", "has_adm:i", "has_overview_camera:i", "has_nivel:i",
            "nivel_mount_offset:d", "max_distance:d", "min_distance:d", "max_data_rate:i",
            "number_of_faces:i", "hz_angle_range:d", "vt_angle_range:d",
            "accuracy_model:i", "lcp_firmware_major:i", "lcp_firmware_minor:i")),
        CommandSpec(Cmd.GET_SYSTEM_SOFTWARE_VERSION, "GetSystemSoftwareVersion",
                    reply=_L("version:S")),
    )
}


def _spec(cmd: int) -> CommandSpec | None:
    return SPECS.get(cmd)


def _cmd_name(cmd: int) -> str:
    spec = _spec(cmd)
    return spec.name if spec is not None else f"command {cmd}"


# --- packets -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Command:
    """Client to server, type 0: ``command`` ID and its parameters by field name."""

    command: int
    params: Mapping[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        """The command's emScon name (``GetUnits``) or ``command <id>``."""
        return _cmd_name(self.command)


@dataclass(frozen=True)
class Reply:
    """Server to client, type 0: the echoed ``command``, its ``status`` and reply data.

    ``data`` is empty when ``status`` is not 0 (a failed reply carries no valid fields, full
    size or not) and for commands this codec has no layout for; ``raw`` then keeps the bytes
    after offset 16.
    """

    command: int
    status: int = 0
    data: Mapping[str, Any] = field(default_factory=dict)
    raw: bytes = b""

    @property
    def name(self) -> str:
        """The command's emScon name."""
        return _cmd_name(self.command)

    @property
    def ok(self) -> bool:
        """True when ``status`` is 0."""
        return self.status == 0


@dataclass(frozen=True)
class ErrorResponse:
    """Type 1 (16 bytes): a failure of ``command`` (the pending one, or unsolicited)."""

    command: int
    status: int

    TYPE: ClassVar[int] = DataType.ERROR
    LAYOUT: ClassVar[Layout] = _L("command:i", "status:i")


@dataclass(frozen=True)
class StatusChange:
    """Type 8 (12 bytes): a system status change event (``Event``)."""

    event: int

    TYPE: ClassVar[int] = DataType.SYSTEM_STATUS_CHANGE
    LAYOUT: ClassVar[Layout] = _L("event:i")


@dataclass(frozen=True)
class _MeasResultFields:
    """Fields both single-point result types carry (wire order: see their ``LAYOUT``)."""

    status: int = 0
    meas_mode: int = 0
    is_try_mode: int = 0
    val1: float = 0.0
    val2: float = 0.0
    val3: float = 0.0
    std1: float = 0.0
    std2: float = 0.0
    std3: float = 0.0
    std_total: float = 0.0
    apriori_std1: float = 0.0
    apriori_std2: float = 0.0
    apriori_std3: float = 0.0
    apriori_std_total: float = 0.0
    temperature: float = 0.0
    pressure: float = 0.0
    humidity: float = 0.0


_MEAS_HEAD = ("status:i", "meas_mode:i", "is_try_mode:i", "val1:d", "val2:d", "val3:d",
              "std1:d", "std2:d", "std3:d", "std_total:d")
_APRIORI = ("apriori_std1:d", "apriori_std2:d", "apriori_std3:d", "apriori_std_total:d")
_METEO = ("temperature:d", "pressure:d", "humidity:d")


@dataclass(frozen=True)
class SingleMeasResult(_MeasResultFields):
    """Type 2 (156 bytes): a single-point result in the current units and CS type."""

    pointing_error1: float = 0.0
    pointing_error2: float = 0.0
    pointing_error3: float = 0.0

    TYPE: ClassVar[int] = DataType.SINGLE_MEAS_RESULT
    LAYOUT: ClassVar[Layout] = _L(
        *_MEAS_HEAD, "pointing_error1:d", "pointing_error2:d", "pointing_error3:d",
        *_APRIORI, *_METEO)


@dataclass(frozen=True)
class SingleMeasResult2(_MeasResultFields):
    """Type 9 (204 bytes): a single-point result with covariances (statistic mode Extended)."""

    covar12: float = 0.0
    covar13: float = 0.0
    covar23: float = 0.0
    pointing_error_h: float = 0.0
    pointing_error_v: float = 0.0
    pointing_error_d: float = 0.0
    apriori_covar12: float = 0.0
    apriori_covar13: float = 0.0
    apriori_covar23: float = 0.0

    TYPE: ClassVar[int] = DataType.SINGLE_MEAS_RESULT2
    LAYOUT: ClassVar[Layout] = _L(
        *_MEAS_HEAD, "covar12:d", "covar13:d", "covar23:d",
        "pointing_error_h:d", "pointing_error_v:d", "pointing_error_d:d", *_APRIORI,
        "apriori_covar12:d", "apriori_covar13:d", "apriori_covar23:d", *_METEO)


@dataclass(frozen=True)
class ReflectorPosResult:
    """Type 7 (36 bytes): live reflector position (current CS and units)."""

    status: int = 0
    val1: float = 0.0
    val2: float = 0.0
    val3: float = 0.0

    TYPE: ClassVar[int] = DataType.REFLECTOR_POS_RESULT
    LAYOUT: ClassVar[Layout] = _L("status:i", "val1:d", "val2:d", "val3:d")


@dataclass(frozen=True)
class NivelResult:
    """Type 6 (40 bytes): levelling sensor result."""

    status: int = 0
    nivel_status: int = 0
    x_tilt: float = 0.0
    y_tilt: float = 0.0
    nivel_temperature: float = 0.0

    TYPE: ClassVar[int] = DataType.NIVEL_RESULT
    LAYOUT: ClassVar[Layout] = _L(
        "status:i", "nivel_status:i", "x_tilt:d", "y_tilt:d", "nivel_temperature:d")


@dataclass(frozen=True)
class UnknownPacket:
    """A packet of a type this codec does not decode (skipped by clients); body after offset 8."""

    type: int
    body: bytes = b""


Packet = (
    Command | Reply | ErrorResponse | StatusChange | SingleMeasResult | SingleMeasResult2
    | ReflectorPosResult | NivelResult | UnknownPacket
)
_FIXED: dict[int, Any] = {
    c.TYPE: c
    for c in (ErrorResponse, StatusChange, SingleMeasResult, SingleMeasResult2,
              ReflectorPosResult, NivelResult)
}


def _frame(type_: int, body: bytes) -> bytes:
    return HEADER.pack(HEADER.size + len(body), type_) + body


def encode(packet: Packet) -> bytes:
    """Return the wire bytes of ``packet`` (header included).

    Raises
    ------
    FramingError
        Missing or unknown parameter names, values that do not fit, names longer than 32
        UTF-16 units, or a command without a layout that carries parameters. ExitApplication
        (command 0) is refused: it stops the tracker's server.
    """
    if isinstance(packet, Command):
        if packet.command == Cmd.EXIT_APPLICATION:
            raise FramingError("refusing to encode ExitApplication (it stops the emScon server)")
        spec = _spec(packet.command)
        if spec is None:
            if packet.params:
                raise FramingError(f"no layout for the parameters of command {packet.command}")
            return _frame(DataType.COMMAND, struct.pack("<i", packet.command))
        return _frame(
            DataType.COMMAND, struct.pack("<i", packet.command) + spec.params.pack(packet.params)
        )
    if isinstance(packet, Reply):
        head = struct.pack("<ii", packet.command, packet.status)
        spec = _spec(packet.command)
        if packet.data:
            if spec is None:
                raise FramingError(f"no layout for the reply data of command {packet.command}")
            return _frame(DataType.COMMAND, head + spec.reply.pack(packet.data) + packet.raw)
        return _frame(DataType.COMMAND, head + packet.raw)
    if isinstance(packet, UnknownPacket):
        return _frame(packet.type, packet.body)
    values = {f.name: getattr(packet, f.name) for f in fields(packet)}
    return _frame(packet.TYPE, packet.LAYOUT.pack(values))


def command(cmd: int, **params: Any) -> bytes:
    """Encode command ``cmd`` with keyword parameters (shorthand for ``encode(Command(...))``)."""
    return encode(Command(int(cmd), params))


def reply(cmd: int, status: int = 0, **data: Any) -> bytes:
    """Encode a reply to ``cmd`` (shorthand for ``encode(Reply(...))``)."""
    return encode(Reply(int(cmd), status, data))


def decode(frame: bytes, *, direction: Direction = "from_server") -> Packet:
    """Decode one complete frame (as returned by :class:`PacketFramer`).

    ``direction`` tells type-0 packets apart: commands come from the client, replies from
    the server.

    Raises
    ------
    FramingError
        If the frame's size field disagrees with its length.
    UnexpectedReply
        If a known packet has the wrong size for its type (the stream stays in step, since
        framing is by the size field: a client may log it and carry on).
    """
    if len(frame) < HEADER.size:
        raise FramingError(f"frame of {len(frame)} bytes is shorter than the header")
    size, type_ = HEADER.unpack_from(frame)
    if size != len(frame):
        raise FramingError(f"size field {size} but frame of {len(frame)} bytes",
                           last_frames=[frame[:64]])
    body = frame[HEADER.size :]
    if type_ == DataType.COMMAND:
        return _decode_type0(frame, body, direction)
    cls = _FIXED.get(type_)
    if cls is None:
        return UnknownPacket(type_, bytes(body))
    layout: Layout = cls.LAYOUT
    if len(body) != layout.size:
        raise UnexpectedReply(
            f"{cls.__name__} must be {HEADER.size + layout.size} bytes, got {size}",
            last_frames=[frame[:64]],
        )
    return cls(**layout.unpack(body))


def _decode_type0(frame: bytes, body: bytes, direction: Direction) -> Packet:
    if len(body) < 4:
        raise UnexpectedReply("type-0 packet without a command ID", last_frames=[frame[:64]])
    (cmd,) = struct.unpack_from("<i", body)
    spec = _spec(cmd)
    if direction == "from_client":
        params = body[4:]
        if spec is None:
            return Command(cmd, {})
        if len(params) != spec.params.size:
            raise UnexpectedReply(
                f"{spec.name} command must be {spec.command_size} bytes, got {len(frame)}",
                last_frames=[frame[:64]],
            )
        return Command(cmd, spec.params.unpack(params))
    if len(body) < 8:
        raise UnexpectedReply(
            f"reply to {_cmd_name(cmd)} shorter than 16 bytes", last_frames=[frame[:64]]
        )
    (status,) = struct.unpack_from("<i", body, 4)
    data = body[8:]
    if status != 0:
        # Only the first 16 bytes of a failed reply are meaningful, whatever its size;
        # the rest is kept raw (so its size stays visible) but never decoded.
        return Reply(cmd, status, {}, bytes(data))
    if spec is None:
        return Reply(cmd, status, {}, bytes(data))
    if len(data) != spec.reply.size:
        raise UnexpectedReply(
            f"OK reply to {spec.name} must be {spec.reply_size} bytes, got {len(frame)}",
            last_frames=[frame[:64]],
        )
    return Reply(cmd, status, spec.reply.unpack(data))


def as_dict(packet: Packet) -> dict[str, Any]:
    """Return the packet's fields as a plain dict (for logs and recordings)."""
    return asdict(packet)


# --- framing -----------------------------------------------------------------------------------
class PacketFramer(StreamBuffer):
    """Cut a byte stream into emScon frames using the ``lPacketSize`` field.

    Bytes may arrive in any split (even inside the 8-byte header) or several packets at
    once. A size below ``min_size`` or above ``max_size`` cannot be recovered from (the
    protocol has no resynchronisation marker): :meth:`next_frame` raises
    :class:`~robocal.errors.FramingError` and keeps raising until :meth:`reset`; the client
    must close and reconnect.

    Parameters
    ----------
    min_size, max_size : int
        Accepted packet sizes, bytes (defaults 12 and 64 KiB).
    history : int
        Number of recent frames kept for error reports.
    """

    def __init__(
        self, *, min_size: int = MIN_PACKET, max_size: int = MAX_PACKET, history: int = 16
    ) -> None:
        if not HEADER.size <= min_size <= max_size:
            raise ValueError("need 8 <= min_size <= max_size")
        super().__init__()
        self.min_size = min_size
        self.max_size = max_size
        self._broken: str | None = None
        self.recent: deque[bytes] = deque(maxlen=history)

    @property
    def broken(self) -> bool:
        """True after a bad size field (the stream cannot be resynchronised)."""
        return self._broken is not None

    def next_frame(self) -> bytes | None:
        """Return the next complete frame, or None if it has not fully arrived.

        Raises
        ------
        FramingError
            On a size field outside ``[min_size, max_size]`` (and on every call after it).
        """
        if self._broken is not None:
            raise FramingError(self._broken, last_frames=list(self.recent))
        if len(self._buf) < 4:
            return None
        (size,) = struct.unpack_from("<i", self._buf)
        if not self.min_size <= size <= self.max_size:
            self._broken = (
                f"packet size {size} outside [{self.min_size}, {self.max_size}]; "
                "no resynchronisation is possible, reconnect"
            )
            self.recent.append(bytes(self._buf[:32]))
            raise FramingError(self._broken, last_frames=list(self.recent))
        if len(self._buf) < size:
            return None
        frame = bytes(self._buf[:size])
        del self._buf[:size]
        self.recent.append(frame[:64])
        return frame

    def frames(self) -> Iterator[bytes]:
        """Yield every complete frame buffered so far (raises like :meth:`next_frame`)."""
        while (frame := self.next_frame()) is not None:
            yield frame

    def reset(self) -> None:
        """Drop buffered bytes and the broken state (after a reconnect)."""
        self._buf.clear()
        self._broken = None
