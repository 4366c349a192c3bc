"""With a site secret configured the daemon signs the models it stores and loads only signed
ones; a stored model edited with a recomputed public hash is refused (issue 25 item 4)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from robocal.daemon.service import CalibrationService
from robocal.errors import ConfigError
from robocal.kinematics._integrity import digests
from tests.unit.daemon.conftest import random_plan


async def test_models_are_signed_and_checked_with_the_site_secret(make_config, tmp_path: Path
                                                                  ) -> None:
    secret = tmp_path / "site.secret"
    secret.write_text("a-long-enough-site-secret\n")
    secret.chmod(0o600)
    svc = CalibrationService(make_config(site_secret_file=str(secret)))
    await svc.start()
    try:
        cid = (await svc.create(random_plan(12), actor="test"))["id"]
        st = await svc.wait(cid, ["fitted", "faulted"], timeout=60.0)
        assert st["state"] == "fitted", st["reason"]
        text = svc.store.model_json(cid, "constant")
        assert text is not None
        doc = json.loads(text)
        assert doc["integrity"]["hmac_sha256"]
        assert svc.fitted_model(cid, "constant").model_id == doc["model_id"]
        # edited in the store, the public hash recomputed: the signature gives it away
        doc["parameters"][0]["value"] += 0.5
        sha, _ = digests(doc)
        doc["model_id"], doc["integrity"]["sha256"] = sha[:16], sha
        svc.store.db.execute("UPDATE fits SET model_json=? WHERE campaign=? AND model=?",
                             (json.dumps(doc), cid, "constant"))
        with pytest.raises(ConfigError, match="site's secret"):
            svc.fitted_model(cid, "constant")
    finally:
        await svc.stop()


def test_a_readable_site_secret_is_refused(make_config, tmp_path: Path) -> None:
    secret = tmp_path / "site.secret"
    secret.write_text("a-long-enough-site-secret\n")
    secret.chmod(0o644)
    with pytest.raises(ConfigError, match="site secret file has mode 0644"):
        CalibrationService(make_config(site_secret_file=str(secret)))


def test_an_implausible_fitted_model_is_not_signed() -> None:
    from robocal.daemon.fitting import sign_fits
    from robocal.kinematics import CalibratedModel, ErrorModelSpec, KinematicModel, load_robot

    robot = load_robot("fanuc_lrmate200i")
    model = KinematicModel(robot, ErrorModelSpec.constant(robot.dof))
    good = CalibratedModel(model, model.nominal_params()).to_dict()
    bad = json.loads(json.dumps(good))
    bad["robot"]["joints"][1]["a_mm"] += 500.0
    sha, _ = digests(bad)
    bad["model_id"], bad["integrity"]["sha256"] = sha[:16], sha
    out = sign_fits({"a": ({"model": "a"}, json.dumps(good)),
                     "b": ({"model": "b"}, json.dumps(bad))}, b"a-long-enough-site-secret", robot)
    assert json.loads(out["a"][1] or "{}")["integrity"]["hmac_sha256"]
    assert out["b"][1] is None and "joints[2].a_mm" in out["b"][0]["error"]
