"""The report's own SVG plotter (ADR 0049): ticks, escaping, hostile data, every artist."""

from __future__ import annotations

import base64
import math
import re
from xml.etree import ElementTree

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.report._svg import Figure, esc, linear_ticks, log_ticks, viridis

NS = "{http://www.w3.org/2000/svg}"
finite = st.floats(-1e9, 1e9, allow_nan=False, allow_infinity=False)


def _parse(fig: Figure, title: str = "t") -> ElementTree.Element:
    return ElementTree.fromstring(fig.svg(title))


@settings(max_examples=300, deadline=None)
@given(finite, st.floats(1e-6, 1e9))
def test_linear_ticks_are_nice_and_inside(lo: float, span: float) -> None:
    hi = lo + span
    if hi - lo < 1e-9 * max(1.0, abs(lo)):  # below float resolution at this magnitude
        return
    ticks, labels = linear_ticks(lo, hi)
    assert 2 <= ticks.size <= 7 and len(labels) == ticks.size
    assert np.all(ticks >= lo - 1e-9 * span) and np.all(ticks <= hi + 1e-9 * span)
    step = float(np.diff(ticks).mean())
    mant = step / 10.0 ** math.floor(math.log10(step) + 1e-12)
    assert any(abs(mant - m) < 1e-6 for m in (1.0, 2.0, 2.5, 5.0, 10.0))
    assert len(set(labels)) == len(labels)  # enough decimals to tell them apart


def test_linear_tick_labels_read_like_numbers() -> None:
    assert linear_ticks(-0.07, 0.07)[1] == ["\u22120.050", "\u22120.025", "0.000", "0.025",
                                            "0.050"]
    assert linear_ticks(0, 1000)[1] == ["0", "200", "400", "600", "800", "1000"]
    assert linear_ticks(0, 0.0125, 5)[1][:3] == ["0.0000", "0.0025", "0.0050"]


@settings(max_examples=300, deadline=None)
@given(st.floats(-12, 8), st.floats(0.05, 14))
def test_log_ticks_are_decades_or_1_2_5(a: float, decades: float) -> None:
    lo, hi = 10.0**a, 10.0 ** (a + decades)
    ticks, _ = log_ticks(lo, hi)
    assert np.all(ticks >= lo * (1 - 1e-9)) and np.all(ticks <= hi * (1 + 1e-9))
    mant = ticks / 10.0 ** np.floor(np.log10(ticks) + 1e-12)
    assert np.all(np.isclose(mant, 1) | np.isclose(mant, 2) | np.isclose(mant, 5))
    if decades >= 1.0:
        assert ticks.size >= 1
    if decades > 2.0:
        assert ticks.size <= 8 and np.allclose(mant, 1)


def test_no_ticks_for_an_empty_or_invalid_range() -> None:
    assert linear_ticks(1.0, 1.0)[0].size == 0
    assert linear_ticks(0.0, math.nan)[0].size == 0
    assert log_ticks(0.0, 1.0)[0].size == 0


@settings(max_examples=100, deadline=None)
@given(st.text(max_size=40))
def test_hostile_labels_stay_text(label: str) -> None:
    label = "".join(c for c in label if c.isprintable())  # XML 1.0 has no control characters
    fig = Figure(4, 3, (0.6, 0.1, 0.5, 0.3))
    ax = fig.add_subplot()
    ax.plot([0, 1], [0, 1], color="#123456", label=label or "x")
    ax.set_title(label)
    ax.set_xlabel(label)
    ax.set_yticks([0.5], [label])
    ax.text(0.5, 0.5, label, axes_coords=True)
    ax.legend("best")
    root = _parse(fig, label)
    texts = [t.text or "" for t in root.iter(f"{NS}text")]
    assert texts.count(label) >= (4 if label else 0)
    assert root.findtext(f"{NS}title") == (label or None)


def test_non_finite_and_empty_series_are_skipped() -> None:
    fig = Figure(6, 3, (0.6, 0.1, 0.5, 0.3))
    ax, bx = fig.subplots(1, 2)[0]
    ax.plot([0, 1, 2, 3], [1, math.nan, math.inf, 2], color="#000", marker="o", label="a")
    ax.plot([], [], color="#f00", label="empty")
    ax.hist(np.array([math.nan, 1.0, 2.0]), bins=4, color="#00f")
    bx.set_yscale("log")
    bx.plot([1, 2, 3], [0.0, -1.0, 1e-3], color="#000", marker="s")  # <= 0 on a log axis
    bx.bar([0, 1], [0.0, 2.0], color="#0f0")
    root = _parse(fig)
    d = " ".join(p.get("d", "") for p in root.iter(f"{NS}path"))
    assert "nan" not in d and "inf" not in d
    assert len(root.findall(f"{NS}g")) == 2  # one group per axes


def test_bars_lines_spans_and_colour_bar_draw_where_the_data_is() -> None:
    fig = Figure(5, 3, (0.6, 0.1, 0.5, 0.3))
    ax = fig.add_subplot()
    ax.bar([0.0, 1.0], [1.0, 3.0], 0.5, color="#0f0", label="bars")
    ax.axhline(2.0, color="#f00", dash="4 3", label="limit")
    ax.axvspan(0.0, 0.5, color="#000", alpha=0.06)
    ax.fill_between([0, 1], [0, 1], [1, 2], color="#00f")
    ax.scatter_colored([0, 1], [1, 2], [0.1, 0.9], vmin=0.0, vmax=1.0)
    fig.colorbar(ax, 0.0, 1.0, "1σ (mm)")
    ax.legend("above", ncol=2)
    svg = fig.svg("x")
    root = ElementTree.fromstring(svg)
    bars = [p for p in root.iter(f"{NS}path") if p.get("fill") == "#0f0"]
    assert len(bars) == 1 and bars[0].get("d", "").count("z") == 2
    # the y axis starts at the bars' base (no margin below 0); the tallest bar sets the top
    _, y0, _, h = ax.box
    rects = [re.match(r"M([-\d.]+),([-\d.]+)h([-\d.]+)v([-\d.]+)", r + "") for r in
             bars[0].get("d", "").split("z") if r]
    tops = [float(m.group(2)) for m in rects if m]
    bottoms = [float(m.group(2)) + float(m.group(4)) for m in rects if m]
    assert bottoms == pytest.approx([y0 + h] * 2, abs=0.11)
    assert y0 < min(tops) < y0 + 0.1 * h
    assert {t.text for t in root.iter(f"{NS}text")} >= {"bars", "limit", "1σ (mm)"}
    assert 'fill="url(#cmap)"' in svg
    assert viridis([0.0, 1.0]) == ["#440154", "#fde725"]


def test_data_uri_is_the_svg_in_base64() -> None:
    fig = Figure(3, 2, (0.5, 0.1, 0.4, 0.2))
    fig.add_subplot().plot([0, 1], [0, 1], color="#000")
    uri = fig.data_uri("alt & <text>")
    head, b64 = uri.split(",", 1)
    assert head == "data:image/svg+xml;base64"
    assert base64.b64decode(b64).decode() == fig.svg("alt & <text>")
    assert esc('a<b>&"c') == "a&lt;b&gt;&amp;&quot;c"


def test_unknown_marker_is_refused() -> None:
    fig = Figure(3, 2, (0.5, 0.1, 0.4, 0.2))
    fig.add_subplot().plot([0], [0], color="#000", marker="?")
    with pytest.raises(ValueError, match="marker"):
        fig.svg()
