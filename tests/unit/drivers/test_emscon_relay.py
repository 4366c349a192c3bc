"""Capture and replay of emScon sessions, the ``robocal sim`` commands, and the deploy config."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from robocal.daemon.config import config_errors, load_config
from robocal.drivers import load_tracker_driver
from robocal.drivers.emscon import EmsconTracker
from robocal.drivers.sim import SimWorld
from robocal.drivers.sim.emscon import EmsconFaults, EmsconSimOptions, EmsconTrackerSimulator
from robocal.drivers.sim.relay import (
    FORMAT,
    EmsconRelay,
    EmsconReplayServer,
    load_recording,
    recorded_packets,
)
from robocal.errors import ConfigError
from robocal.protocols import emscon

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture
def world() -> SimWorld:
    w = SimWorld.create(seed=8)
    w.move([0.25] * w.dof)
    return w


@contextlib.asynccontextmanager
async def served(server: Any) -> AsyncIterator[Any]:
    await server.start()
    try:
        yield server
    finally:
        await server.stop()


async def session(port: int, **options: Any) -> list[Any]:
    tracker = EmsconTracker({"host": "127.0.0.1", "port": port, "request_timeout_s": 2.0,
                             "reflector": "RRR15", **options})
    await tracker.connect(timeout=5.0)
    try:
        return [await tracker.measure(samples=s, timeout=2.0, point_id=f"P{s}")
                for s in (1, 3)]
    finally:
        await tracker.close()


async def test_relay_records_a_session_and_replay_answers_it(world, tmp_path):
    record = tmp_path / "site.jsonl"
    # Split and merged writes: the recording keeps the chunks as they came.
    wire = EmsconFaults(split_rate=0.3, merge_rate=0.3)
    sim = EmsconTrackerSimulator(world, EmsconSimOptions(time_scale=0.0, faults=wire))
    async with served(sim):
        relay = EmsconRelay("127.0.0.1", sim.port, record)
        async with served(relay):
            original = await session(relay.port)
    records = load_recording(record)
    header = json.loads(record.read_text().splitlines()[0])
    assert header["format"] == FORMAT and header["target"] == f"127.0.0.1:{sim.port}"
    assert records[0].dir == "open" and records[-1].dir == "close"
    lines = [json.loads(x) for x in record.read_text().splitlines()[1:]]
    assert any("command StartMeasurement" in p for x in lines for p in x.get("packets", []))
    assert any("SingleMeasResult2" in p for x in lines for p in x.get("packets", []))
    # Everything the client sent and received is in the file, byte for byte.
    packets = recorded_packets(records)
    sent = [f for _, d, f in packets if d == "c2s"]
    assert [emscon.decode(f, direction="from_client") for f in sent] == sim.commands
    got = [emscon.decode(f) for _, d, f in packets if d == "s2c"]
    results = [p for p in got if isinstance(p, emscon.SingleMeasResult2)]
    assert [r.val1 / 1000 for r in results] == [o.position_m[0] for o in original]

    # Replay: the same client session gets the same answers without a tracker.
    replay = EmsconReplayServer(records)
    async with served(replay):
        again = await session(replay.port)
    assert [r.position_m for r in again] == [r.position_m for r in original]
    assert [r.cov_m2 for r in again] == [r.cov_m2 for r in original]
    assert replay.unmatched == []


async def test_replay_answers_unknown_commands_with_not_implemented(world, tmp_path):
    record = tmp_path / "short.jsonl"
    sim = EmsconTrackerSimulator(world, EmsconSimOptions(time_scale=0.0))
    async with served(sim):
        relay = EmsconRelay("127.0.0.1", sim.port, record)
        async with served(relay):
            await session(relay.port)
    replay = EmsconReplayServer(load_recording(record), match="bytes")
    async with served(replay):
        # Other options mean other bytes (SCC instead of RHR): no recorded counterpart.
        with pytest.raises(Exception, match="NotImplemented"):
            await session(replay.port, coordinate_system="SCC")
    assert replay.unmatched
    assert emscon.decode(replay.unmatched[0], direction="from_client").name == (
        "SetCoordinateSystemType")


async def test_relay_reports_an_unreachable_target(tmp_path):
    record = tmp_path / "none.jsonl"
    probe = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
    dead_port = probe.sockets[0].getsockname()[1]
    probe.close()
    await probe.wait_closed()
    relay = EmsconRelay("127.0.0.1", dead_port, record, connect_timeout_s=1.0)
    async with served(relay):
        reader, writer = await asyncio.open_connection("127.0.0.1", relay.port)
        assert await asyncio.wait_for(reader.read(), 5.0) == b""
        writer.close()
    last = json.loads(record.read_text().splitlines()[-1])
    assert last["dir"] == "close" and "cannot reach the target" in last["error"]


def test_bad_recordings_are_config_errors(tmp_path):
    p = tmp_path / "x.jsonl"
    with pytest.raises(ConfigError, match="cannot read"):
        load_recording(p)
    p.write_text('{"format": "something else"}\n')
    with pytest.raises(ConfigError, match="not a robocal-emscon-capture"):
        load_recording(p)
    p.write_text(json.dumps({"format": FORMAT}) + '\n{"t": 0, "conn": 1, "dir": "up"}\n')
    with pytest.raises(ConfigError, match=r"x.jsonl:2.*bad dir"):
        load_recording(p)
    p.write_text(json.dumps({"format": FORMAT}) + "\n")
    with pytest.raises(ConfigError, match="no client packets"):
        EmsconReplayServer(load_recording(p))


# --- robocal sim as a process --------------------------------------------------------------------
async def _start(*args: str) -> tuple[asyncio.subprocess.Process, dict[str, Any]]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "robocal.drivers.sim", *args,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    assert proc.stdout is not None
    line = await asyncio.wait_for(proc.stdout.readline(), 30)
    return proc, json.loads(line)


async def _stop(proc: asyncio.subprocess.Process) -> None:
    if proc.returncode is None:
        proc.send_signal(signal.SIGTERM)
        assert await asyncio.wait_for(proc.wait(), 20) == 0


async def test_sim_relay_and_replay_processes(tmp_path):
    record = tmp_path / "cli.jsonl"
    procs = []
    try:
        tracker, ports = await _start("emscon-tracker", "--time-scale", "0", "--seed", "2")
        procs.append(tracker)
        port = ports["emscon_tracker"]["port"]
        relay, rports = await _start("relay", "--listen", "127.0.0.1:0", "--target",
                                     f"127.0.0.1:{port}", "--record", str(record))
        procs.append(relay)
        first = await session(rports["relay"]["port"])
        await _stop(relay)
        await _stop(tracker)
        replay, pports = await _start("emscon-tracker", "--replay", str(record))
        procs.append(replay)
        again = await session(pports["emscon_tracker"]["port"])
        assert [r.position_m for r in again] == [r.position_m for r in first]
        await _stop(replay)
    finally:
        for p in procs:
            if p.returncode is None:
                p.kill()
                await p.wait()


async def test_sim_cli_errors(tmp_path):
    from robocal.drivers.sim import main

    assert await asyncio.to_thread(main, ["relay", "--target", "127.0.0.1:700"]) == 2
    assert await asyncio.to_thread(
        main, ["relay", "--target", "nohostport", "--record", str(tmp_path / "r")]) == 2
    assert await asyncio.to_thread(
        main, ["emscon-tracker", "--replay", str(tmp_path / "missing.jsonl")]) == 2


# --- deploy config -----------------------------------------------------------------------------
async def test_deploy_config_validates_and_its_tracker_options_work(world):
    path = REPO / "deploy" / "config" / "emscon.toml"
    assert config_errors(path) == []
    cfg = load_config(path)
    assert cfg.robot.kind == "fanuc_rmi" and cfg.tracker.kind == "emscon"
    options = dict(cfg.tracker.options)
    tracker = load_tracker_driver("emscon", options)
    assert isinstance(tracker, EmsconTracker)
    assert tracker.options.port == 700 and tracker.options.reflector == "RRR15"
    # The documented options drive the simulator end to end (only the address differs).
    sim = EmsconTrackerSimulator(world, EmsconSimOptions(time_scale=0.0))
    async with served(sim):
        tracker = load_tracker_driver("emscon", {**options, "host": "127.0.0.1", "port": sim.port})
        await tracker.connect(timeout=cfg.tracker.connect_timeout_s)
        try:
            r = await tracker.measure(samples=cfg.measurement.samples,
                                      timeout=cfg.measurement.timeout_s)
        finally:
            await tracker.close()
    assert r.n == cfg.measurement.samples
    assert [c.params for c in sim.commands if c.name == "SetStationaryModeParams"] == [
        {"meas_time": 1000, "use_adm": 0}]
