"""The SQLite store: durability settings, no duplicates, append-only audit, table stack."""

from __future__ import annotations

import json
import sqlite3

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.daemon.campaign import CampaignState
from robocal.daemon.schemas import Measurement
from robocal.daemon.store import PoseRow, Store, UnknownCampaign, now_iso
from robocal.errors import InvalidTransition


def _row(idx: int) -> Measurement:
    return Measurement(pose_idx=idx, purpose="calibration", q_cmd_deg=(0.0,) * 6,
                          q_act_deg=(0.0,) * 6, p_mm=(1.0, 2.0, 3.0), sigma_mm=(0.01,) * 3,
                          rms_mm=0.001, samples=5, attempts=1, distance_mm=None,
                          weather={"temp_c": 20.0}, measured_at=now_iso())


@pytest.fixture
def store(tmp_path):
    s = Store(tmp_path / "db.sqlite3").open()
    yield s
    s.close()


def _campaign(store: Store, n: int = 3):
    poses = [PoseRow(i, "calibration", (float(i),) * 6) for i in range(n)]
    poses.append(PoseRow(n, "via", (0.0,) * 6, measure=False))
    return store.create_campaign(name="t", robot="r", poses=poses, plan_json="{}",
                                 plan_digest="d", config_digest="c", actor="me")


def test_wal_and_full_sync(store):
    assert store.db.execute("PRAGMA journal_mode").fetchone()[0].lower() == "wal"
    assert store.db.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL


def test_only_measurements_commit_without_fsync(store):
    """A measurement commits at synchronous=NORMAL (1), every other write at FULL (2)."""
    seen: list[tuple[str, int]] = []

    def hook(stage: str) -> None:
        if stage == "commit":
            seen.append((stage, store.db.execute("PRAGMA synchronous").fetchone()[0]))

    rec = _campaign(store)
    store.fault_hook = hook
    store.transition(rec.id, CampaignState.RUNNING, actor="me")
    assert store.add_measurement(rec.id, _row(0))
    store.audit(actor="me", action="a", campaign=rec.id)
    assert store.add_measurement(rec.id, _row(1))
    store.transition(rec.id, CampaignState.PAUSED, actor="me")
    assert [level for _, level in seen] == [2, 1, 2, 1, 2]


def test_a_campaign_was_updated_when_its_last_measurement_was_taken(store):
    """A measurement's commit writes its row alone; the campaign still reports the time of
    its last measurement as its last update."""
    rec = _campaign(store)
    first = _row(0)
    assert store.add_measurement(rec.id, first)
    assert store.campaign(rec.id).updated == first.measured_at >= rec.updated
    later = _row(1).model_copy(update={"measured_at": "2999-01-01T00:00:00.000+00:00"})
    assert store.add_measurement(rec.id, later)
    assert store.campaign(rec.id).updated == later.measured_at
    assert [c.updated for c in store.campaigns()] == [later.measured_at]


def test_measurements_are_unique_per_pose(store):
    rec = _campaign(store)
    assert rec.poses_total == 3  # the via-point is not measured
    assert store.add_measurement(rec.id, _row(0))
    assert not store.add_measurement(rec.id, _row(0))
    assert store.campaign(rec.id).poses_measured == 1
    with pytest.raises(sqlite3.IntegrityError):
        store.db.execute(
            "INSERT INTO measurements(campaign, pose_idx, purpose, q_cmd_deg, q_act_deg, x_mm, "
            "y_mm, z_mm, samples, attempts, measured_at) VALUES(?,0,'c','[]','[]',0,0,0,1,1,'t')",
            (rec.id,))
    back = store.measurements(rec.id)[0]
    assert back.p_mm == (1.0, 2.0, 3.0) and back.weather == {"temp_c": 20.0}


def test_transitions_are_checked_and_recorded(store):
    rec = _campaign(store)
    store.transition(rec.id, CampaignState.RUNNING, actor="a", reason="go")
    with pytest.raises(InvalidTransition):
        store.transition(rec.id, CampaignState.PUSHED, actor="a")
    assert store.campaign(rec.id).state == CampaignState.RUNNING
    hist = store.transitions(rec.id)
    assert [h["to_state"] for h in hist] == ["created", "running"]
    with pytest.raises(UnknownCampaign):
        store.campaign("nope")


def test_audit_log_is_append_only(store):
    store.audit(actor="me", action="x", detail={"k": 1})
    with pytest.raises(sqlite3.DatabaseError, match="append-only"):
        store.db.execute("UPDATE audit SET actor='someone else'")
    with pytest.raises(sqlite3.DatabaseError, match="append-only"):
        store.db.execute("DELETE FROM audit")
    assert store.audit_log()[-1]["detail"] == {"k": 1}


def test_table_stack_push_and_rollback(store):
    ids = [store.add_table(campaign=None, origin="campaign", kind="frames", checksum=f"c{i}",
                           table_json="{}") for i in range(3)]
    for tid in ids:
        store.record_push(action="push", table_id=tid, campaign=None, actor="me",
                          checksum="c", detail={})
    assert store.table_stack() == ids
    store.record_push(action="rollback", table_id=ids[2], campaign=None, actor="me",
                      checksum="c", detail={})
    assert store.table_stack() == ids[:2]
    with pytest.raises(sqlite3.DatabaseError, match="append-only"):
        store.db.execute("DELETE FROM pushes")
    assert [a["action"] for a in store.audit_log()] == ["compensation.push"] * 3 + [
        "compensation.rollback"]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=8))
def test_float_lists_are_written_as_json_dumps_writes_them(values):
    from robocal.daemon.store import _floats_json

    assert _floats_json(values) == json.dumps(values)
    assert _floats_json(tuple(values)) == json.dumps(values)
