"""The report's SVG plotting module: ticks, escaping, odd data, well-formed output."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from robocal.report._svg import Figure, log_ticks, nice_ticks, tick_labels, viridis
from tests.unit.report.svgdoc import NS, figures, texts, title


def _mantissa(v: float) -> float:
    return v / 10.0 ** math.floor(math.log10(v) + 1e-9)


@settings(max_examples=300, deadline=None)
@given(lo=st.floats(-1e6, 1e6), span=st.floats(1e-6, 1e7))
def test_linear_ticks_are_few_nice_and_inside(lo: float, span: float) -> None:
    hi = lo + span
    if hi - lo < 1e-7 * max(1.0, abs(lo)):  # below float resolution of the range
        return
    t = nice_ticks(lo, hi)
    assert 3 <= t.size <= 8
    tol = 1e-9 * (hi - lo)
    assert np.all(t >= lo - tol) and np.all(t <= hi + tol)
    steps = np.diff(t)
    assert np.allclose(steps, steps[0], rtol=1e-6)
    assert any(math.isclose(_mantissa(steps[0]), m, rel_tol=1e-6) for m in (1, 2, 5, 10))


@settings(max_examples=300, deadline=None)
@given(a=st.floats(-9, 6), width=st.floats(0.02, 14))
@example(a=1e-07, width=2.75)   # 1 .. 562: nine 1-2-5 values, more than max_n
def test_log_ticks_are_decades_or_1_2_5_inside(a: float, width: float) -> None:
    lo, hi = 10.0 ** a, 10.0 ** (a + width)
    t = log_ticks(lo, hi)
    assert 3 <= t.size <= 8
    tol = 1e-9 * (hi - lo)
    assert np.all(t >= lo - tol) and np.all(t <= hi + tol) and np.all(np.diff(t) > 0)
    decades = math.floor(math.log10(hi) + 1e-9) - math.ceil(math.log10(lo) - 1e-9) + 1
    if decades >= 3:  # powers of ten only, evenly strided
        k = np.log10(t)
        assert np.allclose(k, np.rint(k)) and np.allclose(np.diff(k), np.diff(k)[0])
    elif t.size >= 3 and all(any(math.isclose(_mantissa(v), m, rel_tol=1e-6)
                                 for m in (1, 2, 5)) for v in t):
        pass  # 1-2-5 within the decades
    else:  # less than a decade without three 1-2-5 values: linear nice ticks
        assert np.allclose(np.diff(t), np.diff(t)[0], rtol=1e-6)


def test_tick_labels_are_compact_with_a_real_minus() -> None:
    assert tick_labels(np.array([-0.1, 0.0, 0.1, 0.2]), "linear") == ["−0.1", "0.0", "0.1",
                                                                      "0.2"]
    assert tick_labels(np.array([0.01, 0.1, 1.0, 10.0]), "log") == ["0.01", "0.1", "1", "10"]
    assert tick_labels(np.array([0.0, 50.0, 100.0]), "linear") == ["0", "50", "100"]


# every character class, including ones XML 1.0 forbids (they are dropped)
hostile = st.text(alphabet=st.characters(codec="utf-8"), max_size=40) | st.sampled_from(
    ['</text></svg><script>alert(1)</script>', '" onload="x', "&amp; &#0; ]]>", "\x00\x1b"])


def _norm(s: str) -> str:
    """What an XML parser reads back: forbidden characters gone, line ends normalised."""
    s = "".join(c for c in s if c in "\t\n\r" or (0x20 <= ord(c) < 0xD800)
                or (0xE000 <= ord(c) < 0xFFFE) or ord(c) > 0xFFFF)
    return s.replace("\r\n", "\n").replace("\r", "\n")


@settings(max_examples=150, deadline=None)
@given(label=hostile, alt=hostile, key=hostile)
def test_hostile_text_is_escaped(label: str, alt: str, key: str) -> None:
    fig = Figure(400, 300)
    (ax,) = fig.subplots(1, 1, (50, 10, 40, 40))
    ax.line([0, 1, 2], [1, 3, 2], "#123456", label=label)
    ax.markers([0.5], [2], "#654321", "s", label=label + "!")
    ax.set_xticks([0, 1, 2], [label, alt, "x"])
    ax.title, ax.xlabel, ax.ylabel = label, alt, label
    ax.text(1, 2, label)
    ax.legend("above", ncol=2)
    fig.colorbar(ax, 0.0, 1.0, label)
    (svg,) = figures(fig.svg(key, alt))
    assert title(svg) == _norm(alt)
    assert _norm(label) in texts(svg) and _norm(label) + "!" in texts(svg)
    assert svg.find(f"{NS}script") is None and svg.get("onload") is None


def test_non_finite_and_empty_series_are_skipped() -> None:
    fig = Figure(400, 300)
    a, b = fig.subplots(1, 2, (50, 10, 40, 40))
    nan, inf = math.nan, math.inf
    a.line([0, 1, 2, 3, 4], [1, 2, nan, 3, 4], "#f00", label="broken")
    a.markers([0, 1, inf, 3], [1, nan, 2, 3], "#0f0", label="dots")
    a.band([0, 1, 2], [0, nan, 0], [1, 1, 1], "#00f")
    a.line([], [], "#000", label="empty")
    a.rects([0, nan], [1, 2], [0, 0], [1, 1], "#888")
    a.hist([nan, inf], 10, "#888")
    a.step_hist([], [1, 2, 3], "#888")
    b.yscale = "log"
    b.line([1, 2, 3, 4], [-1, 0, 10, 100], "#f00")  # non-positive values cannot sit on log
    b.markers([nan], [nan], "#0f0")
    b.xlim = (nan, nan)  # ignored: autoscaled
    (svg,) = figures(fig.svg("odd", "odd data"))
    paths = [p.get("d") or "" for p in svg.iter(f"{NS}path")]
    assert not any("nan" in d.lower() or "inf" in d.lower() for d in paths)
    red = [p.get("d") or "" for p in svg.iter(f"{NS}path") if p.get("stroke") == "#f00"
           and p.get("fill") == "none"]
    assert red[0].count("M") == 2 and red[0].count("L") == 2  # broken at the NaN
    assert red[1].count("M") == 1 and red[1].count("L") == 1  # only 10 and 100 on log
    assert "broken" not in texts(svg)  # no legend asked for


def test_an_axes_without_data_still_draws() -> None:
    fig = Figure(300, 200)
    (ax,) = fig.subplots(1, 1, (40, 10, 30, 20))
    ax.note("nothing measured")
    ax.legend("best")  # no labelled series: no legend
    (svg,) = figures(fig.svg("empty", "empty"))
    assert "nothing measured" in texts(svg)


def test_markers_are_one_path_per_series_and_open() -> None:
    fig = Figure(400, 300)
    (ax,) = fig.subplots(1, 1, (50, 10, 40, 40))
    x = np.arange(500.0)
    ax.markers(x, np.sin(x), "#abcdef", "^", label="many")
    ax.legend("upper right")
    (svg,) = figures(fig.svg("m", "markers"))
    series = [p for p in svg.iter(f"{NS}path") if p.get("stroke") == "#abcdef"]
    assert len(series) == 2  # the series and its legend swatch
    assert (series[0].get("d") or "").count("M") == 500
    assert all(p.get("fill") == "none" for p in series)
    assert "many" in texts(svg)


def test_ids_are_prefixed_by_the_figure_key() -> None:
    fig = Figure(400, 300)
    a, b = fig.subplots(1, 2, (50, 60, 40, 40))
    a.barh([0, 1], 0, [1, 2], 0.4, ["#111", "#222"], hatch=True, label="hatched")
    fig.colorbar(b, 0, 1, "c")
    (svg,) = figures(fig.svg("a b/c", "ids"))
    ids = [e.get("id") for e in svg.iter() if e.get("id")]
    assert ids and len(ids) == len(set(ids)) and all(i.startswith("f-a_b_c-") for i in ids)


def test_log_axis_and_equal_aspect() -> None:
    fig = Figure(500, 300)
    a, b = fig.subplots(1, 2, (50, 10, 40, 40))
    a.yscale = "log"
    a.line([0, 1, 2], [0.001, 0.1, 10], "#000")
    b.markers([0, 100], [0, 10], "#000")
    b.equal = True
    (svg,) = figures(fig.svg("log", "log"))
    assert {"0.001", "0.01", "0.1", "1", "10"} <= set(texts(svg))
    b._prepare()
    assert b._xl[1] - b._xl[0] == pytest.approx((b._yl[1] - b._yl[0]) * b.width / b.height)


def test_viridis_ends() -> None:
    assert viridis([0.0, 1.0, 2.0, math.nan]) == ["#440154", "#fde725", "#fde725", "#440154"]


def _legend_box(svg: ET.Element) -> tuple[float, float, float, float]:
    """x0, y0, x1, y1 of the (only) inside legend's background box."""
    (r,) = [e for e in svg.iter(f"{NS}rect") if e.get("fill-opacity") == ".8"]
    x, y = float(r.get("x") or 0), float(r.get("y") or 0)
    return x, y, x + float(r.get("width") or 0), y + float(r.get("height") or 0)


