"""kill -9 at every journaled point of approve, push and rollback, against the FANUC simulator.

The simulators run in this process (a thread with its own event loop) so every position
register write the controller receives is counted; the daemon is a real process that
``ROBOCAL_FAULT_POINT`` makes ``os._exit`` at the named point (the same as kill -9 there).
After each crash the daemon restarts without the hook and reconciles its journal with the
controller. Checked: exactly one controller write per approved push, never a second blind
one; the approved model is the one pushed; every action has its audit entries; rollback
after the first push restores the controller's own position registers.
"""

from __future__ import annotations

import asyncio
import json
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from tests.integration.test_daemon_processes import (
    ROBOT,
    Daemon,
    small_plan,
    wait_for,
    write_config,
)

from robocal.daemon.client import ApiError, DaemonUnavailable
from robocal.protocols import fanuc_rmi as rmi

PR_BASE = 11


class SimThread:
    """FANUC RMI and LTP simulators on a background event loop; records PR writes."""

    def __init__(self) -> None:
        from robocal.drivers.sim import FanucSimOptions, LtpSimOptions, SimCell

        self.loop = asyncio.new_event_loop()
        self.cell = SimCell(robot=ROBOT, seed=5, fanuc=FanucSimOptions(time_scale=0.0005),
                            modbus=False, ltp=LtpSimOptions(time_scale=0.0005))
        self.writes: list[tuple[int, tuple[float, ...]]] = []
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)

    def __enter__(self) -> SimThread:
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self.cell.start(), self.loop).result(30)
        sim = self.cell.fanuc_sim
        assert sim is not None
        original = sim.command

        def counting(packet: Any, session: Any) -> dict[str, Any]:
            reply = original(packet, session)
            if packet.name == "FRC_WritePositionRegister" and reply.get("ErrorID", 0) == 0:
                pos = packet.body["Position"]
                self.writes.append((int(packet.body["RegisterNumber"]),
                                    tuple(float(pos[k]) for k in "XYZWPR")))
            return reply

        sim.command = counting  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        asyncio.run_coroutine_threadsafe(self.cell.stop(), self.loop).result(30)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(10)
        self.loop.close()

    @property
    def ports(self) -> dict[str, Any]:
        return self.cell.ports

    def registers(self) -> dict[int, tuple[float, ...]]:
        sim = self.cell.fanuc_sim
        assert sim is not None
        return {n: tuple(float(v["Position"][k]) for k in "XYZWPR")
                for n, v in sim.position_registers.items()}

    def set_register(self, n: int, q_deg: list[float]) -> None:
        sim = self.cell.fanuc_sim
        assert sim is not None
        sim.position_registers[n] = {
            "Configuration": rmi.Configuration().fields(),
            "Position": dict(zip("XYZWPR", [*q_deg, *([0.0] * (6 - len(q_deg)))],
                                 strict=True))}


@pytest.fixture
def sims() -> Iterator[SimThread]:
    with SimThread() as s:
        yield s


def _db(tmp: Path) -> sqlite3.Connection:
    db = sqlite3.connect(f"file:{tmp / 'state' / 'robocal.sqlite3'}?mode=ro", uri=True)
    db.row_factory = sqlite3.Row
    return db


def _audit(tmp: Path) -> list[dict[str, Any]]:
    db = _db(tmp)
    try:
        rows = db.execute("SELECT action, actor, campaign, detail FROM audit ORDER BY id")
        return [{**dict(r), "detail": json.loads(r["detail"])} for r in rows]
    finally:
        db.close()


def _tables(tmp: Path) -> dict[int, dict[str, Any]]:
    db = _db(tmp)
    try:
        return {int(r["id"]): dict(r) for r in db.execute("SELECT * FROM tables")}
    finally:
        db.close()


def _rows(table_json: str) -> dict[int, tuple[float, ...]]:
    """Register number -> the six values the FANUC driver writes there for this table.

    Found by letting the driver write it to a recorder instead of a controller, so the test
    follows the driver's register layout.
    """
    from robocal.compensation import CompensationTable
    from robocal.drivers.fanuc_rmi import FanucRmiRobot
    from robocal.kinematics import load_robot as load_description

    limits = np.degrees(load_description(ROBOT).joint_limits).tolist()
    robot = FanucRmiRobot({"pr_base": PR_BASE, "joint_limits_deg": limits})
    out: dict[int, tuple[float, ...]] = {}

    async def record(name: str, **fields: Any) -> None:
        assert name == "FRC_WritePositionRegister"
        out[int(fields["RegisterNumber"])] = tuple(float(fields["Position"][k])
                                                   for k in "XYZWPR")

    robot._command = record  # type: ignore[method-assign,assignment]
    asyncio.run(robot._write_targets(CompensationTable.model_validate_json(table_json)))
    return out


