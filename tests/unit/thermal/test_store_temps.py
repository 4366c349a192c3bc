"""Joint temperatures in the store: kept per measurement, and a schema-1 store migrated."""

from __future__ import annotations

import sqlite3

import pytest

from robocal.daemon.schemas import Measurement
from robocal.daemon.store import SCHEMA_VERSION, PoseRow, Store, now_iso
from robocal.errors import ConfigError


def _row(idx: int, temps: tuple[float, ...] = ()) -> Measurement:
    return Measurement(pose_idx=idx, purpose="calibration", q_cmd_deg=(0.0,) * 6,
                          q_act_deg=(0.0,) * 6, p_mm=(1.0, 2.0, 3.0), sigma_mm=(0.01,) * 3,
                          rms_mm=0.001, samples=5, attempts=1, distance_mm=None,
                          weather={"temp_c": 20.5}, measured_at=now_iso(), temps_c=temps)


def _campaign(store: Store) -> str:
    poses = [PoseRow(i, "calibration", (float(i),) * 6) for i in range(3)]
    return store.create_campaign(name="t", robot="r", poses=poses, plan_json="{}",
                                 plan_digest="d", config_digest="c", actor="me").id


def test_temperatures_round_trip(tmp_path):
    store = Store(tmp_path / "db.sqlite3").open()
    try:
        cid = _campaign(store)
        temps = (31.5, 30.25, 29.0, 27.5, 26.0, 25.125)
        assert store.add_measurement(cid, _row(0, temps))
        assert store.add_measurement(cid, _row(1))
        rows = store.measurements(cid)
        assert rows[0].temps_c == temps and rows[0].weather == {"temp_c": 20.5}
        assert rows[1].temps_c == ()
        assert rows[0].model_dump(mode="json")["temps_c"] == list(temps)
    finally:
        store.close()


def _schema_1_file(path) -> str:
    """A store as schema 1 left it: no ``temps`` column, ``meta.schema`` = 1, one
    measurement."""
    store = Store(path).open()
    cid = _campaign(store)
    assert store.add_measurement(cid, _row(0))
    store.close()
    db = sqlite3.connect(path)
    db.execute("ALTER TABLE measurements DROP COLUMN temps")
    db.execute("UPDATE meta SET value='1' WHERE key='schema'")
    db.commit()
    db.close()
    return cid


def test_schema_1_store_is_migrated_and_keeps_its_measurements(tmp_path):
    path = tmp_path / "db.sqlite3"
    cid = _schema_1_file(path)
    store = Store(path).open()
    try:
        assert SCHEMA_VERSION == 2
        assert store.db.execute("SELECT value FROM meta WHERE key='schema'").fetchone()[0] == "2"
        (old,) = store.measurements(cid)
        assert old.temps_c == () and old.p_mm == (1.0, 2.0, 3.0)
        assert store.add_measurement(cid, _row(1, (25.0,) * 6))
        assert store.measurements(cid)[1].temps_c == (25.0,) * 6
    finally:
        store.close()
    again = Store(path).open()  # a migrated store opens as it is
    try:
        assert [m.pose_idx for m in again.measurements(cid)] == [0, 1]
    finally:
        again.close()


def test_unknown_schema_is_still_refused(tmp_path):
    path = tmp_path / "db.sqlite3"
    Store(path).open().close()
    db = sqlite3.connect(path)
    db.execute("UPDATE meta SET value='7' WHERE key='schema'")
    db.commit()
    db.close()
    with pytest.raises(ConfigError, match="schema 7"):
        Store(path).open()

