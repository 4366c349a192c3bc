"""``robocal compensation list`` shows each push's predicted, nominal and measured residual."""

from __future__ import annotations

from tests.unit.daemon.conftest import base_config
from tests.unit.daemon.test_service import program_plan

from robocal.cli._controller_compensation import _print_state
from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService


async def test_list_prints_what_was_predicted_and_measured(tmp_path, capsys):
    cfg = base_config(tmp_path, limits={"max_joint_correction_deg": 5.0},
                      compensation={"verify_count": 3})
    svc = CalibrationService(parse_config(cfg, source="test"))
    await svc.start()
    try:
        st = await svc.create(program_plan(36, validation=6), actor="a")
        st = await svc.wait(st["id"], ["fitted"], timeout=60)
        await svc.approve(st["id"], actor="a")
        st = await svc.push(st["id"], actor="op")
        v = await svc.wait_verification(st["push"]["key"], timeout=60)
        assert v is not None and v["state"] == "done"
        out = svc.compensation()
    finally:
        await svc.stop()
    _print_state(out)
    text = capsys.readouterr().out
    push = next(h for h in out["history"] if h["action"] == "push")
    # the history row (the "active:" line above it names the push too)
    line = next(x for x in text.splitlines() if x.startswith("  ") and " push " in x)
    for value in (push["predicted_residual_mm"], push["nominal_residual_mm"],
                  v["before"]["rms_mm"], v["after"]["rms_mm"]):
        assert f"{value:.4f}" in line
    assert line.rstrip().endswith("op")
    assert "compensated program targets" in text
