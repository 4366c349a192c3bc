"""The report's Compensation section, added after a push has been measured again."""

from __future__ import annotations

import json

from robocal.report import add_compensation_section
from tests.unit.report.svgdoc import figures, texts


def _entry(after_rms: float) -> dict:
    return {
        "key": "k" * 32, "action": "push", "state": "completed", "actor": "alice",
        "at": "2026-11-23T21:00:00.000+00:00", "checksum": "ab" * 32, "kind": "targets",
        "purpose": "compensated program targets (the whole model, per target)",
        "predicted_residual_mm": 0.00002, "nominal_residual_mm": 1.0412,
        "model_accuracy_mm": 0.0128, "forced": False, "refusal": None, "warnings": [],
        "verification": {
            "state": "done", "before": {"n": 3, "rms_mm": 1.05},
            "after": {"n": 3, "rms_mm": after_rms},
            "per_target": [{"index": i, "before_mm": 1.0 + i / 10, "after_mm": after_rms}
                           for i in range(3)]},
    }


def test_section_is_added_once_and_replaced_with_the_measured_numbers(tmp_path):
    (tmp_path / "report.html").write_text(
        "<html><body><main><section id=\"verdict\">v</section></main><footer>f</footer>"
        "</body></html>")
    (tmp_path / "report.json").write_text(json.dumps({"format": "x", "verdict": "ok"}))
    add_compensation_section(tmp_path, [_entry(0.0123)])
    page = (tmp_path / "report.html").read_text()
    assert page.count('<section id="compensation">') == 1
    assert page.index('id="compensation"') < page.index("</main>")
    assert "0.0123" in page and "1.0500" in page and "1.0412" in page and "alice" in page
    (plot,) = figures(page)  # the before/after plot
    assert {"before (program targets)", "after (pushed values)",
            "position error, mm"} <= set(texts(plot))
    # the measured before -> after right under the verdict, not only at the end
    top = page[:page.index('id="compensation"')]
    assert page.index('<div id="push-result"') == page.index("</section>") + len("</section>")
    assert "measured 1.0500 mm before &rarr; 0.0123 mm after on 3 re-measured targets" in top
    add_compensation_section(tmp_path, [_entry(0.0111)])
    page = (tmp_path / "report.html").read_text()
    assert page.count('<section id="compensation">') == 1
    assert "0.0111" in page and "0.0123" not in page
    assert page.count('id="push-result"') == 1
    doc = json.loads((tmp_path / "report.json").read_text())
    assert doc["verdict"] == "ok"
    assert doc["compensation"][0]["verification"]["after"]["rms_mm"] == 0.0111


def test_forced_push_and_missing_measurement_are_stated(tmp_path):
    (tmp_path / "report.html").write_text("<html><body><main></main></body></html>")
    e = _entry(0.5)
    e.update(kind="frames", forced=True, refusal="frames table predicts 1.07 mm",
             verification={"state": "skipped", "reason": "a frames table changes the frames"})
    add_compensation_section(tmp_path, [e])
    page = (tmp_path / "report.html").read_text()
    assert "Pushed by force: frames table predicts 1.07 mm" in page
    assert "Not measured after the push: a frames table changes the frames" in page
    assert not (tmp_path / "report.json").exists()


def test_the_section_says_where_the_push_is_now_and_is_not_rewritten_when_it_agrees(tmp_path):
    """Approval, push key, measured before -> after and the table's state now (issue 32)."""
    (tmp_path / "report.html").write_text("<html><body><main></main></body></html>")
    (tmp_path / "report.json").write_text(json.dumps({"format": "x"}))
    approval = {"model": "auto", "actor": "bob", "at": "2026-11-23T20:50:00+00:00"}
    assert add_compensation_section(tmp_path, [], approval=approval)
    page = (tmp_path / "report.html").read_text()
    assert "Model auto approved by bob at 2026-11-23 20:50 UTC." in page
    assert "Not pushed to the controller yet." in page
    e = {**_entry(0.0123), "key": "3f2a9c1b7d04", "compensation_state": "superseded",
         "superseded_by": "9c1b7d043f2a", "rolled_back_by": None, "rolled_back_at": None}
    assert add_compensation_section(tmp_path, [e], approval=approval)
    page = (tmp_path / "report.html").read_text()
    assert ("Pushed as <b>push 3f2a9c1b7d04</b> by alice at 2026-11-23 21:00 UTC; measured "
            "1.0500 mm before -&gt; 0.0123 mm after (3 targets). Now: <b>superseded by push "
            "9c1b7d043f2a</b>.") in page
    assert "Not pushed" not in page
    assert not add_compensation_section(tmp_path, [e], approval=approval)  # already shown
    e.update(compensation_state="rolled back", superseded_by=None, rolled_back_by="r1b2c3d4",
             rolled_back_at="2026-11-23T21:30:00+00:00")
    assert add_compensation_section(tmp_path, [e], approval=approval)
    page = (tmp_path / "report.html").read_text()
    assert "Now: <b>rolled back at 2026-11-23 21:30 UTC by rollback r1b2c3d4</b>." in page
    assert page.count('<section id="compensation">') == 1
    doc = json.loads((tmp_path / "report.json").read_text())
    assert doc["approval"] == approval and doc["compensation"][0]["rolled_back_by"] == "r1b2c3d4"
