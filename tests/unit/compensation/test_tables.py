"""CompensationTable: validation, JSON round trip and checksum (hypothesis), offsets, diffs."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from robocal.compensation import (
    CompensationTable,
    Frame,
    FramesPayload,
    JointCorrection,
    TargetRow,
    diff_tables,
)
from robocal.errors import CompensationError, ConfigError

# within every bound a table enforces on load (angles +-360 deg, lengths +-1e5 mm)
finite = st.floats(allow_nan=False, allow_infinity=False, min_value=-300.0, max_value=300.0)
small_text = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=12)


@st.composite
def grids(draw: Any, n_min: int = 2) -> list[float]:
    pts = draw(st.lists(finite, min_size=n_min, max_size=12, unique=True))
    return sorted(pts)


@st.composite
def tables(draw: Any) -> CompensationTable:
    kind = draw(st.sampled_from(["targets", "joint", "frames"]))
    dof = draw(st.integers(1, 7))
    ranges = [tuple(sorted(draw(st.lists(finite, min_size=2, max_size=2)))) for _ in range(dof)]
    common: dict[str, Any] = {
        "model_id": draw(small_text), "robot": draw(small_text), "valid_range_deg": ranges,
        "predicted_residual_mm": draw(st.floats(0, 1e3)), "created": draw(small_text),
        "stats": draw(st.dictionaries(small_text, finite, max_size=3)),
    }
    if kind == "targets":
        rows = [TargetRow(index=i, q_deg=draw(st.lists(finite, min_size=dof, max_size=dof)),
                          status=draw(st.sampled_from(["ok", "not-converged", "out-of-limits",
                                                       "unreachable"])),
                          model_residual_mm=draw(st.floats(0, 10)))
                for i in range(draw(st.integers(0, 5)))]
        return CompensationTable(kind="targets", targets=rows, **common)
    if kind == "joint":
        entries = []
        for _ in range(draw(st.integers(0, 4))):
            g = draw(grids())
            entries.append(JointCorrection(
                joint=draw(st.integers(1, dof)), q_deg=g,
                dq_deg=draw(st.lists(finite, min_size=len(g), max_size=len(g))),
                interpolation_error_bound_deg=draw(st.floats(0, 1)),
                source_joint=draw(st.none() | st.integers(1, dof))))
        return CompensationTable(kind="joint", joints=entries, **common)
    frame = st.builds(Frame, x=finite, y=finite, z=finite, w=finite, p=finite, r=finite)
    return CompensationTable(kind="frames", frames=FramesPayload(base=draw(frame),
                                                                 tool=draw(frame)), **common)


@settings(max_examples=60, deadline=None)
@given(tables())
def test_json_round_trip_and_checksum(table: CompensationTable) -> None:
    sealed = table.sealed()
    sealed.verify()
    back = CompensationTable.model_validate_json(sealed.to_json())
    assert back == sealed
    back.verify()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "t.json"
        sealed.write(path)
        assert CompensationTable.read(path) == sealed
        assert sorted(p.name for p in Path(d).iterdir()) == ["t.json"]   # no temp file left


@settings(max_examples=60, deadline=None)
@given(tables(), st.floats(1e-6, 10.0))
def test_any_change_breaks_the_checksum(table: CompensationTable, delta: float) -> None:
    sealed = table.sealed()
    d = json.loads(sealed.to_json())
    d["predicted_residual_mm"] += delta
    tampered = CompensationTable.model_validate(d)
    with pytest.raises(CompensationError, match="checksum mismatch"):
        tampered.verify()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "t.json"
        path.write_text(json.dumps(d))
        with pytest.raises(ConfigError, match="checksum"):
            CompensationTable.read(path)


def _joint_table(**kw: Any) -> CompensationTable:
    entries = kw.pop("joints", [
        JointCorrection(joint=2, q_deg=[-90.0, 0.0, 90.0], dq_deg=[0.01, 0.02, 0.0],
                        interpolation_error_bound_deg=1e-4),
        JointCorrection(joint=3, q_deg=[-90.0, 90.0], dq_deg=[0.0, 0.04],
                        interpolation_error_bound_deg=1e-4, source_joint=2),
    ])
    fields: dict[str, Any] = {"kind": "joint", "model_id": "m", "robot": "r",
                              "valid_range_deg": [(-90.0, 90.0)] * 3,
                              "predicted_residual_mm": 0.1, "joints": entries}
    return CompensationTable(**{**fields, **kw})


def test_joint_offsets_sum_entries_and_hold_beyond_the_grid() -> None:
    t = _joint_table()
    q = np.array([[0.0, 45.0, 10.0], [0.0, 180.0, 10.0]])
    np.testing.assert_allclose(t.joint_offsets_deg(q), [[0.0, 0.01, 0.03], [0.0, 0.0, 0.04]])
    np.testing.assert_allclose(t.joint_offsets_deg(q[0]), [0.0, 0.01, 0.03])
    with pytest.raises(CompensationError, match="needs 3 joints"):
        t.joint_offsets_deg(np.zeros((1, 2)))
    frames = CompensationTable(kind="frames", model_id="m", robot="r", valid_range_deg=[],
                               predicted_residual_mm=0.0, frames=FramesPayload(
                                   base=Frame(x=0, y=0, z=0, w=0, p=0, r=0),
                                   tool=Frame(x=0, y=0, z=0, w=0, p=0, r=0)))
    with pytest.raises(CompensationError, match="no joint corrections"):
        frames.joint_offsets_deg(np.zeros(6))


@pytest.mark.parametrize(("change", "match"), [
    ({"kind": "targets"}, "needs the 'targets' payload"),
    ({"frames": FramesPayload(base=Frame(x=0, y=0, z=0, w=0, p=0, r=0),
                              tool=Frame(x=0, y=0, z=0, w=0, p=0, r=0))}, "carries only"),
    ({"valid_range_deg": [(1.0, -1.0)]}, "empty"),
    ({"predicted_residual_mm": float("nan")}, "finite"),
])
def test_table_validation(change: dict[str, Any], match: str) -> None:
    with pytest.raises(ValidationError, match=match):
        _joint_table(**change)


@pytest.mark.parametrize(("q", "dq", "match"), [
    ([0.0, 1.0], [0.0], "points"),
    ([0.0], [0.0], "at least 2"),
    ([0.0, 0.0], [0.0, 1.0], "increasing"),
    ([0.0, float("inf")], [0.0, 1.0], "finite"),
])
def test_grid_validation(q: list[float], dq: list[float], match: str) -> None:
    with pytest.raises(ValidationError, match=match):
        JointCorrection(joint=1, q_deg=q, dq_deg=dq, interpolation_error_bound_deg=0.0)


def test_target_rows_must_agree_on_joint_count() -> None:
    rows = [TargetRow(index=0, q_deg=[0.0] * 6, status="ok", model_residual_mm=0.0),
            TargetRow(index=1, q_deg=[0.0] * 5, status="ok", model_residual_mm=0.0)]
    with pytest.raises(ValidationError, match="joint counts"):
        CompensationTable(kind="targets", model_id="m", robot="r", valid_range_deg=[],
                          predicted_residual_mm=0.0, targets=rows)


def test_read_reports_bad_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        CompensationTable.read(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ConfigError, match=r"bad\.json"):
        CompensationTable.read(tmp_path / "bad.json")
    unsealed = json.loads(_joint_table().model_dump_json())
    (tmp_path / "unsealed.json").write_text(json.dumps(unsealed))
    with pytest.raises(ConfigError, match="no checksum"):
        CompensationTable.read(tmp_path / "unsealed.json")


def test_diff_tables() -> None:
    a = _joint_table().sealed()
    assert diff_tables(a, a).identical
    moved = a.model_copy(update={"joints": [
        a.joints[0].model_copy(update={"dq_deg": [0.01, 0.025, 0.0]}), a.joints[1]]})
    d = diff_tables(a, moved)
    assert not d.identical and d.max_joint_deg == pytest.approx(0.005)
    assert any("joint 2 (from joint 2)" in line for line in d.lines)
    dropped = a.model_copy(update={"joints": a.joints[:1]})
    assert any("only in a" in line for line in diff_tables(a, dropped).lines)

    def targets(q6: float, status: str = "ok") -> CompensationTable:
        rows = [TargetRow(index=0, q_deg=[1.0] * 6, status="ok", model_residual_mm=0.0),
                TargetRow(index=1, q_deg=[2.0] * 5 + [q6], status=status,
                          model_residual_mm=0.0)]
        return CompensationTable(kind="targets", model_id="m", robot="r", valid_range_deg=[],
                                 predicted_residual_mm=0.0, targets=rows)

    d = diff_tables(targets(2.0), targets(2.5))
    assert d.rows_changed == (1,) and d.max_joint_deg == pytest.approx(0.5)
    assert diff_tables(targets(2.0), targets(2.0, "not-converged")).rows_changed == (1,)

    def frames(x: float, r: float) -> CompensationTable:
        f = Frame(x=x, y=0, z=0, w=0, p=0, r=r)
        return CompensationTable(kind="frames", model_id="m", robot="r", valid_range_deg=[],
                                 predicted_residual_mm=0.0, frames=FramesPayload(base=f, tool=f))

    d = diff_tables(frames(0.0, 10.0), frames(1.5, 10.25))
    assert d.max_translation_mm == pytest.approx(1.5)
    assert d.max_rotation_deg == pytest.approx(0.25)
    other = diff_tables(a, frames(0.0, 0.0))
    assert not other.same_kind and "kind" in other.metadata


@settings(max_examples=60, deadline=None)
@given(tables(), tables())
def test_a_diff_is_empty_against_itself_and_symmetric(a: CompensationTable,
                                                      b: CompensationTable) -> None:
    """Property: a table agrees with itself; from a to b finds what b to a finds (the same
    largest changes, as many lines, the same rows)."""
    assert diff_tables(a, a).identical and diff_tables(b, b).identical
    ab, ba = diff_tables(a, b), diff_tables(b, a)
    assert ab.identical == ba.identical and len(ab.lines) == len(ba.lines)
    assert ab.same_kind == (a.kind == b.kind) and ab.metadata == ba.metadata
    assert (ab.max_joint_deg, ab.max_translation_mm, ab.max_rotation_deg) == pytest.approx(
        (ba.max_joint_deg, ba.max_translation_mm, ba.max_rotation_deg))
    assert sorted(ab.rows_changed) == sorted(ba.rows_changed)
