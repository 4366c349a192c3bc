"""The emscon driver against the emScon simulator over real loopback sockets.

Every behaviour the research note leaves open is exercised in each of its simulated forms,
and every fault class of the simulator is injected at least once.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import struct
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest

from robocal.drivers import load_tracker_driver
from robocal.drivers.emscon import (
    EmsconBeamLost,
    EmsconBusy,
    EmsconNotInitialized,
    EmsconOptions,
    EmsconStatusError,
    EmsconTimeout,
    EmsconTracker,
    EmsconUnstable,
)
from robocal.drivers.sim import SimWorld
from robocal.drivers.sim.emscon import EmsconFaults, EmsconSimOptions, EmsconTrackerSimulator
from robocal.drivers.sim.faults import FaultConfig
from robocal.errors import (
    BeamLost,
    ConfigError,
    ConnectFailed,
    DriverTimeout,
    UnexpectedReply,
    Unstable,
)
from robocal.protocols import emscon
from robocal.protocols.emscon import Cmd
from tests._waiting import eventually


@pytest.fixture
def world() -> SimWorld:
    w = SimWorld.create(seed=3)
    w.move([0.3] * w.dof)
    return w


@contextlib.asynccontextmanager
async def running(world: SimWorld, shared: FaultConfig | None = None,
                  **sim_options: Any) -> AsyncIterator[EmsconTrackerSimulator]:
    sim_options.setdefault("time_scale", 0.0)
    sim = EmsconTrackerSimulator(world, EmsconSimOptions(**sim_options), shared)
    await sim.start()
    try:
        yield sim
    finally:
        await sim.stop()


@contextlib.asynccontextmanager
async def driver(sim: EmsconTrackerSimulator, connect_timeout: float = 5.0,
                 **options: Any) -> AsyncIterator[EmsconTracker]:
    options.setdefault("request_timeout_s", 2.0)
    tracker = EmsconTracker({"host": "127.0.0.1", "port": sim.port, **options})
    try:
        await tracker.connect(timeout=connect_timeout)
        yield tracker
    finally:
        await tracker.close()


def names(sim: EmsconTrackerSimulator) -> list[str]:
    return [c.name for c in sim.commands]


def assert_close(reading: Any, world: SimWorld, sigmas: float = 6.0) -> None:
    err = np.asarray(reading.position_m) - world.true_reflector_position()
    assert np.all(np.abs(err) < sigmas * np.asarray(reading.std_m) + 1e-9), err


async def test_session_sequence_units_settings_and_no_exit(world):
    async with running(world) as sim, driver(sim, reflector="rrr05") as tracker:
        reading = await tracker.measure(samples=4, timeout=2.0, point_id="A1")
        assert reading.n == 4 and reading.point_id == "A1"
        assert_close(reading, world)
        assert reading.weather == {"temp_c": 20.4, "press_hpa": 1012.6, "hum_pct": 41.0}
    assert names(sim) == [
        "GetSystemStatus", "SetUnits", "GetUnits", "GetSystemSettings", "SetSystemSettings",
        "Initialize", "SetMeasurementMode", "SetStatisticMode", "SetCoordinateSystemType",
        "GetReflectors", "SetReflector", "SetStationaryModeParams", "StartMeasurement",
    ]
    by_name = {c.name: dict(c.params) for c in sim.commands}
    assert by_name["SetUnits"] == {"length_unit": 1, "angle_unit": 0, "temperature_unit": 0,
                                   "pressure_unit": 0, "humidity_unit": 0}
    settings = by_name["SetSystemSettings"]
    assert settings["send_unsolicited_messages"] == 1
    assert settings["apply_transformation_params"] == 0
    assert settings["apply_station_orientation_params"] == 0
    assert settings["has_video_camera"] == 1  # read-modify-write kept what it did not change
    assert by_name["SetReflector"] == {"internal_reflector_id": 2}
    assert by_name["SetStationaryModeParams"] == {"meas_time": 400, "use_adm": 0}
    assert not sim.exit_received and Cmd.EXIT_APPLICATION not in [c.command for c in sim.commands]


async def test_already_initialised_tracker_is_not_initialised_again(world):
    async with running(world, initialized=True) as sim, driver(sim) as tracker:
        await tracker.measure(samples=1, timeout=2.0)
        # The measuring time is sent only when it changes.
        await tracker.measure(samples=1, timeout=2.0)
        await tracker.measure(samples=3, timeout=2.0)
    assert "Initialize" not in names(sim)
    assert names(sim).count("SetStationaryModeParams") == 2


@pytest.mark.parametrize("cs", ["RHR", "SCC", "SCW"])
@pytest.mark.parametrize("hz_ccw", [True, False])
async def test_coordinate_systems_give_the_same_point_and_covariance(world, cs, hz_ccw):
    async with running(world, scc_hz_counterclockwise=hz_ccw) as sim, driver(
            sim, coordinate_system=cs, scc_hz_counterclockwise=hz_ccw) as tracker:
        r = await tracker.measure(samples=10, timeout=2.0)
    assert_close(r, world)
    cov = np.asarray(r.cov_m2)
    assert np.allclose(cov, cov.T, rtol=0, atol=1e-20)
    assert np.allclose(np.sqrt(np.diag(cov)), r.std_m)
    # The tracker noise model is radial/transverse, so its Cartesian covariance is full; the
    # driver must recover it from whatever coordinate type the server reports in.
    truth = world.true_reflector_position()
    expected = world.cell.noise.covariances(truth[None, :])[0] / 1000  # 1 s of 1 ms samples
    assert abs(expected[0, 1]) > 0.05 * math.sqrt(expected[0, 0] * expected[1, 1])
    scale = np.max(np.abs(expected))
    assert np.max(np.abs(cov - expected)) < 1e-4 * scale
    # Spherical results are only linearised at the measured point, not at the truth.
    if cs == "RHR":
        assert np.allclose(cov, expected, rtol=1e-9, atol=0)


async def test_wrong_hz_sense_is_caught_by_geometry(world):
    # A driver assuming the other sense of Hz mirrors y: the point lands far from the truth.
    async with running(world, scc_hz_counterclockwise=True) as sim, driver(
            sim, coordinate_system="SCC", scc_hz_counterclockwise=False) as tracker:
        r = await tracker.measure(samples=1, timeout=2.0)
    truth = world.true_reflector_position()
    assert math.isclose(r.position_m[1], -truth[1], abs_tol=1e-4)


async def test_type2_results_give_a_diagonal_covariance(world):
    async with running(world, result_type="always_2") as sim, driver(sim) as tracker:
        r = await tracker.measure(samples=2, timeout=2.0)
    cov = np.asarray(r.cov_m2)
    assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0
    assert np.all(np.diag(cov) > 0)


def test_covariance_of_a_type9_result_is_mapped_to_square_metres():
    tracker = EmsconTracker({"host": "127.0.0.1"})
    res = emscon.SingleMeasResult2(val1=1000.0, val2=2000.0, val3=300.0, std1=0.01, std2=0.02,
                                   std3=0.03, covar12=1e-4, covar13=-2e-4, covar23=3e-4)
    r = tracker._reading([res], 5, "p")
    expected = np.array([[1e-4, 1e-4, -2e-4], [1e-4, 4e-4, 3e-4], [-2e-4, 3e-4, 9e-4]]) * 1e-6
    assert np.allclose(r.cov_m2, expected, rtol=1e-12, atol=0)
    assert r.position_m == (1.0, 2.0, 0.3) and r.n == 5
    # Repeats average the points; the covariance of the mean shrinks with their number.
    r2 = tracker._reading([res, res], 2, None)
    assert np.allclose(r2.cov_m2, expected / 2)


async def test_repeat_mode_takes_one_measurement_per_sample(world):
    async with running(world) as sim, driver(sim, samples_mode="repeat",
                                             sample_time_ms=50) as tracker:
        r = await tracker.measure(samples=3, timeout=2.0)
    assert names(sim).count("StartMeasurement") == 3 and r.n == 3 and r.rms_m is not None
    assert_close(r, world)


# --- open points of the note, each simulated form ---------------------------------------------
@pytest.mark.parametrize("sim_options", [
    {"result_order": "result_first"},
    {"failed_reply_size": "full"},
    {"events": "none"},
    {"result_type": "always_9"},
    {"result_type": "always_2"},
    {"announce_on_connect": True},
    {"keep_state_across_connections": False},
    {"initial_units": (0, 2, 1, 3, 0)},
    {"monitor_overrides_meteo": False},
], ids=lambda o: ",".join(f"{k}={v}" for k, v in o.items()))
async def test_driver_defaults_work_with_every_simulated_server(world, sim_options):
    async with running(world, **sim_options) as sim:
        for _ in range(2):  # a second connection sees whatever state the first left
            async with driver(sim, environment={"temp_c": 21.0, "press_hpa": 990.0,
                                                "hum_pct": 50.0}) as tracker:
                r = await tracker.measure(samples=2, timeout=2.0)
                assert_close(r, world)


async def test_optional_commands_may_be_missing_on_the_server(world):
    async with running(world, not_implemented=(Cmd.SET_STATISTIC_MODE, Cmd.GET_UNITS)) as sim, \
            driver(sim) as tracker:
        r = await tracker.measure(samples=2, timeout=2.0)
        assert_close(r, world)
        cov = np.asarray(r.cov_m2)
        assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0  # type-2 results
    async with running(world, not_implemented=(Cmd.SET_COORDINATE_SYSTEM_TYPE,)) as sim:
        with pytest.raises(EmsconStatusError, match="NotImplemented"):
            async with driver(sim):
                pass


async def test_strict_result_order_rejects_the_other_order(world):
    async with running(world, result_order="reply_first") as sim, driver(
            sim, result_order="result_first", reconnect=False) as tracker:
        with pytest.raises(Exception, match="reply before its result"):
            await tracker.measure(samples=1, timeout=1.0)


async def test_profile_only_firmware_falls_back_to_a_profile(world):
    async with running(world, stationary_mode="reject") as sim:
        async with driver(sim) as tracker:
            await tracker.measure(samples=1, timeout=2.0)
            assert tracker.meas_mode == 22
        modes = [c.params["meas_mode"] for c in sim.commands if c.name == "SetMeasurementMode"]
        assert modes == [0, 22]
        with pytest.raises(EmsconStatusError, match="InvalidMeasurementProfile") as info:
            async with driver(sim, meas_mode_fallback=None):
                pass
        assert info.value.status == 10023


async def test_initialize_status_outside_the_enum(world):
    async with running(world, initialize_status=705) as sim:
        with pytest.raises(EmsconStatusError, match=r"status 705 \(not in the enum\)"):
            async with driver(sim):
                pass
        async with driver(sim, initialize="always", initialize_ok_statuses=(705,)) as tracker:
            await tracker.measure(samples=1, timeout=2.0)


async def test_wait_for_an_event_after_initialize(world):
    async with running(world) as sim, driver(sim, wait_event_after_initialize=151) as tracker:
        assert 151 in tracker.events
    async with running(world, events="none") as sim:
        with pytest.raises(DriverTimeout, match="event 151"):
            async with driver(sim, wait_event_after_initialize=151, request_timeout_s=0.2):
                pass


async def test_meteo_out_of_range_and_units_verified(world):
    async with running(world, temp_range_c=(0.0, 30.0)) as sim:
        with pytest.raises(EmsconStatusError, match="MeteoDataOutOfRange"):
            async with driver(sim, environment={"temp_c": 35.0, "press_hpa": 1000.0,
                                                "hum_pct": 40.0}):
                pass
    async with running(world, monitor_overrides_meteo=False) as sim, driver(sim) as tracker:
        with pytest.raises(ConfigError, match="less than or equal to 100"):
            await tracker.set_environment(18.5, 950.0, 130.0)
        await tracker.set_environment(18.5, 950.0, 30.0)
        r = await tracker.measure(samples=1, timeout=2.0)
        assert r.weather == {"temp_c": 18.5, "press_hpa": 950.0, "hum_pct": 30.0}


async def test_second_client_is_told_off(world):
    async with running(world) as sim, driver(sim):
        # the refused client retries until its connect timeout, then says why
        with pytest.raises(EmsconStatusError, match="MultiConnectionsNotAllowed"):
            async with driver(sim, connect_timeout=1.0):
                pass
    async with running(world, second_client="refuse") as sim, driver(sim):
        with pytest.raises(Exception, match=r"closed|lost|connect"):
            async with driver(sim, reconnect=False):
                pass


async def test_a_client_waits_for_the_previous_session_to_end(world):
    """The server still holds a session that is going away: connect waits (bounded)."""
    async with running(world) as sim:
        first = EmsconTracker({"host": "127.0.0.1", "port": sim.port, "request_timeout_s": 2.0})
        await first.connect(timeout=5.0)
        second = EmsconTracker({"host": "127.0.0.1", "port": sim.port,
                                "request_timeout_s": 2.0})
        sent = len(sim.commands)
        pending = asyncio.create_task(second.connect(timeout=5.0))
        # a second command from it: its first was refused with 10011 and it tries again
        await eventually(lambda: len(sim.commands) >= sent + 2, 5,
                         what="the refused client to try again")
        assert not pending.done()
        await first.close()
        await asyncio.wait_for(pending, 5.0)
        reading = await second.measure(samples=2, timeout=5.0)
        assert_close(reading, world)
        await second.close()


async def test_unknown_reflector_is_a_config_error(world):
    async with running(world) as sim:
        with pytest.raises(ConfigError, match="1:RRR15, 2:RRR05, 3:BRR15"):
            async with driver(sim, reflector="CCR-0.5in"):
                pass
        async with driver(sim, reflector=3):
            pass
        assert sim.state.reflector_id == 3


# --- beam breaks and re-acquisition ---------------------------------------------------------
@pytest.mark.parametrize("signal", ["error", "event", "both", "result", "reply"])
@pytest.mark.parametrize("order", ["reply_first", "result_first"])
async def test_beam_lost_during_measurement_in_every_reported_form(world, signal, order):
    async with running(world, beam_lost_signal=signal, result_order=order) as sim, driver(
            sim, abort_drain_s=0.05) as tracker:
        sim.next_beam_break = "during"
        r = await tracker.measure(samples=2, timeout=2.0)
        assert_close(r, world)
        # Re-acquired with GoPosition to the last point (none yet: FindReflector only).
        assert names(sim).count("FindReflector") == 1
        again = await tracker.measure(samples=2, timeout=2.0)
        assert_close(again, world)
        sim.next_beam_break = "during"
        await tracker.measure(samples=2, timeout=2.0)
    tail = names(sim)[-4:]
    assert tail[:3] == ["GetMeasurementStatusInfo", "GoPosition", "FindReflector"], names(sim)
    go = [c for c in sim.commands if c.name == "GoPosition"][-1].params
    assert math.isclose(go["val1"] / 1000, again.position_m[0], abs_tol=1e-4)
    fr = [c for c in sim.commands if c.name == "FindReflector"][-1].params
    assert math.isclose(fr["approx_distance"], 1000 * math.dist(again.position_m, (0, 0, 0)),
                        rel_tol=1e-3)


@pytest.mark.parametrize("reacquire", ["find", "birdbath", "wait"])
async def test_beam_broken_at_start_is_recovered(world, reacquire):
    relock = 0.02 if reacquire == "wait" else None
    async with running(world, relock_after_s=relock) as sim, driver(
            sim, reacquire=reacquire, move_timeout_s=2.0) as tracker:
        sim.next_beam_break = "start"
        r = await tracker.measure(samples=1, timeout=2.0)
        assert_close(r, world)
    replies = names(sim)
    assert replies.count("StartMeasurement") == 2
    if reacquire == "birdbath":
        assert "GoBirdBath" in replies
    if reacquire == "wait":
        assert "FindReflector" not in replies and "GoBirdBath" not in replies


async def test_beam_lost_is_raised_when_it_stays_broken(world):
    async with running(world, find_fail_status=10014) as sim, driver(
            sim, reacquire_attempts=2) as tracker:
        sim.next_beam_break = "start"
        with pytest.raises(EmsconBeamLost, match="MeasurementStatusNotReady") as info:
            await tracker.measure(samples=1, timeout=2.0)
        assert isinstance(info.value, BeamLost) and info.value.status == 10004
        assert names(sim).count("FindReflector") == 2
    async with running(world) as sim, driver(sim, reacquire="none") as tracker:
        sim.next_beam_break = "start"
        with pytest.raises(BeamLost):
            await tracker.measure(samples=1, timeout=2.0)
        assert "FindReflector" not in names(sim)


@pytest.mark.parametrize("code", [10004, 10009, 10014, 37])
async def test_configurable_beam_broken_codes(world, code):
    async with running(world, beam_broken_start_status=code) as sim:
        async with driver(sim, reacquire="none") as tracker:
            sim.next_beam_break = "start"
            with pytest.raises(EmsconBeamLost):
                await tracker.measure(samples=1, timeout=2.0)
        async with driver(sim, reacquire="none", beam_broken_statuses=(1234,),
                          fail_on_not_ready_event=False) as tracker:
            sim.next_beam_break = "start"
            with pytest.raises(EmsconStatusError) as info:
                await tracker.measure(samples=1, timeout=2.0)
            assert not isinstance(info.value, BeamLost) and info.value.status == code


# --- typed errors ---------------------------------------------------------------------------
async def test_busy_is_retried_then_raised(world):
    async with running(world, initialized=True) as sim, driver(sim, busy_retries=0) as tracker:
        sim.emscon_faults.rates = EmsconFaults(busy_rate=1.0)
        with pytest.raises(EmsconBusy, match="ServerBusy"):
            await tracker.measure(samples=1, timeout=1.0)
        sim.emscon_faults.rates = EmsconFaults(busy_rate=0.5)
    async with running(world, initialized=True,
                       faults=EmsconFaults(busy_rate=0.5)) as sim, driver(
            sim, busy_retries=20, busy_backoff_s=0.001) as tracker:
        for _ in range(5):
            await tracker.measure(samples=1, timeout=1.0)
        assert sim.emscon_faults.counts["busy"] >= 3


async def test_not_initialised_is_typed_or_repaired(world):
    async with running(world) as sim:
        async with driver(sim, initialize="never", reinitialize=False) as tracker:
            with pytest.raises(EmsconNotInitialized, match="TrackerNotInitialized"):
                await tracker.measure(samples=1, timeout=1.0)
        async with driver(sim, initialize="never") as tracker:
            await tracker.measure(samples=1, timeout=1.0)
        assert names(sim).count("Initialize") == 1


async def test_unstable_and_module_timeout_statuses(world):
    async with running(world, FaultConfig(unstable_rate=1.0), initialized=True) as sim, driver(
            sim) as tracker:
        with pytest.raises(EmsconUnstable) as info:
            await tracker.measure(samples=1, timeout=1.0)
        assert isinstance(info.value, Unstable) and info.value.status == 10013
    async with running(world, beam_broken_start_status=41) as sim, driver(
            sim, fail_on_not_ready_event=False) as tracker:
        sim.next_beam_break = "start"
        with pytest.raises(EmsconTimeout, match="ModuleTimedOut") as t_info:
            await tracker.measure(samples=1, timeout=1.0)
        assert isinstance(t_info.value, DriverTimeout)


async def test_late_reply_times_out_and_the_session_recovers(world):
    async with running(world, initialized=True, time_scale=2.0) as sim, driver(
            sim, abort_drain_s=0.1) as tracker:
        await tracker.measure(samples=1, timeout=1.0)  # 100 ms measuring, 200 ms simulated
        with pytest.raises(DriverTimeout):
            # 500 ms measuring + 10 ms allowance, but the server takes 1 s.
            await tracker.measure(samples=5, timeout=0.01)
        # The abandoned measurement was stopped and its late packets dropped.
        assert names(sim)[-1] == "StopMeasurement"
        r = await tracker.measure(samples=1, timeout=1.0)
        assert_close(r, world)


async def test_slow_replies_within_the_timeout_are_fine(world):
    faults = FaultConfig(slow_rate=0.3, slow_s=0.02, seed=4)
    async with running(world, faults) as sim, driver(sim) as tracker:
        for _ in range(6):
            await tracker.measure(samples=1, timeout=1.0)
        assert sim.faults.counts["slow"] >= 2


# --- wire faults ----------------------------------------------------------------------------
async def test_split_merged_unknown_and_unsolicited_packets_are_handled(world):
    rates = EmsconFaults(split_rate=0.5, merge_rate=0.3, unknown_type_rate=0.3,
                         error_packet_rate=0.3)
    async with running(world, faults=rates) as sim, driver(sim) as tracker:
        for _ in range(8):
            assert_close(await tracker.measure(samples=1, timeout=1.0), world)
        counts = sim.emscon_faults.counts
        assert min(counts[k] for k in ("split", "merge", "unknown_type", "error_packet")) >= 2
        assert (66, 10015) in tracker.async_errors


async def test_bad_size_reconnects_once_and_carries_on(world):
    async with running(world) as sim, driver(sim) as tracker:
        await tracker.measure(samples=1, timeout=1.0)
        session = sim._session
        assert session is not None
        await session.send(struct.pack("<ii", 3, 0))
        r = await tracker.measure(samples=1, timeout=1.0)
        assert_close(r, world)
        assert names(sim).count("GetSystemStatus") == 2  # the session was set up again


async def test_garbage_packet_types_from_shared_faults(world):
    faults = FaultConfig(garbage_rate=0.5, seed=1)
    async with running(world, faults) as sim, driver(sim) as tracker:
        for _ in range(4):
            await tracker.measure(samples=1, timeout=1.0)
    assert sim.faults.counts["garbage"] >= 2


async def test_a_server_that_keeps_dropping_fails_cleanly(world):
    async with running(world, initialized=True) as sim, driver(sim) as tracker:
        sim.faults = type(sim.faults)(FaultConfig(drop_rate=1.0))
        with pytest.raises(ConnectFailed):
            await tracker.measure(samples=1, timeout=1.0)
        assert len(sim.commands) < 40  # one reconnect, no reconnect storm


async def test_dropped_connection_is_reconnected(world):
    async with running(world, initialized=True) as sim, driver(sim) as tracker:
        await tracker.measure(samples=1, timeout=1.0)
        sim.faults = type(sim.faults)(FaultConfig(drop_rate=1.0))
        task = asyncio.create_task(tracker.measure(samples=1, timeout=1.0))
        await asyncio.sleep(0.05)
        sim.faults = type(sim.faults)(FaultConfig())
        with contextlib.suppress(Exception):
            await asyncio.wait_for(task, 5.0)
        r = await tracker.measure(samples=1, timeout=1.0)
        assert_close(r, world)


async def test_one_command_in_flight_for_concurrent_callers(world):
    async with running(world, initialized=True, time_scale=0.2) as sim, driver(
            sim, busy_retries=0) as tracker:
        readings = await asyncio.gather(
            *(tracker.measure(samples=1, timeout=1.0, point_id=f"P{i}") for i in range(4)))
    assert [r.point_id for r in readings] == ["P0", "P1", "P2", "P3"]
    assert names(sim).count("StartMeasurement") == 4


async def test_live_positions_when_streaming(world):
    async with running(world, position_stream_period_s=0.01) as sim, driver(
            sim, reflector_position_stream=True) as tracker:
        for _ in range(40):
            await asyncio.sleep(0.02)
            await tracker.measurement_status_info()
            if tracker.live_position_m is not None:
                break
        assert tracker.live_position_m is not None
        assert math.dist(tracker.live_position_m, world.true_reflector_position()) < 1e-3


# --- options and registry -------------------------------------------------------------------
def test_options_are_strict_and_documented():
    assert EmsconOptions.model_config["extra"] == "forbid"
    with pytest.raises(ConfigError, match="no_such"):
        load_tracker_driver("emscon", {"no_such": 1})
    with pytest.raises(ConfigError, match="coordinate_system"):
        load_tracker_driver("emscon", {"coordinate_system": "CCW"})
    with pytest.raises(ConfigError, match="max_meas_time_ms"):
        load_tracker_driver("emscon", {"min_meas_time_ms": 500, "max_meas_time_ms": 100})
    doc = EmsconOptions.__doc__ or ""
    for name in EmsconOptions.model_fields:
        assert name in doc, f"option {name} is not documented"
    for point in range(1, 15):
        assert f"[10.{point}]" in doc, f"open point 10.{point} has no option"


async def test_measure_before_connect_and_bad_samples(world):
    tracker = EmsconTracker({"host": "127.0.0.1", "port": 9})
    with pytest.raises(Exception, match="not connected"):
        await tracker.measure(samples=1, timeout=1.0)
    async with running(world) as sim, driver(sim) as tracker:
        with pytest.raises(ConfigError, match="samples"):
            await tracker.measure(samples=0, timeout=1.0)


async def test_malformed_answers_fail_at_once_not_at_the_timeout():
    """A hand-written server: a GetSystemStatus reply 4 bytes short, then a short result."""
    script: dict[int, bytes] = {}

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        framer = emscon.PacketFramer()
        with contextlib.suppress(ConnectionError):
            while data := await reader.read(4096):
                framer.feed(data)
                for frame in framer.frames():
                    cmd = emscon.decode(frame, direction="from_client").command
                    writer.write(script.get(cmd, emscon.reply(cmd)))
        writer.close()

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    ok_status = emscon.reply(Cmd.GET_SYSTEM_STATUS, 0, **dict.fromkeys(
        emscon.SPECS[Cmd.GET_SYSTEM_STATUS].reply.names, 5))
    try:
        script[Cmd.GET_SYSTEM_STATUS] = struct.pack("<i", 52) + ok_status[4:52]
        tracker = EmsconTracker({"host": "127.0.0.1", "port": port, "request_timeout_s": 5.0,
                                 "verify_units": False, "reconnect": False})
        t0 = asyncio.get_running_loop().time()
        with pytest.raises(UnexpectedReply, match="GetSystemStatus must be 56 bytes"):
            await tracker.connect(timeout=5.0)
        assert asyncio.get_running_loop().time() - t0 < 2.0
        script[Cmd.GET_SYSTEM_STATUS] = ok_status
        script[Cmd.GET_SYSTEM_SETTINGS] = emscon.reply(Cmd.GET_SYSTEM_SETTINGS, 0, **dict.fromkeys(
            emscon.SPECS[Cmd.GET_SYSTEM_SETTINGS].reply.names, 0))
        script[Cmd.START_MEASUREMENT] = emscon.reply(Cmd.START_MEASUREMENT) + struct.pack(
            "<iii", 12, 2, 0)
        async with contextlib.AsyncExitStack() as stack:
            await tracker.connect(timeout=5.0)
            stack.push_async_callback(tracker.close)
            t0 = asyncio.get_running_loop().time()
            with pytest.raises(UnexpectedReply, match="SingleMeasResult must be 156 bytes"):
                await tracker.measure(samples=1, timeout=5.0)
            assert asyncio.get_running_loop().time() - t0 < 2.0
    finally:
        server.close()
        await server.wait_closed()


async def test_contract_suite_repeatedly_with_ten_percent_faults():
    """The whole tracker contract, 10 times over, with the contract test's 10 % fault mix."""
    from robocal.drivers import contracts
    from robocal.drivers.sim import SimCell

    world = SimWorld.create(seed=6)
    world.move([0.2] * world.dof)
    sigma = max(world.measure(1).sigma_m)
    rates = EmsconFaults(busy_rate=0.05, split_rate=0.1, merge_rate=0.1,
                         unknown_type_rate=0.1, error_packet_rate=0.05)
    cell = SimCell(world=world, fanuc=False, modbus=False, ltp=False,
                   emscon=EmsconSimOptions(time_scale=0.0, faults=rates),
                   faults=FaultConfig(beam_break_rate=0.05, seed=9))
    async with cell:
        options = {**cell.emscon_options(), "abort_drain_s": 0.02, "busy_backoff_s": 0.001}
        tut = contracts.TrackerUnderTest(
            "emscon", make=lambda: load_tracker_driver("emscon", options),
            true_position=world.true_reflector_position, position_tol_m=10 * sigma)
        for _ in range(10):
            await contracts.check_tracker(tut)
        sim = cell.emscon_sim
        assert sim is not None
        fired = {**sim.faults.counts, **sim.emscon_faults.counts}
    assert fired.get("beam_break", 0) >= 1 and fired.get("busy", 0) >= 3, fired
    assert min(fired.get(k, 0) for k in ("split", "merge", "unknown_type")) >= 5, fired


