"""A push compensates for the joint temperatures the configuration asks for (ADR 0054): the
model's thermal term folded in at the robot's current temperatures or configured ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robocal.daemon.config import CompensationConfig
from robocal.errors import CompensationError
from robocal.identification import at_temperatures
from tests.unit.daemon.conftest import ROBOT, random_plan

pytestmark = pytest.mark.timeout(120)


class _Prog:
    measured = total = 1
    rate_per_min = eta_s = None
    retries = beam_losses = 0

# a small auto search (constant + first harmonics), enough for the thermal term to be tried
FAST = {"auto_maps": False, "auto_max_order": 1, "auto_ripple_orders": [],
        "auto_strain_wave": False, "auto_gravity": False}


async def _fitted(service, **compensation):
    """An approved campaign measured while the robot warmed (no warm-up routine), its model
    with a thermal term."""
    opts = {"robot": ROBOT, "scenario": "constant", "warmup_drift_mm": 0.1}
    svc = await service(robot={"options": opts}, tracker={"options": opts},
                        fit={"models": ["constant", "auto"], "select": "auto",
                             "options": FAST},
                        compensation={"verify_count": 0, **compensation})
    st = await svc.create(random_plan(160, seed=4, validation=20), actor="t")
    st = await svc.wait(st["id"], ["fitted", "faulted"], timeout=100)
    assert st["state"] == "fitted", st["reason"]
    await svc.approve(st["id"], actor="t")
    return svc, st["id"]


async def test_push_at_the_robots_current_temperatures(service):
    svc, cid = await _fitted(service, temperatures="current")
    rows = svc.store.measurements(cid)
    assert rows[-1].temps_c and max(rows[-1].temps_c) > min(rows[0].temps_c) + 1.0
    # the preview takes the campaign's last measured temperatures
    _, desc = svc.build_push_table(cid)
    t = desc["temperatures"]
    assert t["applied"] is True and t["mode"] == "current", t
    assert t["temps_c"] == list(rows[-1].temps_c) and "preview" in t["source"]
    # the model's reference is the mean temperature of the poses it was fitted on
    fitted_on = [r.temps_c for r in rows if r.purpose == "calibration"]
    assert t["reference_c"] == pytest.approx(np.mean(fitted_on, axis=0), abs=0.05)
    robot = await svc.hub.robot()
    robot.world.thermal.temps_c = np.asarray(rows[-1].temps_c) + 3.0  # type: ignore[attr-defined]
    now = (await robot.read_joint_temperatures()).temps_c  # type: ignore[attr-defined]
    st = await svc.push(cid, actor="t")
    assert st["state"] == "pushed"
    detail = svc.journal.entries()[-1].detail
    assert detail.temperatures["source"] == "read from the robot"
    assert detail.temperatures["temps_c"] == pytest.approx(list(now))
    assert detail.model_id == desc["model_id"]          # the approved model's id
    pushed = await robot.read_compensation()  # type: ignore[attr-defined]
    assert [pushed.stats[f"temp{j}_c"] for j in range(1, 7)] == pytest.approx(list(now))
    # the active table, the campaign's status and the station's page say what it is for
    temps_txt = ", ".join(f"{t:.1f}" for t in now)
    active = svc.compensation()["active"]
    assert active["purpose"].endswith(f", for joint temperatures {temps_txt} degC")
    st = svc.status(cid)
    assert st["push"]["temperatures_c"] == pytest.approx(list(now))
    from robocal.daemon.station import _pages
    from robocal.daemon.station._auth import Session

    html = _pages.campaign_live(
        st, session=Session(id="s", role="operator", name="t", peer="local"), steps=[],
        prog=_Prog(), fitting=False, fit_since=None,
        active_here=True, rolled_back=None, verify_count=0, models=[], has_report=False)
    temps = ", ".join(f"{t:.1f}" for t in now)
    assert f"compensated for joint temperatures {temps} °C" in html


async def test_configured_and_reference_temperatures(service):
    svc, cid = await _fitted(service, temperatures=[35.0] * 6)
    _, desc = svc.build_push_table(cid)
    assert desc["temperatures"]["temps_c"] == [35.0] * 6
    assert desc["temperatures"]["source"] == "compensation.temperatures"
    warm_targets = svc.build_push_table(cid)[0]
    # the same campaign at the reference temperatures: the model as fitted
    comp = svc.compensator
    comp.config = comp.config.model_copy(update={"compensation": CompensationConfig(
        verify_count=0, temperatures="reference")})
    ref_table, ref_desc = svc.build_push_table(cid)
    assert ref_desc["temperatures"]["applied"] is False
    assert ref_desc["temperatures"]["temps_c"] == ref_desc["temperatures"]["reference_c"]
    assert warm_targets.checksum != ref_table.checksum
    # a list of the wrong length is named, nothing built
    comp.config = comp.config.model_copy(update={"compensation": CompensationConfig(
        verify_count=0, temperatures=[30.0] * 5)})
    with pytest.raises(CompensationError, match=r"5 values; .* 6 joints"):
        svc.build_push_table(cid)
    # "current" when pushing without a reading (a driver that cannot read them) refuses
    comp.config = comp.config.model_copy(update={"compensation": CompensationConfig(
        verify_count=0, temperatures="current")})
    with pytest.raises(CompensationError, match="cannot be read"):
        svc.compensator.build_push_table(cid, pushing_now=True)


def test_temperatures_setting_is_checked():
    assert CompensationConfig().temperatures == "reference"
    assert CompensationConfig(temperatures=[30, 31, 32, 33, 34, 35]).temperatures[0] == 30.0
    for bad in ("warm", [], [float("nan")] * 6, [200.0] * 6):
        with pytest.raises(ValueError, match="temperatures"):
            CompensationConfig(temperatures=bad)


def test_a_model_without_a_thermal_term_is_left_alone():
    from robocal.identification import fit
    from robocal.simulation import VirtualCell

    cell = VirtualCell.create(ROBOT, "constant", seed=1)
    rng = np.random.default_rng(0)
    q, p, _, _ = cell.simulate(cell.random_joints(60, rng), rng)
    from robocal._core.measurements import MeasurementSet

    cal = fit(cell.robot, MeasurementSet(q, p), "constant").calibrated
    assert at_temperatures(cal, [30.0] * 6) is cal


async def test_a_failed_temperature_reading_writes_nothing(service):
    from robocal.errors import ConnectFailed, DriverError

    svc, cid = await _fitted(service, temperatures="current")
    robot = await svc.hub.robot()

    async def broken() -> None:
        raise DriverError("temperature read timed out")

    robot.read_joint_temperatures = broken  # type: ignore[method-assign]
    with pytest.raises(ConnectFailed, match="joint temperatures could not be read"):
        await svc.push(cid, actor="t")
    # nothing journaled, nothing written; the campaign can be pushed when the robot answers
    assert all(e.action != "push" for e in svc.journal.entries())
    assert svc.status(cid)["state"] == "approved"
    robot = await svc.hub.robot()          # the hub was reset: a new connection reads them
    assert robot.read_joint_temperatures is not broken
    st = await svc.push(cid, actor="t")
    assert st["state"] == "pushed" and st["push"]["temperatures_c"] is not None


def test_a_bad_temperatures_setting_is_one_error(tmp_path):
    from robocal.daemon.config import config_errors

    example = (Path(__file__).resolve().parents[3] / "deploy" / "config"
               / "robocal.example.toml").read_text()
    assert 'temperatures = "reference"' in example
    for bad in ('"hot"', '[30, 31, "warm"]', "[]", "[30, 300]"):
        path = tmp_path / "robocal.toml"
        path.write_text(example.replace('temperatures = "reference"', f"temperatures = {bad}"))
        errors = config_errors(path)
        assert len(errors) == 1 and "compensation.temperatures" in errors[0], errors
        assert 'must be "reference", "current" or a list of joint temperatures' in errors[0]
