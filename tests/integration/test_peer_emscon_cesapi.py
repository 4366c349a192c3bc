"""The third-party PyPI client ``CESAPI`` drives the emScon simulator through a whole session.

``CESAPI`` (MuffinSpawn/Leica, written for an AT401) is someone else's reading of the TPI: its
packet classes, its blocking ``CommandSync`` and its reader thread. It agreeing with the
simulator is the check that the simulator speaks emScon as trackers do. Where the client
departs from the protocol note (docs/protocols/emscon.md, "Clients' quirks"), the session
works around it on the client's side, never in the simulator:

- the reader thread sleeps 0.2 s after every header read and ``CommandSync`` spins without
  sleeping while nothing has arrived; the test shortens the sleep to 5 ms (timing only);
- ``CommandSync.ExitApplication`` waits for a reply, which a server that stops does not
  send: the session shortens the client's 30 s timeout and expects it to run out;
- ``CommandSync.GetReflectors`` returns the first of the ``iTotalReflectors`` reply packets
  and leaves the others in its buffer (it skips replies to other commands later), so the
  session reads the rest from the buffer itself.
"""

from __future__ import annotations

import logging
import math
import time
import types
from collections.abc import Callable
from typing import Any

import numpy as np
from tests._peer import run_steps, session_in_thread

from robocal.drivers.sim import EmsconSimOptions, SimWorld
from robocal.drivers.sim.emscon import EmsconTrackerSimulator

_root_handlers = list(logging.getLogger().handlers)
from CESAPI import command as ces_command  # noqa: E402  (a test dependency: missing, it errors)
from CESAPI import connection as ces_connection  # noqa: E402
from CESAPI import packet as ces  # noqa: E402

# the client calls logging.basicConfig() when imported: the root handler it may have added
# would print every later warning of the test session to stderr
for _h in logging.getLogger().handlers[:]:
    if _h not in _root_handlers:
        logging.getLogger().removeHandler(_h)

Q_DEG = [(10.0, 20.0, -10.0, 15.0, -40.0, 30.0), (-35.0, 5.0, 20.0, -60.0, 30.0, 90.0)]


def _quick_time() -> types.SimpleNamespace:
    """The client's ``time`` module with sleeps of at most 5 ms."""
    return types.SimpleNamespace(time=time.time, sleep=lambda s: time.sleep(min(s, 0.005)))


def _near(meas: Any, truth_mm: np.ndarray, k: float = 6.0) -> bool:
    """A Cartesian result (mm) within ``k`` of its own sigmas (plus 1 um) of the truth."""
    val = np.array([meas.dVal1, meas.dVal2, meas.dVal3])
    std = np.array([meas.dStd1, meas.dStd2, meas.dStd3])
    return bool(np.all(np.abs(val - truth_mm) <= k * std + 1e-3))