async def test_late_reply_after_an_error_packet_does_not_answer_the_next_measurement():
    """Type-1 error for 49 first, its failed reply 50 ms later: the retry must not take it."""
    starts = 0

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nonlocal starts
        framer = emscon.PacketFramer()
        with contextlib.suppress(ConnectionError):
            while data := await reader.read(4096):
                framer.feed(data)
                for frame in framer.frames():
                    cmd = emscon.decode(frame, direction="from_client").command
                    spec = emscon.SPECS[cmd]
                    if cmd == Cmd.START_MEASUREMENT:
                        starts += 1
                        if starts == 1:
                            writer.write(emscon.encode(emscon.ErrorResponse(cmd, 10009)))
                            await writer.drain()
                            await asyncio.sleep(0.05)
                            writer.write(emscon.reply(cmd, 10009))
                        else:
                            writer.write(emscon.reply(cmd) + emscon.encode(
                                emscon.SingleMeasResult(val1=1000.0, val2=500.0, val3=250.0,
                                                        std1=0.01, std2=0.01, std3=0.01)))
                        continue
                    data_ = dict.fromkeys(spec.reply.names, 5)
                    if cmd == Cmd.GET_UNITS:
                        data_ = {"length_unit": 1, "angle_unit": 0, "temperature_unit": 0,
                                 "pressure_unit": 0, "humidity_unit": 0}
                    writer.write(emscon.reply(cmd, 0, **data_))
        writer.close()

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    tracker = EmsconTracker({"host": "127.0.0.1", "port": port, "reacquire": "none"})
    try:
        await tracker.connect(timeout=5.0)
        with pytest.raises(EmsconBeamLost, match="NoStationaryResult"):
            await tracker.measure(samples=1, timeout=2.0)
        r = await tracker.measure(samples=1, timeout=2.0)
        assert r.position_m == (1.0, 0.5, 0.25) and starts == 2
    finally:
        await tracker.close()
        server.close()
        await server.wait_closed()


async def test_injected_bad_sizes_are_survived_by_reconnecting(world):
    rates = EmsconFaults(bad_size_rate=0.04)
    async with running(world, initialized=True, faults=rates) as sim, driver(sim) as tracker:
        for _ in range(12):
            assert_close(await tracker.measure(samples=1, timeout=1.0), world)
        assert sim.emscon_faults.counts["bad_size"] >= 1
        assert names(sim).count("GetSystemStatus") == 1 + sim.emscon_faults.counts["bad_size"]