def _writes_of(sims: SimThread, values: dict[int, tuple[float, ...]]) -> int:
    """How many times the controller received this whole set of register values."""
    counts = []
    for n, v in values.items():
        counts.append(sum(1 for reg, pos in sims.writes if reg == n
                          and all(abs(a - b) < 1e-4 for a, b in zip(pos, v, strict=True))))
    assert len(set(counts)) == 1, f"registers written unevenly: {counts}"
    return counts[0]


def _crash(daemon: Daemon, monkeypatch: pytest.MonkeyPatch, point: str, method: str,
           path: str, body: dict[str, Any] | None = None) -> None:
    """Restart the daemon with the fault hook at ``point``, send the request, see it die."""
    daemon.stop()
    monkeypatch.setenv("ROBOCAL_FAULT_POINT", point)
    daemon.start()
    monkeypatch.delenv("ROBOCAL_FAULT_POINT")
    with pytest.raises((DaemonUnavailable, ApiError, OSError)):
        daemon.client.request(method, path, body)
    assert daemon.proc is not None
    assert daemon.proc.wait(30) == 86, f"the daemon did not die at {point}"
    daemon.start()


def _state(daemon: Daemon, cid: str) -> dict[str, Any]:
    return daemon.status(cid)


_EXTRA = """
[limits]
max_joint_correction_deg = 10.0

[compensation]
kind = "targets"
verify_count = 0
"""


def _cell(tmp_path: Path, sims: SimThread) -> tuple[Daemon, Path, dict[int, tuple[float, ...]]]:
    """A started daemon against ``sims`` (FANUC targets table at PR_BASE), the plan to run,
    and the robot program's own targets, written into the registers robocal will write."""
    config = write_config(tmp_path, sims.ports, extra=_EXTRA)
    text = config.read_text().replace(
        'options = { host = "127.0.0.1", connect_port',
        f'options = {{ pr_base = {PR_BASE}, host = "127.0.0.1", connect_port')
    config.write_text(text)
    plan = small_plan(tmp_path, count=36, validation=6)
    originals: dict[int, tuple[float, ...]] = {}
    for n in range(PR_BASE, PR_BASE + 40):
        values = [n + 0.5, -n - 0.25, 100.0 + n, 0.0, 0.0, 0.0]
        sims.set_register(n, values)
        originals[n] = tuple(values)
    daemon = Daemon(tmp_path, config)
    daemon.start()
    return daemon, plan, originals


def _fitted(daemon: Daemon, tmp_path: Path, plan: Path) -> str:
    """Run one campaign of ``plan`` to ``fitted``; its id."""
    out = daemon.cli("campaign", "start", "--socket", str(tmp_path / "api.sock"), "--plan",
                     str(plan))
    cid = out.stdout.strip()
    wait_for(lambda: _state(daemon, cid)["state"] in ("fitted", "faulted"), 180,
             f"campaign {cid} fitted")
    assert _state(daemon, cid)["state"] == "fitted", daemon.log_tail()
    return cid


def _story(tmp_path: Path) -> list[str]:
    return [a["action"] for a in _audit(tmp_path)
            if a["action"].startswith(("campaign.approve", "compensation."))]