class _Session:
    """The client's session, step by step (blocking sockets, run in a thread)."""

    def __init__(self, sim: EmsconTrackerSimulator, port: int) -> None:
        self.sim, self.port, self.world = sim, port, sim.world
        self.conn = ces_connection.Connection()
        self.cmd = ces_command.CommandSync(self.conn)
        self.stream: Any = None

    def connect(self) -> bool:
        self.stream = self.conn.connect(host="127.0.0.1", port=self.port)
        return True

    def status_before_init(self) -> bool:
        r = self.cmd.GetSystemStatus()
        return (r.trackerProcessorStatus == 4 and r.lTrackerSerialNumber == 390123
                and r.packetInfo.status == ces.ES_RS_AllOK)

    def initialize(self) -> bool:
        self.cmd.Initialize()
        return self.cmd.GetSystemStatus().trackerProcessorStatus == 5

    def units(self) -> bool:
        u = ces.SystemUnitsDataT()
        u.lenUnitType, u.angUnitType = ces.ES_LU_Millimeter, ces.ES_AU_Radian
        u.tempUnitType, u.pressUnitType, u.humUnitType = (
            ces.ES_TU_Celsius, ces.ES_PU_Mbar, ces.ES_HU_RH)
        self.cmd.SetUnits(u)
        got = self.cmd.GetUnits().unitsSettings
        return (got.lenUnitType, got.angUnitType) == (ces.ES_LU_Millimeter, ces.ES_AU_Radian)

    def environment(self) -> bool:
        env = ces.EnvironmentDataT()
        env.dTemperature, env.dPressure, env.dHumidity = 22.5, 1001.0, 35.0
        self.cmd.SetEnvironmentParams(env)
        got = self.cmd.GetEnvironmentParams().environmentData
        # the weather monitor reads (status 2) and overrides what a client sets, as on a
        # tracker whose monitor works: the values in force are the monitor's
        return (got.dTemperature, got.dPressure, got.dHumidity) == (20.4, 1012.6, 41.0)

    def coordinate_system(self) -> bool:
        self.cmd.SetCoordinateSystemType(ces.ES_CS_RHR)
        return self.cmd.GetCoordinateSystemType().coordSysType == ces.ES_CS_RHR

    def measurement_mode(self) -> bool:
        self.cmd.SetMeasurementMode(ces.ES_MM_Stationary)
        params = ces.StationaryModeDataT()
        params.lMeasTime, params.bUseADM = 500, 0
        self.cmd.SetStationaryModeParams(params)
        got = self.cmd.GetStationaryModeParams().stationaryModeData
        return (self.cmd.GetMeasurementMode().measMode == ces.ES_MM_Stationary
                and got.lMeasTime == 500)

    def reflectors(self) -> bool:
        first = self.cmd.GetReflectors()
        rest = []
        deadline = time.monotonic() + 5.0
        while len(rest) < first.iTotalReflectors - 1 and time.monotonic() < deadline:
            pkt = self.stream.read()
            if pkt is None:
                time.sleep(0.005)
            elif isinstance(pkt, ces.GetReflectorsRT):
                rest.append(pkt)
        ids = [first.iInternalReflectorId] + [p.iInternalReflectorId for p in rest]
        names = [p.cReflectorName.decode("utf-16-le").rstrip("\x00") for p in [first, *rest]]
        return first.iTotalReflectors == 3 and sorted(ids) == [1, 2, 3] and "RRR15" in names

    def reflector(self) -> bool:
        self.cmd.SetReflector(2)
        ok = self.cmd.GetReflector().iInternalReflectorId == 2
        self.cmd.SetReflector(1)
        return ok and self.cmd.GetReflector().iInternalReflectorId == 1

    def find_reflector(self) -> bool:
        self.cmd.GoBirdBath()
        self.world.move(np.radians(Q_DEG[0]))
        self.cmd.FindReflector(1000.0)
        return self.cmd.GetTrackerStatus().trackerStatus == ces.ES_TS_Ready

    def measure_cartesian(self) -> bool:
        ok = True
        for q in Q_DEG:
            self.world.move(np.radians(q))
            self.cmd.FindReflector(1000.0)
            res = self.cmd.StartMeasurement()
            truth = self.world.true_reflector_position() * 1e3
            ok = ok and isinstance(res, ces.SingleMeasResultT) and _near(res, truth)
        return ok

    def measure_extended(self) -> bool:
        # extended statistics: the type-9 result with the covariances
        self.cmd.SetStatisticMode(ces.ES_SM_Extended, ces.ES_SM_Extended)
        try:
            res = self.cmd.StartMeasurement()
        finally:
            self.cmd.SetStatisticMode(ces.ES_SM_Standard, ces.ES_SM_Standard)
        cov = np.array([[res.dStd1**2, res.dCovar12, res.dCovar13],
                        [res.dCovar12, res.dStd2**2, res.dCovar23],
                        [res.dCovar13, res.dCovar23, res.dStd3**2]])
        return (isinstance(res, ces.SingleMeasResult2T)
                and _near(res, self.world.true_reflector_position() * 1e3)
                and bool(np.all(np.linalg.eigvalsh(cov) > 0)))

    def measure_spherical(self) -> bool:
        self.cmd.SetCoordinateSystemType(ces.ES_CS_SCC)
        try:
            res = self.cmd.StartMeasurement()
        finally:
            self.cmd.SetCoordinateSystemType(ces.ES_CS_RHR)
        x, y, z = self.world.true_reflector_position() * 1e3
        hz, v, d = math.atan2(y, x), math.atan2(math.hypot(x, y), z), math.sqrt(x*x + y*y + z*z)
        return (abs(res.dVal1 - hz) < 1e-5 and abs(res.dVal2 - v) < 1e-5
                and abs(res.dVal3 - d) < 0.05)

    def direction(self) -> bool:
        # locked: the beam follows the reflector; after GoPosition it points at the target
        x, y, z = self.world.true_reflector_position()
        r = self.cmd.GetDirection()
        follows = (abs(r.dHzAngle - math.atan2(y, x)) < 1e-9
                   and abs(r.dVtAngle - math.atan2(math.hypot(x, y), z)) < 1e-9)
        self.cmd.GoPosition(0, 1000.0, 1000.0, 0.0)
        r = self.cmd.GetDirection()
        sent = abs(r.dHzAngle - math.pi / 4) < 1e-9 and abs(r.dVtAngle - math.pi / 2) < 1e-9
        self.cmd.FindReflector(1000.0)
        return follows and sent

    def faces(self) -> bool:
        # face 2 points the same beam with the head turned over: hz + pi, v -> 2 pi - v
        f1 = self.cmd.GetFace().trackerFace
        d1 = self.cmd.GetDirection()
        self.cmd.ChangeFace()
        f2 = self.cmd.GetFace().trackerFace
        d2 = self.cmd.GetDirection()
        self.cmd.ChangeFace()
        res = self.cmd.StartMeasurement()
        return ((f1, f2, self.cmd.GetFace().trackerFace) == (ces.ES_TF_Face1, ces.ES_TF_Face2,
                                                            ces.ES_TF_Face1)
                and abs(math.remainder(d2.dHzAngle - d1.dHzAngle - math.pi, 2 * math.pi)) < 1e-9
                and abs(d2.dVtAngle - (2 * math.pi - d1.dVtAngle)) < 1e-9
                and _near(res, self.world.true_reflector_position() * 1e3))

    def point_and_return(self) -> bool:
        # pointing the laser elsewhere leaves the reflector (a measurement fails); the last
        # measured point is where it still is, so GoLastMeasuredPoint locks on it again
        self.cmd.PointLaser(2000.0, -500.0, 300.0)
        d = self.cmd.GetDirection()
        pointed = (abs(d.dHzAngle - math.atan2(-500.0, 2000.0)) < 1e-9
                   and abs(d.dVtAngle - math.atan2(math.hypot(2000.0, 500.0), 300.0)) < 1e-9)
        try:
            self.cmd.StartMeasurement()
            off = False
        except Exception as err:
            off = "with status 10004" in str(err)
        self.cmd.GoLastMeasuredPoint()
        res = self.cmd.StartMeasurement()
        return pointed and off and _near(res, self.world.true_reflector_position() * 1e3)

    def park(self) -> bool:
        self.cmd.PointLaserHVD(3000.0, 0.5, 1.2)    # the client's order: distance, hz, v
        d = self.cmd.GetDirection()
        self.cmd.Park()
        parked = self.cmd.GetDirection()
        self.cmd.FindReflector(1000.0)
        res = self.cmd.StartMeasurement()
        return ((d.dHzAngle, d.dVtAngle) == (0.5, 1.2)
                and (parked.dHzAngle, parked.dVtAngle) == (0.0, math.pi)
                and _near(res, self.world.true_reflector_position() * 1e3))

    def bad_angle(self) -> bool:
        # a zenith angle beyond a turn is a wrong parameter (status 3), nothing moves
        before = self.cmd.GetDirection()
        try:
            self.cmd.PointLaserHVD(3000.0, 0.5, 7.0)
            refused = False
        except Exception as err:
            refused = "with status 3" in str(err)
        after = self.cmd.GetDirection()
        return refused and (before.dHzAngle, before.dVtAngle) == (after.dHzAngle,
                                                                  after.dVtAngle)

    def refraction(self) -> bool:
        r = ces.RefractionDataT()
        r.dIfmRefractionIndex, r.dAdmRefractionIndex = 1.000281, 1.000275
        self.cmd.SetRefractionParams(r)
        got = self.cmd.GetRefractionParams().refractionData
        return (got.dIfmRefractionIndex, got.dAdmRefractionIndex) == (1.000281, 1.000275)

    def beam_break(self) -> bool:
        # a broken beam: StartMeasurement fails with a status (the client raises), and
        # after FindReflector the next measurement is good again
        self.sim.next_beam_break = "start"
        try:
            self.cmd.StartMeasurement()
        except Exception as err:  # CESAPI raises a bare Exception naming the status
            failed = "with status 10004" in str(err)
        else:
            failed = False
        self.cmd.FindReflector(1000.0)
        res = self.cmd.StartMeasurement()
        return failed and _near(res, self.world.true_reflector_position() * 1e3)

    def software_version(self) -> bool:
        v = self.cmd.GetSystemSoftwareVersion().cSoftwareVersion
        return len(v.decode("utf-16-le").rstrip("\x00")) > 0

    def exit_application(self) -> bool:
        # the server stops on ExitApplication without a reply (docs/protocols/emscon.md);
        # the client waits for one until its timeout (shortened from 30 s)
        self.cmd._CommandSync__timeout = 500
        try:
            self.cmd.ExitApplication()
        except Exception as err:
            return "timed out" in str(err) and self.sim.exit_received
        return False

    def steps(self) -> list[tuple[str, Callable[[], Any]]]:
        return [
            ("connect", self.connect),
            ("GetSystemStatus before Initialize", self.status_before_init),
            ("Initialize", self.initialize),
            ("SetUnits / GetUnits", self.units),
            ("SetEnvironmentParams / GetEnvironmentParams", self.environment),
            ("SetCoordinateSystemType / Get", self.coordinate_system),
            ("SetMeasurementMode / SetStationaryModeParams", self.measurement_mode),
            ("GetReflectors (3 packets)", self.reflectors),
            ("SetReflector / GetReflector", self.reflector),
            ("GoBirdBath / FindReflector / GetTrackerStatus", self.find_reflector),
            ("StartMeasurement (RHR, mm)", self.measure_cartesian),
            ("StartMeasurement, extended statistics (type 9)", self.measure_extended),
            ("StartMeasurement (SCC, rad, mm)", self.measure_spherical),
            ("GetDirection", self.direction),
            ("GetFace / ChangeFace", self.faces),
            ("PointLaser / GoLastMeasuredPoint", self.point_and_return),
            ("PointLaserHVD / Park", self.park),
            ("PointLaserHVD out of range", self.bad_angle),
            ("SetRefractionParams / GetRefractionParams", self.refraction),
            ("beam break and re-acquire", self.beam_break),
            ("GetSystemSoftwareVersion", self.software_version),
            ("ExitApplication", self.exit_application),
        ]


def _run(sim: EmsconTrackerSimulator, port: int) -> tuple[int, int, list[str]]:
    """Run every step (a failing step does not stop the session); passed, tried, failures."""
    session = _Session(sim, port)
    try:
        return run_steps(session.steps())
    finally:
        session.conn.disconnect()


async def test_cesapi_client_session_passes_every_step(monkeypatch, capsys):
    monkeypatch.setattr(ces_connection, "time", _quick_time())
    monkeypatch.setattr(ces_command, "time", _quick_time())
    world = SimWorld.create(seed=5)
    sim = EmsconTrackerSimulator(world, EmsconSimOptions(time_scale=0.001))
    port = await sim.start()
    passed, tried, failures = await session_in_thread(sim, "CESAPI", capsys, _run, sim, port)
    assert not failures, failures
    assert passed == tried == 22
    names = {c.command for c in sim.commands}
    assert len(names) >= 20     # the session used the commands it claims to
