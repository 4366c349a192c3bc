"""A small plotting module that writes SVG (ADR 0049): the report's figures, drawn by robocal.

Just what the report needs: axes with "nice" linear ticks (1-2-5 steps) and log ticks
(decades, or 1-2-5 per decade when few decades show), a grid, lines, open markers, bands,
bars, shaded spans, horizontal/vertical rules, text, legends, titles, axis labels, subplot
grids and a colour bar. Text is SVG ``<text>`` (the browser lays it out, so there is no glyph
cost here); every string is XML-escaped. Coordinates are transformed with numpy and each
series becomes one ``<path>`` (markers are relative sub-paths of it), so a figure costs a few
string joins. Non-finite values (and non-positive ones on a log axis) are skipped.

Sizes are CSS pixels (96 per inch); numbers are written with one decimal.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
Scale = Literal["linear", "log"]
LegendLoc = Literal["above", "below", "best", "upper right", "upper left", "lower left",
                    "lower right", "center right", "center left", "upper center",
                    "lower center"]
# the inside places "best" chooses from, in order of preference on a tie
_INSIDE: tuple[LegendLoc, ...] = ("upper right", "upper left", "lower left", "lower right",
                                  "center right", "center left", "upper center",
                                  "lower center")
PX = 96.0  # pixels per inch
TICK_FONT = 10.5
LABEL_FONT = 11.5
TITLE_FONT = 12.5
LEGEND_FONT = 10.0
_CHAR = 0.58  # average glyph width / font size of the sans-serif fonts browsers pick
TAB10 = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
         "#7f7f7f", "#bcbd22", "#17becf")
# viridis at 0, 0.1, ..., 1 (the published 11-step table)
_VIRIDIS = ("#440154", "#482475", "#414487", "#355f8d", "#2a788e", "#21918c", "#22a884",
            "#44bf70", "#7ad151", "#bddf26", "#fde725")
# Marker outlines, relative to the point, for a marker of radius 1 (scaled per series).
# Closed shapes are drawn open (no fill) so that overlapping points stay visible.
_SHAPES: dict[str, tuple[tuple[tuple[str, tuple[float, ...]], ...], bool]] = {
    "s": ((("m", (-0.85, -0.85)), ("h", (1.7,)), ("v", (1.7,)), ("h", (-1.7,)),
           ("z", ())), True),
    "^": ((("m", (0, -1.1)), ("l", (0.95, 1.65, -1.9, 0)), ("z", ())), True),
    "v": ((("m", (0, 1.1)), ("l", (0.95, -1.65, -1.9, 0)), ("z", ())), True),
    "<": ((("m", (-1.1, 0)), ("l", (1.65, 0.95, 0, -1.9)), ("z", ())), True),
    ">": ((("m", (1.1, 0)), ("l", (-1.65, 0.95, 0, -1.9)), ("z", ())), True),
    "D": ((("m", (0, -1.1)), ("l", (1.1, 1.1, -1.1, 1.1, -1.1, -1.1)), ("z", ())), True),
    "h": ((("m", (0, -1)), ("l", (0.87, 0.5, 0, 1, -0.87, 0.5, -0.87, -0.5, 0, -1)),
           ("z", ())), True),
    "x": ((("m", (-0.8, -0.8)), ("l", (1.6, 1.6)), ("m", (0, -1.6)), ("l", (-1.6, 1.6))),
          False),
    "+": ((("m", (-1, 0)), ("h", (2,)), ("m", (-1, -1)), ("v", (2,))), False),
    "P": ((("m", (-1, 0)), ("h", (2,)), ("m", (-1, -1)), ("v", (2,))), False),
    "*": ((("m", (-1, 0)), ("h", (2,)), ("m", (-1.5, -0.87)), ("l", (1, 1.73)),
           ("m", (0, -1.73)), ("l", (-1, 1.73))), False),
    "|": ((("m", (0, -1)), ("v", (2,))), False),
}
_BAD_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")
_ID = re.compile(r"[^A-Za-z0-9_-]")
_UID = "\x00"  # stands for the figure's id prefix until it is known (esc drops it from text)


def esc(text: object) -> str:
    """``text`` safe inside XML text and double-quoted attributes (characters XML forbids
    are dropped)."""
    t = _BAD_XML.sub("", str(text))
    return t.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace(
        '"', "&quot;")


def text_width(text: str, size: float) -> float:
    """Estimated width (px) of ``text`` at font ``size`` px (no font metrics: an average)."""
    return len(text) * size * _CHAR


def nice_ticks(lo: float, hi: float, max_n: int = 8) -> Array:
    """3..``max_n`` ticks inside [lo, hi] at multiples of a 1-2-5 step (``lo < hi``)."""
    span = hi - lo
    if not (math.isfinite(span) and span > 0):
        return np.array([lo]) if math.isfinite(lo) else np.array([])
    base = 10.0 ** math.floor(math.log10(span)) / 100
    eps = 1e-9
    while True:
        for m in (1.0, 2.0, 5.0):
            step = m * base
            k0, k1 = math.ceil(lo / step - eps), math.floor(hi / step + eps)
            if k1 - k0 + 1 <= max_n:
                t = np.arange(k0, k1 + 1, dtype=float) * step
                t[np.abs(t) < step * 1e-6] = 0.0
                return t
        base *= 10


def log_ticks(lo: float, hi: float, max_n: int = 8) -> Array:
    """Ticks of a log axis on [lo, hi] (``0 < lo < hi``): decades (every n-th when more than
    ``max_n``); with fewer than 3 decades inside, 1, 2 and 5 times each decade (1 and 5, or
    1, when those are more than ``max_n``); with fewer than 3 of those, :func:`nice_ticks`."""
    a, b = math.log10(lo), math.log10(hi)
    k0, k1 = math.ceil(a - 1e-9), math.floor(b + 1e-9)
    n = k1 - k0 + 1
    if n >= 3:
        stride = -(-n // max_n)
        return 10.0 ** np.arange(k0, k1 + 1, stride, dtype=float)
    tol = (hi - lo) * 1e-9
    # just under three decades, 1-2-5 gives up to 9 values: then 1 and 5, then 1 alone
    for mantissas in ((1.0, 2.0, 5.0), (1.0, 5.0), (1.0,)):
        c = (np.array(mantissas) * 10.0 ** np.arange(k0 - 1, k1 + 1)[:, None]).ravel()
        c = c[(c >= lo - tol) & (c <= hi + tol)]
        if c.size <= max_n:
            break
    return c if 3 <= c.size <= max_n else nice_ticks(lo, hi, max_n)


def tick_labels(ticks: Array, scale: Scale) -> list[str]:
    """Compact labels: ``%g`` on a log axis, on a linear one as many decimals as the step
    needs; a real minus sign."""
    if scale == "log" or ticks.size < 2:
        out = [f"{v:g}" for v in ticks.tolist()]
    else:
        step = float(np.min(np.diff(ticks)))
        big = float(np.max(np.abs(ticks)))
        if big >= 1e6 or step < 1e-4:
            out = [f"{v:g}" for v in ticks.tolist()]
        else:
            d = max(0, -math.floor(math.log10(step) + 1e-9))
            out = [f"{v + 0.0:.{d}f}" for v in ticks.tolist()]
    return [s.replace("-", "−") for s in out]


def viridis(t: ArrayLike) -> list[str]:
    """Colours of the viridis map at ``t`` in [0, 1] (clipped), interpolated in sRGB."""
    v = np.clip(np.nan_to_num(np.asarray(t, dtype=float), nan=0.0), 0, 1) * (len(_VIRIDIS) - 1)
    rgb = np.array([[int(h[i:i + 2], 16) for i in (1, 3, 5)] for h in _VIRIDIS], dtype=float)
    i = np.minimum(v.astype(int), len(_VIRIDIS) - 2)
    f = (v - i)[..., None]
    c = np.rint(rgb[i] * (1 - f) + rgb[i + 1] * f).astype(int)
    return [f"#{r:02x}{g:02x}{b:02x}" for r, g, b in c.reshape(-1, 3).tolist()]


def _num(v: float) -> str:
    s = f"{v:.1f}"
    return s[:-2] if s.endswith(".0") else s


def _pairs(cmd: NDArray[np.str_] | str, x: Array, y: Array) -> str:
    """``cmd[i] x[i] y[i]`` joined, one decimal (the one loop per series)."""
    if isinstance(cmd, str):
        return "".join(f"{cmd}{a:.1f} {b:.1f}" for a, b in zip(x.tolist(), y.tolist(),
                                                               strict=True))
    return "".join(f"{c}{a:.1f} {b:.1f}" for c, a, b in zip(cmd.tolist(), x.tolist(),
                                                            y.tolist(), strict=True))


def _shape(mk: str, r: float) -> tuple[str, bool]:
    """The relative path of marker ``mk`` at radius ``r`` px and whether it is closed."""
    if mk in ("o", "."):
        return (f"m{-r:.1f} 0a{r:.1f} {r:.1f} 0 1 0 {2 * r:.1f} 0"
                f"a{r:.1f} {r:.1f} 0 1 0 {-2 * r:.1f} 0"), True
    parts, closed = _SHAPES.get(mk, _SHAPES["s"])
    return "".join(c + " ".join(_num(v * r) for v in vals) for c, vals in parts), closed


def _dash(style: str | None) -> str:
    return {"--": ' stroke-dasharray="5 3"', ":": ' stroke-dasharray="1.5 2.5"'}.get(
        style or "", "")


@dataclass
class _Item:
    kind: str
    x: Array
    y: Array
    x2: Array | None = None
    y2: Array | None = None
    color: str | list[str] = "#000"
    alpha: float = 1.0
    width: float = 1.2
    dash: str | None = None
    marker: str | None = None
    size: float = 3.0
    filled: bool = False
    hatch: bool = False
    label: str | None = None
    text: str = ""
    anchor: str = "start"
    sticky: str = ""  # "x"/"y": bars standing on zero along that axis


def _arr(v: ArrayLike) -> Array:
    return np.atleast_1d(np.asarray(v, dtype=float))


@dataclass
class Axes:
    """One plotting area at (left, top, width, height) px in its figure."""

    left: float
    top: float
    width: float
    height: float
    xscale: Scale = "linear"
    yscale: Scale = "linear"
    title: str = ""
    xlabel: str = ""
    ylabel: str = ""
    title_size: float = TITLE_FONT
    items: list[_Item] = field(default_factory=list)
    xlim: tuple[float, float] | None = None
    ylim: tuple[float, float] | None = None
    xticks: tuple[Array, list[str]] | None = None
    yticks: tuple[Array, list[str]] | None = None
    y_inverted: bool = False
    equal: bool = False
    legend_spec: tuple[LegendLoc, int, float] | None = None
    message: str = ""
    _xl: tuple[float, float] = field(default=(0.0, 1.0), init=False)
    _yl: tuple[float, float] = field(default=(0.0, 1.0), init=False)

    # --- drawing -------------------------------------------------------------------------
    def line(self, x: ArrayLike, y: ArrayLike, color: str, *, width: float = 1.2,
             dash: str | None = None, marker: str | None = None, size: float = 3.0,
             alpha: float = 1.0, label: str | None = None) -> None:
        """A polyline (broken at non-finite points), optionally with markers."""
        self.items.append(_Item("line", _arr(x), _arr(y), color=color, width=width,
                                dash=dash, marker=marker, size=size, alpha=alpha,
                                label=label, filled=marker == "."))

    def markers(self, x: ArrayLike, y: ArrayLike, color: str, marker: str = "o", *,
                size: float = 3.0, width: float = 1.0, alpha: float = 1.0,
                filled: bool = False, label: str | None = None) -> None:
        """Markers of radius ``size`` px, open unless ``filled``."""
        self.items.append(_Item("markers", _arr(x), _arr(y), color=color, marker=marker,
                                size=size, width=width, alpha=alpha, filled=filled,
                                label=label))

    def band(self, x: ArrayLike, lo: ArrayLike, hi: ArrayLike, color: str, *,
             alpha: float = 0.18) -> None:
        """The area between ``lo`` and ``hi`` along ``x`` (non-finite points dropped)."""
        self.items.append(_Item("band", _arr(x), _arr(lo), y2=_arr(hi), color=color,
                                alpha=alpha))

    def rects(self, x0: ArrayLike, x1: ArrayLike, y0: ArrayLike, y1: ArrayLike,
              color: str | Sequence[str], *, alpha: float = 1.0, hatch: bool = False,
              label: str | None = None, sticky: str = "") -> None:
        """Filled rectangles [x0, x1] x [y0, y1] (bars), one colour or one per rectangle."""
        x0a, x1a, y0a, y1a = np.broadcast_arrays(_arr(x0), _arr(x1), _arr(y0), _arr(y1))
        self.items.append(_Item("rects", x0a.astype(float), y0a.astype(float),
                                x2=x1a.astype(float), y2=y1a.astype(float),
                                color=color if isinstance(color, str) else list(color),
                                alpha=alpha, hatch=hatch, label=label, sticky=sticky))

    def bar(self, x: ArrayLike, height: ArrayLike, width: float, color: str | Sequence[str],
            *, bottom: float = 0.0, alpha: float = 1.0, label: str | None = None) -> None:
        """Vertical bars centred on ``x``."""
        xa = _arr(x)
        self.rects(xa - width / 2, xa + width / 2, bottom, height, color, alpha=alpha,
                   label=label, sticky="y")

    def barh(self, y: ArrayLike, left: ArrayLike, right: ArrayLike, height: float,
             color: str | Sequence[str], *, alpha: float = 1.0, hatch: bool = False,
             label: str | None = None) -> None:
        """Horizontal bars centred on ``y`` from ``left`` to ``right``."""
        ya = _arr(y)
        self.rects(left, right, ya - height / 2, ya + height / 2, color, alpha=alpha,
                   hatch=hatch, label=label, sticky="x")

    def step_hist(self, data: ArrayLike, bins: ArrayLike, color: str, *, width: float = 1.5,
                  label: str | None = None) -> None:
        """The outline of the histogram of the finite ``data`` over the ``bins`` edges."""
        d = _arr(data)
        edges = _arr(bins)
        counts = np.histogram(d[np.isfinite(d)], bins=edges)[0].astype(float)
        x = np.repeat(edges, 2)
        y = np.concatenate([[0.0], np.repeat(counts, 2), [0.0]])
        self.line(x, y, color, width=width, label=label)
        self.items[-1].kind = "stairs"
        self.items[-1].sticky = "y"

    def hist(self, data: ArrayLike, bins: int, color: str, *, alpha: float = 0.8) -> None:
        """A filled histogram of the finite ``data`` in ``bins`` equal bins."""
        d = _arr(data)
        d = d[np.isfinite(d)]
        if not d.size:
            return
        counts, edges = np.histogram(d, bins=bins)
        self.rects(edges[:-1], edges[1:], 0.0, counts.astype(float), color, alpha=alpha,
                   sticky="y")

    def vspan(self, a: float, b: float, color: str = "#000", alpha: float = 0.06) -> None:
        """A shaded band over the full height between x = a and x = b."""
        self.items.append(_Item("vspan", _arr([a, b]), np.array([]), color=color,
                                alpha=alpha))

    def hline(self, y: float, color: str, *, width: float = 0.8, dash: str | None = None,
              label: str | None = None) -> None:
        """A horizontal rule across the axes at ``y``."""
        self.items.append(_Item("hline", np.array([]), _arr([y]), color=color, width=width,
                                dash=dash, label=label))

    def vline(self, x: float, color: str, *, width: float = 0.8, dash: str | None = None,
              label: str | None = None) -> None:
        """A vertical rule across the axes at ``x``."""
        self.items.append(_Item("vline", _arr([x]), np.array([]), color=color, width=width,
                                dash=dash, label=label))

    def text(self, x: float, y: float, text: str, *, size: float = 10.0,
             anchor: str = "start", color: str = "#222") -> None:
        """``text`` at data point (x, y), vertically centred."""
        self.items.append(_Item("text", _arr([x]), _arr([y]), text=text, size=size,
                                anchor=anchor, color=color))

    def set_xticks(self, ticks: ArrayLike, labels: Sequence[str]) -> None:
        """Fixed x ticks with their labels (categories)."""
        self.xticks = (_arr(ticks), list(labels))

    def set_yticks(self, ticks: ArrayLike, labels: Sequence[str]) -> None:
        """Fixed y ticks with their labels (categories)."""
        self.yticks = (_arr(ticks), list(labels))

    def legend(self, loc: LegendLoc = "upper right", ncol: int = 1,
               size: float = LEGEND_FONT) -> None:
        """A legend of the labelled series, placed at ``loc``."""
        self.legend_spec = (loc, max(1, ncol), size)

    def note(self, text: str) -> None:
        """A grey message in the middle of the axes (e.g. nothing to show)."""
        self.message = text

    # --- limits and transforms -------------------------------------------------------------
    def _extent(self, axis: str) -> Array:
        parts = []
        for it in self.items:
            if it.kind == "text":
                continue
            a, b = (it.x, it.x2) if axis == "x" else (it.y, it.y2)
            parts.append(a)
            if b is not None:
                parts.append(b)
        v = np.concatenate(parts) if parts else np.array([])
        scale = self.xscale if axis == "x" else self.yscale
        return v[np.isfinite(v) & (v > 0)] if scale == "log" else v[np.isfinite(v)]

    def _limits(self, axis: str) -> tuple[float, float]:
        fixed = self.xlim if axis == "x" else self.ylim
        scale = self.xscale if axis == "x" else self.yscale
        v = self._extent(axis)
        if fixed is not None and all(math.isfinite(f) for f in fixed) and fixed[0] != fixed[1]:
            lo, hi = sorted(fixed)
            if scale == "log" and lo <= 0:
                lo = float(v.min()) if v.size else hi / 10
            return lo, hi
        if not v.size:
            return (1.0, 10.0) if scale == "log" else (0.0, 1.0)
        lo, hi = float(v.min()), float(v.max())
        if scale == "log":
            a, b = math.log10(lo), math.log10(hi)
            pad = 0.05 * (b - a) if b > a else 0.5
            return 10 ** (a - pad), 10 ** (b + pad)
        if hi == lo:
            d = abs(lo) * 0.1 or 1.0
            return lo - d, hi + d
        pad = 0.05 * (hi - lo)
        # bars standing on zero keep zero as the edge (no margin below the baseline)
        zero = any(it.sticky == axis for it in self.items)
        return (0.0 if zero and lo >= 0 else lo - pad,
                0.0 if zero and hi <= 0 else hi + pad)

    def _prepare(self) -> None:
        self._xl = self._limits("x")
        self._yl = self._limits("y")
        if self.equal and self.xscale == self.yscale == "linear":
            ux = (self._xl[1] - self._xl[0]) / self.width
            uy = (self._yl[1] - self._yl[0]) / self.height
            if ux > uy:
                c, h = sum(self._yl) / 2, ux * self.height / 2
                self._yl = (c - h, c + h)
            else:
                c, h = sum(self._xl) / 2, uy * self.width / 2
                self._xl = (c - h, c + h)

    @staticmethod
    def _map(v: Array, lim: tuple[float, float], scale: Scale, p0: float, size: float) -> Array:
        if scale == "log":
            with np.errstate(divide="ignore", invalid="ignore"):
                v = np.where(v > 0, np.log10(np.where(v > 0, v, 1.0)), np.nan)
            a, b = math.log10(lim[0]), math.log10(lim[1])
        else:
            a, b = lim
        return p0 + (v - a) * (size / (b - a))

    def tx(self, x: Array) -> Array:
        """Data x -> pixel x."""
        return self._map(x, self._xl, self.xscale, self.left, self.width)

    def ty(self, y: Array) -> Array:
        """Data y -> pixel y (up unless inverted)."""
        if self.y_inverted:
            return self._map(y, self._yl, self.yscale, self.top, self.height)
        return self._map(y, self._yl, self.yscale, self.top + self.height, -self.height)

    def _ticks(self, axis: str) -> tuple[Array, list[str]]:
        fixed = self.xticks if axis == "x" else self.yticks
        lim = self._xl if axis == "x" else self._yl
        if fixed is not None:
            t, lab = fixed
            ok = (t >= min(lim)) & (t <= max(lim))
            return t[ok], [s for s, k in zip(lab, ok.tolist(), strict=True) if k]
        scale = self.xscale if axis == "x" else self.yscale
        # fewer ticks where their labels would crowd (narrow x axes, short y axes)
        for n in range(8, 2, -1):
            t = log_ticks(*lim, n) if scale == "log" else nice_ticks(*lim, n)
            labels = tick_labels(t, scale)
            need = (sum(text_width(s, TICK_FONT) + 22 for s in labels) if axis == "x"
                    else len(labels) * TICK_FONT * 2.5)
            if need <= (self.width if axis == "x" else self.height):
                break
        return t, labels

    # --- SVG -------------------------------------------------------------------------------
    def _svg(self, fig_uid: str, i: int, out: list[str]) -> None:
        self._prepare()
        uid = f"{fig_uid}-{i}"
        L, T, W, H = self.left, self.top, self.width, self.height
        B, R = T + H, L + W
        xt, xlab = self._ticks("x")
        yt, ylab = self._ticks("y")
        px, py = self.tx(xt), self.ty(yt)
        grid = "".join(f"M{x:.1f} {T:.1f}V{B:.1f}" for x in px.tolist()) + "".join(
            f"M{L:.1f} {y:.1f}H{R:.1f}" for y in py.tolist())
        ticks = "".join(f"M{x:.1f} {B:.1f}v3.5" for x in px.tolist()) + "".join(
            f"M{L:.1f} {y:.1f}h-3.5" for y in py.tolist())
        out.append(f'<path d="{grid}" stroke="#000" stroke-opacity=".12" stroke-width=".7"/>')
        clip = f"{uid}-c"
        out.append(f'<clipPath id="{clip}"><rect x="{L:.1f}" y="{T:.1f}" width="{W:.1f}" '
                   f'height="{H:.1f}"/></clipPath><g clip-path="url(#{clip})">')
        for it in self.items:
            self._item(it, fig_uid, out)
        out.append("</g>")
        out.append(f'<path d="M{L:.1f} {T:.1f}V{B:.1f}H{R:.1f}{ticks}" stroke="#333" '
                   'stroke-width=".8" fill="none"/>')
        out.append(f'<g font-size="{TICK_FONT}" fill="#222" text-anchor="middle">'
                   + "".join(f'<text x="{x:.1f}" y="{B + 15:.1f}">{esc(s)}</text>'
                             for x, s in zip(px.tolist(), xlab, strict=True)) + "</g>")
        out.append(f'<g font-size="{TICK_FONT}" fill="#222" text-anchor="end">'
                   + "".join(f'<text x="{L - 6:.1f}" y="{y:.1f}" dy=".35em">{esc(s)}</text>'
                             for y, s in zip(py.tolist(), ylab, strict=True)) + "</g>")
        if self.xlabel:
            out.append(f'<text x="{L + W / 2:.1f}" y="{B + 32:.1f}" font-size="{LABEL_FONT}" '
                       f'text-anchor="middle">{esc(self.xlabel)}</text>')
        if self.ylabel:
            wide = max((text_width(s, TICK_FONT) for s in ylab), default=0.0)
            x = L - wide - 14
            out.append(f'<text transform="translate({x:.1f} {T + H / 2:.1f}) rotate(-90)" '
                       f'font-size="{LABEL_FONT}" text-anchor="middle">{esc(self.ylabel)}'
                       "</text>")
        top = T - 6
        if self.legend_spec is not None:
            top = self._legend(out, top, fig_uid)
        if self.title:
            out.append(f'<text x="{L + W / 2:.1f}" y="{top:.1f}" font-size="{self.title_size}" '
                       f'text-anchor="middle">{esc(self.title)}</text>')
        if self.message:
            out.append(f'<text x="{L + W / 2:.1f}" y="{T + H / 2:.1f}" dy=".35em" '
                       f'fill="#777" text-anchor="middle">{esc(self.message)}</text>')

    def _item(self, it: _Item, uid: str, out: list[str]) -> None:
        op = f' opacity="{it.alpha:.2f}"' if it.alpha < 1 else ""
        col = it.color if isinstance(it.color, str) else "#000"
        L, T, W, H = self.left, self.top, self.width, self.height
        if it.kind in ("line", "stairs"):
            x, y = self.tx(it.x), self.ty(it.y)
            ok = np.isfinite(x) & np.isfinite(y)
            if ok.sum() >= 2:
                start = ok & ~np.concatenate([[False], ok[:-1]])
                cmd = np.where(start, "M", "L")[ok]
                out.append(f'<path d="{_pairs(cmd, x[ok], y[ok])}" fill="none" stroke="{col}" '
                           f'stroke-width="{it.width}" stroke-linejoin="round"'
                           f'{_dash(it.dash)}{op}/>')
            if it.marker:
                self._markers(it, x, y, op, out)
        elif it.kind == "markers":
            self._markers(it, self.tx(it.x), self.ty(it.y), op, out)
        elif it.kind == "band":
            assert it.y2 is not None
            x, lo, hi = self.tx(it.x), self.ty(it.y), self.ty(it.y2)
            ok = np.isfinite(x) & np.isfinite(lo) & np.isfinite(hi)
            if ok.sum() >= 2:
                xs = np.concatenate([x[ok], x[ok][::-1]])
                ys = np.concatenate([hi[ok], lo[ok][::-1]])
                cmd = np.full(xs.size, "L")
                cmd[0] = "M"
                out.append(f'<path d="{_pairs(cmd, xs, ys)}Z" fill="{col}"{op}/>')
        elif it.kind == "rects":
            self._rects(it, uid, op, out)
        elif it.kind == "vspan":
            a, b = np.sort(self.tx(it.x))
            if np.isfinite([a, b]).all() and b > a:
                out.append(f'<rect x="{a:.1f}" y="{T:.1f}" width="{b - a:.1f}" '
                           f'height="{H:.1f}" fill="{col}"{op}/>')
        elif it.kind in ("hline", "vline"):
            v = (self.ty(it.y) if it.kind == "hline" else self.tx(it.x))[0]
            if math.isfinite(v):
                d = f"M{L:.1f} {v:.1f}h{W:.1f}" if it.kind == "hline" else \
                    f"M{v:.1f} {T:.1f}v{H:.1f}"
                out.append(f'<path d="{d}" stroke="{col}" stroke-width="{it.width}"'
                           f'{_dash(it.dash)}/>')
        elif it.kind == "text":
            x, y = self.tx(it.x)[0], self.ty(it.y)[0]
            if math.isfinite(x) and math.isfinite(y):
                out.append(f'<text x="{x:.1f}" y="{y:.1f}" dy=".35em" font-size="{it.size}" '
                           f'text-anchor="{it.anchor}" fill="{col}">{esc(it.text)}</text>')

    @staticmethod
    def _markers(it: _Item, x: Array, y: Array, op: str, out: list[str]) -> None:
        ok = np.isfinite(x) & np.isfinite(y)
        if not ok.any():
            return
        shape, closed = _shape(it.marker or "o", it.size)
        d = "".join(f"M{a:.1f} {b:.1f}{shape}" for a, b in zip(x[ok].tolist(), y[ok].tolist(),
                                                               strict=True))
        fill = it.color if it.filled and closed else "none"
        out.append(f'<path d="{d}" fill="{fill}" stroke="{it.color}" '
                   f'stroke-width="{it.width}"{op}/>')

    def _rects(self, it: _Item, uid: str, op: str, out: list[str]) -> None:
        assert it.x2 is not None and it.y2 is not None
        xa, xb = self.tx(it.x), self.tx(it.x2)
        ya, yb = self.ty(it.y), self.ty(it.y2)
        # a bar starting at 0 on a log axis starts at the axis' edge
        if self.xscale == "log":
            xa = np.where(it.x <= 0, self.left, xa)
        if self.yscale == "log":
            ya = np.where(it.y <= 0, self.top + self.height, ya)
        x0, x1 = np.minimum(xa, xb), np.maximum(xa, xb)
        y0, y1 = np.minimum(ya, yb), np.maximum(ya, yb)
        ok = np.isfinite(x0) & np.isfinite(x1) & np.isfinite(y0) & np.isfinite(y1)
        cols = np.array([it.color] * it.x.size if isinstance(it.color, str) else it.color)
        for c in dict.fromkeys(cols[ok].tolist()):
            sel = ok & (cols == c)
            d = "".join(f"M{a:.1f} {b:.1f}h{w:.1f}v{h:.1f}h{-w:.1f}z" for a, b, w, h in zip(
                x0[sel].tolist(), y0[sel].tolist(), (x1 - x0)[sel].tolist(),
                (y1 - y0)[sel].tolist(), strict=True))
            out.append(f'<path d="{d}" fill="{c}"{op}/>')
            if it.hatch:
                out.append(f'<path d="{d}" fill="url(#{uid}-hatch)"/>')

    def _entries(self) -> list[_Item]:
        return [it for it in self.items if it.label]

    def _legend(self, out: list[str], top: float, fig_uid: str) -> float:
        """Draw the legend; return the baseline for a title above it."""
        assert self.legend_spec is not None
        loc, ncol, size = self.legend_spec
        entries = self._entries()
        if not entries:
            return top
        ncol = min(ncol, len(entries))
        rows = -(-len(entries) // ncol)
        sw, gap, row_h = 22.0, 12.0, size * 1.45
        col_w = [max(text_width(entries[k].label or "", size)
                     for k in range(c, len(entries), ncol)) + sw + 5 for c in range(ncol)]
        w = sum(col_w) + gap * (ncol - 1)
        h = rows * row_h
        L, T, W, H = self.left, self.top, self.width, self.height
        if loc == "above":
            x0, y0 = L + (W - w) / 2, T - 4 - h
            top = y0 - 4
        elif loc == "below":
            x0, y0 = L + (W - w) / 2, T + H + 40
        else:
            if loc == "best":
                loc = self._best(w, h)
            x0, y0 = self._place(loc, w, h)
            out.append(f'<rect x="{x0 - 4:.1f}" y="{y0 - 2:.1f}" width="{w + 8:.1f}" '
                       f'height="{h + 4:.1f}" fill="#fff" fill-opacity=".8"/>')
        parts = [f'<g font-size="{size}" fill="#222">']
        for k, it in enumerate(entries):
            r, c = divmod(k, ncol)
            x = x0 + sum(col_w[:c]) + gap * c
            yc = y0 + (r + 0.5) * row_h
            parts.append(self._swatch(it, x, yc, sw, fig_uid))
            parts.append(f'<text x="{x + sw + 5:.1f}" y="{yc:.1f}" dy=".35em">'
                         f'{esc(it.label)}</text>')
        parts.append("</g>")
        out.append("".join(parts))
        return top

    def _place(self, loc: LegendLoc, w: float, h: float) -> tuple[float, float]:
        """Top-left corner (px) of a ``w`` x ``h`` legend box at an inside ``loc``."""
        L, T, W, H = self.left, self.top, self.width, self.height
        x0 = (L + 8 if loc.endswith("left") else L + W - 8 - w if loc.endswith("right")
              else L + (W - w) / 2)
        y0 = (T + 6 if loc.startswith("upper") else T + H - 6 - h if loc.startswith("lower")
              else T + (H - h) / 2)
        return x0, y0

    def _best(self, w: float, h: float) -> LegendLoc:
        """The inside place whose legend box would cover the least data: markers count
        once each, lines by 8 points along each of their segments."""
        xs, ys = [], []
        for it in self.items:
            if it.kind not in ("line", "stairs", "markers"):
                continue
            x, y = self.tx(it.x), self.ty(it.y)
            if it.kind != "markers" and x.size >= 2:
                # 8 samples per segment; segments through a non-finite point give NaN
                t = np.linspace(0.0, 1.0, 8, endpoint=False)
                x = (x[:-1, None] + np.diff(x)[:, None] * t).ravel()
                y = (y[:-1, None] + np.diff(y)[:, None] * t).ravel()
            xs.append(x)
            ys.append(y)
        if not xs:
            return _INSIDE[0]
        x, y = np.concatenate(xs), np.concatenate(ys)
        best, least = _INSIDE[0], -1
        for loc in _INSIDE:
            x0, y0 = self._place(loc, w, h)
            n = int(np.count_nonzero((x >= x0) & (x <= x0 + w) & (y >= y0) & (y <= y0 + h)))
            if least < 0 or n < least:
                best, least = loc, n
        return best

    @staticmethod
    def _swatch(it: _Item, x: float, yc: float, sw: float, fig_uid: str) -> str:
        op = f' opacity="{it.alpha:.2f}"' if it.alpha < 1 else ""
        col = it.color if isinstance(it.color, str) else it.color[0] if it.color else "#000"
        if it.kind == "rects":
            box = f'<rect x="{x:.1f}" y="{yc - 5:.1f}" width="{sw:.1f}" height="10" '
            hatch = f'{box}fill="url(#{fig_uid}-hatch)"/>' if it.hatch else ""
            return f'{box}fill="{col}"{op}/>{hatch}'

        s = ""
        if it.kind in ("line", "stairs", "hline", "vline"):
            s = (f'<path d="M{x:.1f} {yc:.1f}h{sw:.1f}" stroke="{col}" '
                 f'stroke-width="{it.width}"{_dash(it.dash)}{op}/>')
        if it.marker or it.kind == "markers":
            shape, closed = _shape(it.marker or "o", min(it.size, 5.0))
            fill = col if it.filled and closed else "none"
            s += (f'<path d="M{x + sw / 2:.1f} {yc:.1f}{shape}" fill="{fill}" stroke="{col}" '
                  f'stroke-width="{it.width}"{op}/>')
        return s


class Figure:
    """A canvas of ``width`` x ``height`` px holding axes; :meth:`svg` writes the markup."""

    def __init__(self, width: float, height: float) -> None:
        self.width = width
        self.height = height
        self.axes: list[Axes] = []
        self.extra: list[str] = []

    def subplots(self, rows: int, cols: int, margins: tuple[float, float, float, float], *,
                 wspace: float = 0.3, hspace: float = 0.5) -> list[Axes]:
        """A grid of axes, row by row, inside ``margins`` (left, right, bottom, top; px);
        ``wspace``/``hspace``: gaps as fractions of the mean axes width/height."""
        left, right, bottom, top = margins
        W, H = self.width - left - right, self.height - bottom - top
        aw = W / (cols + wspace * (cols - 1))
        ah = H / (rows + hspace * (rows - 1))
        new = [Axes(left + c * aw * (1 + wspace), top + r * ah * (1 + hspace), aw, ah)
               for r in range(rows) for c in range(cols)]
        self.axes.extend(new)
        return new

    def colorbar(self, ax: Axes, lo: float, hi: float, label: str) -> None:
        """A vertical viridis colour bar for values ``lo``..``hi`` right of ``ax``."""
        x, y, w, h = ax.left + ax.width + 12, ax.top, 12.0, ax.height
        stops = "".join(f'<stop offset="{k / 10:.1f}" stop-color="{c}"/>'
                        for k, c in enumerate(_VIRIDIS))
        if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
            lo, hi = (lo, lo + 1.0) if math.isfinite(lo) else (0.0, 1.0)
        t = nice_ticks(lo, hi, 6)
        py = y + h - (t - lo) / (hi - lo) * h
        labels = tick_labels(t, "linear")
        ticks = "".join(f"M{x + w:.1f} {p:.1f}h3" for p in py.tolist())
        text = "".join(f'<text x="{x + w + 6:.1f}" y="{p:.1f}" dy=".35em">{esc(s)}</text>'
                       for p, s in zip(py.tolist(), labels, strict=True))
        wide = max((text_width(s, TICK_FONT) for s in labels), default=0.0)
        self.extra.append(
            f'<linearGradient id="{_UID}-cb" x1="0" y1="1" x2="0" y2="0">{stops}'
            f'</linearGradient><rect x="{x:.1f}" y="{y:.1f}" width="{w}" height="{h:.1f}" '
            f'fill="url(#{_UID}-cb)"/><path d="{ticks}" stroke="#333" stroke-width=".8"/>'
            f'<g font-size="{TICK_FONT}" fill="#222">{text}</g>'
            f'<text transform="translate({x + w + wide + 18:.1f} {y + h / 2:.1f}) '
            f'rotate(-90)" font-size="{LABEL_FONT}" text-anchor="middle">{esc(label)}</text>')

    def svg(self, key: str, alt: str) -> str:
        """The figure as one ``<svg>`` element (ids prefixed by ``key``, unique per page)."""
        uid = "f-" + _ID.sub("_", key)
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {self.width:.0f} '
               f'{self.height:.0f}" width="{self.width:.0f}" height="{self.height:.0f}" '
               f'role="img" aria-label="{esc(alt)}" font-family="DejaVu Sans,Helvetica,'
               f'Arial,sans-serif" font-size="{TICK_FONT}"><title>{esc(alt)}</title>'
               f'<defs><pattern id="{uid}-hatch" patternUnits="userSpaceOnUse" width="6" '
               f'height="6"><path d="M-1 1l2-2M0 6l6-6M5 7l2-2" stroke="#fff" '
               f'stroke-width="1.2"/></pattern></defs>'
               f'<rect width="100%" height="100%" fill="#fff"/>']
        for i, ax in enumerate(self.axes):
            ax._svg(uid, i, out)
        out.extend(e.replace(_UID, uid) for e in self.extra)
        out.append("</svg>")
        return "".join(out)