def test_best_legend_avoids_lines_between_their_vertices() -> None:
    fig = Figure(400, 300)
    (ax,) = fig.subplots(1, 1, (50, 10, 40, 40))
    # two long segments along the top and the bottom: every corner box crosses one
    ax.line([0, 10], [10, 10], "#123456", label="top")
    ax.line([0, 10], [0, 0], "#654321", label="bottom")
    ax.legend("best")
    (svg,) = figures(fig.svg("best", "best"))
    _, y0, x1, y1 = _legend_box(svg)
    ax._prepare()
    top, bottom = ax.ty(np.array([10.0, 0.0])).tolist()
    assert top < y0 and y1 < bottom  # between the lines, not on them
    assert x1 > ax.left + ax.width - 10  # at the right (the first free place)


def test_y_ticks_keep_room_between_their_labels() -> None:
    fig = Figure(400, 280)
    (ax,) = fig.subplots(1, 1, (50, 10, 30, 44))  # 206 px tall, as the histograms
    ax.line([0, 1], [0, 73], "#000")
    (svg,) = figures(fig.svg("ticks", "ticks"))
    assert [t for t in texts(svg) if t in {"0", "10", "20", "40", "60", "70"}] == [
        "0", "20", "40", "60"]  # not 0, 10, ..., 70: labels 26 px apart, not 23