# The journal's points are split over two tests with a campaign each, so that xdist runs
# them side by side (one test restarting the daemon 18 times was the suite's longest).
@pytest.mark.slow
def test_kill9_at_every_journaled_point_of_approve_and_push(tmp_path, sims, monkeypatch):
    daemon, plan, originals = _cell(tmp_path, sims)
    try:
        first = _fitted(daemon, tmp_path, plan)
        fits = _state(daemon, first)["fits"]

        # --- approve -------------------------------------------------------------------------
        _crash(daemon, monkeypatch, "approve:before-commit", "POST",
               f"/campaigns/{first}/approve", {"model": "constant"})
        assert _state(daemon, first)["state"] == "fitted"
        assert not [a for a in _audit(tmp_path) if a["action"] == "campaign.approve"]
        _crash(daemon, monkeypatch, "approve:after-commit", "POST",
               f"/campaigns/{first}/approve", {"model": "constant"})
        st = _state(daemon, first)
        assert st["state"] == "approved" and st["selected_model"] == "constant"
        approvals = [a for a in _audit(tmp_path) if a["action"] == "campaign.approve"]
        assert len(approvals) == 1 and approvals[0]["detail"]["model"] == "constant"
        # approving again is refused (already approved); nothing changes
        with pytest.raises(ApiError):
            daemon.client.request("POST", f"/campaigns/{first}/approve", {"model": "constant"})

        # --- push: killed before, at and after the controller write --------------------------
        assert sims.writes == []
        _crash(daemon, monkeypatch, "push:after-snapshot", "POST", f"/campaigns/{first}/push")
        assert _state(daemon, first)["state"] == "approved" and sims.writes == []
        _crash(daemon, monkeypatch, "push:after-intent", "POST", f"/campaigns/{first}/push")
        # the restarted daemon read the controller, found nothing written, abandoned the intent
        assert _state(daemon, first)["state"] == "approved" and sims.writes == []
        assert sims.registers() == originals
        abandoned = [a for a in _audit(tmp_path) if a["action"] == "compensation.push-abandoned"]
        assert len(abandoned) == 1 and "interrupted" in abandoned[0]["detail"]["reason"]
        _crash(daemon, monkeypatch, "push:after-write", "POST", f"/campaigns/{first}/push")
        # written before the kill: the restart found it on the controller and completed it
        st = _state(daemon, first)
        assert st["state"] == "pushed", st["reason"]
        push1 = st["push"]
        tables = _tables(tmp_path)
        t1 = next(t for t in tables.values() if t["checksum"] == push1["checksum"])
        assert _writes_of(sims, _rows(t1["table_json"])) == 1
        # a retry is refused, and writes nothing
        with pytest.raises(ApiError) as err:
            daemon.client.request("POST", f"/campaigns/{first}/push")
        assert err.value.status == 409
        assert _writes_of(sims, _rows(t1["table_json"])) == 1
        # the pushed model is the approved one
        assert push1["model"] == "constant"
        done = [a for a in _audit(tmp_path) if a["action"] == "compensation.push"]
        assert len(done) == 1 and done[0]["detail"]["model_id"] == fits["constant"]["model_id"]
        assert done[0]["detail"]["reconciled_by"] == "daemon"

        # --- the audit log tells the whole story, in order ----------------------------------
        assert _story(tmp_path) == [
            "campaign.approve",
            "compensation.push-intended", "compensation.push-abandoned",
            "compensation.push-intended", "compensation.push",
        ]
    finally:
        daemon.stop()


@pytest.mark.slow
def test_kill9_after_a_completed_push_and_at_every_journaled_point_of_rollback(
        tmp_path, sims, monkeypatch):
    daemon, plan, originals = _cell(tmp_path, sims)
    try:
        first = _fitted(daemon, tmp_path, plan)
        second = _fitted(daemon, tmp_path, plan)
        daemon.client.request("POST", f"/campaigns/{first}/approve", {"model": "constant"})
        daemon.client.request("POST", f"/campaigns/{first}/push")
        wait_for(lambda: _state(daemon, first)["state"] == "pushed", 60, "first push done")
        push1 = _state(daemon, first)["push"]
        t1 = next(t for t in _tables(tmp_path).values() if t["checksum"] == push1["checksum"])
        assert _writes_of(sims, _rows(t1["table_json"])) == 1

        # --- second campaign: killed after the completing transaction -----------------------
        daemon.client.request("POST", f"/campaigns/{second}/approve")
        _crash(daemon, monkeypatch, "push:after-complete", "POST", f"/campaigns/{second}/push")
        st = _state(daemon, second)
        assert st["state"] == "pushed"
        t2 = next(t for t in _tables(tmp_path).values()
                  if t["checksum"] == st["push"]["checksum"])
        assert _writes_of(sims, _rows(t2["table_json"])) == 1
        assert _writes_of(sims, _rows(t1["table_json"])) == 1

        # --- rollback: killed before and after the controller write -------------------------
        _crash(daemon, monkeypatch, "rollback:after-intent", "POST", "/compensation/rollback")
        comp = daemon.client.request("GET", "/compensation")
        assert comp["active"]["checksum"] == st["push"]["checksum"]
        assert _writes_of(sims, _rows(t1["table_json"])) == 1
        _crash(daemon, monkeypatch, "rollback:after-write", "POST", "/compensation/rollback")
        comp = daemon.client.request("GET", "/compensation")
        assert comp["active"]["checksum"] == push1["checksum"]
        assert _writes_of(sims, _rows(t1["table_json"])) == 2  # the push and the restore
        # rollback after the first ever push: the controller's own registers come back
        comp = daemon.client.request("POST", "/compensation/rollback", {"reason": "done"})
        assert comp["active"]["origin"] == "controller"
        assert set(_rows(t1["table_json"])) <= set(originals)
        held = sims.registers()
        for n, v in originals.items():
            assert held[n] == pytest.approx(v, abs=1e-5), n

        # --- the audit log tells the whole story, in order ----------------------------------
        assert _story(tmp_path) == [
            "campaign.approve",
            "compensation.push-intended", "compensation.push",
            "campaign.approve",
            "compensation.push-intended", "compensation.push",
            "compensation.rollback-intended", "compensation.rollback-abandoned",
            "compensation.rollback-intended", "compensation.rollback",
            "compensation.rollback-intended", "compensation.rollback",
        ], _story(tmp_path)
    finally:
        daemon.stop()
