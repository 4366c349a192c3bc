"""A small SVG plotter for the report's figures (ADR 0049).

Figures are laid out on fixed margins in inches (96 px per inch), drawn with numpy-transformed
coordinates and one ``<path>`` per series, and emitted as SVG text: no font rasterising, no
text-extent search, no PNG encoding. Text widths are estimated (``text_width``), which is all
the fixed layouts need. The API follows matplotlib's names where it can, so a figure reads
like one, but only what the report draws is there.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
DPI = 96.0
PT = DPI / 72.0  # px per typographic point
FONT = "DejaVu Sans,Helvetica,Arial,sans-serif"
MINUS = "\u2212"
# Viridis (matplotlib's perceptually uniform colour map) sampled at 9 evenly spaced points;
# values between them are interpolated linearly in RGB.
VIRIDIS = ((68, 1, 84), (71, 44, 122), (59, 81, 139), (44, 113, 142), (33, 144, 141),
           (39, 173, 129), (92, 200, 99), (170, 220, 50), (253, 231, 37))
Scale = Literal["linear", "log"]
_CB_AXES = 0.72  # the share of its box an axes with a colour bar keeps


def esc(s: object) -> str:
    """``s`` as XML character data or attribute value."""
    return (str(s).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
            .replace('"', "&quot;"))


def text_width(s: str, size_px: float) -> float:
    """Estimated width (px) of ``s`` in the sans-serif font at ``size_px``."""
    return 0.58 * size_px * len(s)


def viridis(t: ArrayLike) -> list[str]:
    """Hex colours of the values ``t`` in [0, 1] (clipped) on the viridis map."""
    v = np.clip(np.nan_to_num(np.asarray(t, dtype=float), nan=0.0), 0.0, 1.0)
    pos = v * (len(VIRIDIS) - 1)
    i = np.minimum(pos.astype(int), len(VIRIDIS) - 2)
    f = (pos - i)[:, None]
    table = np.asarray(VIRIDIS, dtype=float)
    rgb = np.rint(table[i] * (1 - f) + table[i + 1] * f).astype(int)
    return [f"#{r:02x}{g:02x}{b:02x}" for r, g, b in rgb.tolist()]


# ---------------------------------------------------------------------------- ticks

def _fmt_step(v: float, decimals: int) -> str:
    s = f"{v:.{decimals}f}"
    if s.lstrip("-").strip("0.") == "":
        s = s.lstrip("-")  # no "-0.0"
    return s.replace("-", MINUS)


def linear_ticks(lo: float, hi: float, nbins: int = 6) -> tuple[Array, list[str]]:
    """Tick positions at a 1-2-2.5-5 step, at most ``nbins`` intervals over [lo, hi], with
    labels of just enough decimals for the step."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return np.zeros(0), []
    raw = (hi - lo) / nbins
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * mag >= raw * (1 - 1e-9))
    first = math.ceil(lo / step - 1e-9)
    last = math.floor(hi / step + 1e-9)
    ticks = np.arange(first, last + 1, dtype=float) * step
    exp = math.floor(math.log10(step) + 1e-12)
    decimals = max(0, -exp + (1 if round(step / 10.0 ** exp, 6) == 2.5 else 0))
    return ticks, [_fmt_step(float(t), decimals) for t in ticks]


def _fmt_log(v: float) -> str:
    return f"{v:g}".replace("-", MINUS)


def log_ticks(lo: float, hi: float) -> tuple[Array, list[str]]:
    """Decades in [lo, hi] (every k-th when there are many); with fewer than three decades
    in view also 2 and 5 times each decade, so an axis always has labelled ticks."""
    if not (lo > 0 and hi > lo and math.isfinite(hi)):
        return np.zeros(0), []
    d0, d1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    subs = (1.0, 2.0, 5.0) if hi <= 100 * lo else (1.0,)
    every = max(1, math.ceil((d1 - d0) / 7))
    vals = [m * 10.0 ** d for d in range(d0, d1 + 1) if (d - d0) % every == 0 for m in subs]
    ticks = np.array([v for v in vals if lo * (1 - 1e-9) <= v <= hi * (1 + 1e-9)])
    return ticks, [_fmt_log(float(t)) for t in ticks]


# ---------------------------------------------------------------------------- markers

def _marker_path(mk: str, r: float) -> tuple[str, str, bool]:
    """(start offset "dx,dy" from the centre, relative path drawn from there, fillable) of
    marker ``mk`` with half-size ``r`` px."""
    def f(v: float) -> str:
        return f"{v:.2f}".rstrip("0").rstrip(".") or "0"

    d, h = f(2 * r), f(r)
    if mk in ("o", "."):
        return f"{-r:.2f},0", f"a{h},{h} 0 1 0 {d},0a{h},{h} 0 1 0 -{d},0z", True
    if mk == "s":
        return f"{-r:.2f},{-r:.2f}", f"h{d}v{d}h-{d}z", True
    if mk == "D":
        return f"0,{-r:.2f}", f"l{h},{h}l-{h},{h}l-{h},-{h}z", True
    if mk in ("^", "v", "<"):
        s = -1 if mk == "^" else 1
        if mk == "<":
            return f"{-r:.2f},0", f"l{d},-{h}v{d}z", True
        return f"0,{s * r:.2f}", f"l{h},{f(-2 * s * r)}h-{d}z", True
    if mk == "h":
        a, b = f(r * 0.866), f(r * 0.5)
        return f"0,{-r:.2f}", f"l{a},{b}v{h}l-{a},{b}l-{a},-{b}v-{h}z", True
    if mk == "x":
        return f"{-r:.2f},{-r:.2f}", f"l{d},{d}m0,-{d}l-{d},{d}", False
    if mk in ("+", "P"):
        return f"{-r:.2f},0", f"h{d}m-{h},-{h}v{d}", False
    if mk == "*":
        a, b = f(r * 0.95), f(r * 0.31)
        return f"0,{-r:.2f}", (f"v{d}m-{a},-{f(r * 1.31)}l{f(r * 1.9)},{f(r * 0.62)}"
                                f"m0,-{f(r * 0.62)}l-{f(r * 1.9)},{f(r * 0.62)}m{a},-{b}"), False
    if mk == "|":
        return f"0,{-r:.2f}", f"v{d}", False
    raise ValueError(f"unknown marker {mk!r}")


def _points_path(px: Array, py: Array, mk: str, r: float) -> tuple[str, bool]:
    start, rel, fillable = _marker_path(mk, r)
    sx, sy = (float(v) for v in start.split(","))
    parts = [f"M{x:.1f},{y:.1f}{rel}" for x, y in zip((px + sx).tolist(), (py + sy).tolist(),
                                                       strict=True)]
    return "".join(parts), fillable


def _polyline(px: Array, py: Array) -> str:
    """One path through the finite points; a non-finite value breaks the line."""
    ok = np.isfinite(px) & np.isfinite(py)
    out: list[str] = []
    pen = False
    for x, y, good in zip(px.tolist(), py.tolist(), ok.tolist(), strict=True):
        if not good:
            pen = False
            continue
        out.append(f"{'L' if pen else 'M'}{x:.1f},{y:.1f}")
        pen = True
    return "".join(out)


# ---------------------------------------------------------------------------- artists

@dataclass
class _Line:
    x: Array
    y: Array
    color: str
    lw: float
    dash: str | None
    marker: str | None
    ms: float
    mew: float
    hollow: bool
    alpha: float
    label: str | None
    linestyle: bool


@dataclass
class _Rects:
    x0: Array
    x1: Array
    y0: Array
    y1: Array
    colors: list[str]
    alpha: float
    hatch: bool
    edge: str | None
    label: str | None


@dataclass
class _Fill:
    x: Array
    y0: Array
    y1: Array
    color: str
    alpha: float


@dataclass
class _Span:
    axis: Literal["x", "y"]
    a: float
    b: float
    color: str
    alpha: float
    lw: float = 0.0
    dash: str | None = None
    label: str | None = None


@dataclass
class _Text:
    x: float
    y: float
    s: str
    axes_coords: bool
    ha: str
    va: str
    color: str
    size: float


@dataclass
class _Colored:
    x: Array
    y: Array
    colors: list[str]
    ms: float


@dataclass
class _Legend:
    loc: str
    ncol: int
    size: float


@dataclass
class _Axis:
    scale: Scale = "linear"
    lim: tuple[float, float] | None = None
    ticks: tuple[list[float], list[str]] | None = None
    label: str = ""
    inverted: bool = False


@dataclass
class Axes:
    """One plot area: a box in figure pixels (left, top, width, height) and its artists."""

    box: tuple[float, float, float, float]
    artists: list[Any] = field(default_factory=list)
    xaxis: _Axis = field(default_factory=_Axis)
    yaxis: _Axis = field(default_factory=_Axis)
    title: str = ""
    title_size: float = 9.5
    legend_: _Legend | None = None
    equal: bool = False
    colorbar: tuple[float, float, str] | None = None

    # -- drawing
    def plot(self, x: ArrayLike, y: ArrayLike, *, color: str, lw: float = 1.4,
             dash: str | None = None, marker: str | None = None, ms: float = 3.4,
             mew: float = 0.8, hollow: bool = True, alpha: float = 1.0,
             label: str | None = None, line: bool | None = None) -> None:
        """A series: a line (``line``; default when there is no marker) and/or markers
        (``ms`` points across, open when ``hollow``)."""
        self.artists.append(_Line(_arr(x), _arr(y), color, lw, dash, marker, ms, mew, hollow,
                                  alpha, label, marker is None if line is None else line))

    def barh(self, y: ArrayLike, width: ArrayLike, *, left: ArrayLike = 0.0,
             height: float = 0.8, color: str | Sequence[str], alpha: float = 1.0,
             hatch: bool = False, edgecolor: str | None = None,
             label: str | None = None) -> None:
        """Horizontal bars centred on ``y``."""
        yc, w = np.broadcast_arrays(_arr(y), _arr(width))
        x0 = np.broadcast_to(_arr(left), yc.shape)
        self._rects(x0, x0 + w, yc - height / 2, yc + height / 2, color, alpha, hatch,
                    edgecolor, label)

    def bar(self, x: ArrayLike, height: ArrayLike, width: float = 0.8, *,
            bottom: ArrayLike = 0.0, color: str | Sequence[str], alpha: float = 1.0,
            label: str | None = None) -> None:
        """Vertical bars centred on ``x``."""
        xc, h = np.broadcast_arrays(_arr(x), _arr(height))
        y0 = np.broadcast_to(_arr(bottom), xc.shape)
        self._rects(xc - width / 2, xc + width / 2, y0, y0 + h, color, alpha, False, None,
                    label)

    def _rects(self, x0: Array, x1: Array, y0: Array, y1: Array,
               color: str | Sequence[str], alpha: float, hatch: bool, edge: str | None,
               label: str | None) -> None:
        cols = [color] * x0.size if isinstance(color, str) else list(color)
        self.artists.append(_Rects(np.asarray(x0, float), np.asarray(x1, float),
                                   np.asarray(y0, float), np.asarray(y1, float), cols, alpha,
                                   hatch, edge, label))

    def hist(self, data: ArrayLike, bins: ArrayLike | int, *, color: str, lw: float = 1.6,
             step: bool = True, alpha: float = 1.0, label: str | None = None) -> None:
        """Histogram of the finite ``data``: a step outline (``step``) or filled bars."""
        d = _arr(data)
        counts, edges = np.histogram(d[np.isfinite(d)], bins=bins)
        c = counts.astype(float)
        if step:
            x = np.repeat(edges, 2)
            y = np.concatenate([[0.0], np.repeat(c, 2), [0.0]])
            self.plot(x, y, color=color, lw=lw, label=label)
        else:
            self._rects(edges[:-1], edges[1:], np.zeros(c.size), c, color, alpha, False, None,
                        label)
        self.artists.append(_Span("y", 0.0, 0.0, "none", 0.0))  # the axis starts at 0

    def fill_between(self, x: ArrayLike, y0: ArrayLike, y1: ArrayLike, *, color: str,
                     alpha: float = 0.18) -> None:
        """The band between two curves over ``x``."""
        self.artists.append(_Fill(_arr(x), _arr(y0), _arr(y1), color, alpha))

    def axvspan(self, a: float, b: float, *, color: str, alpha: float) -> None:
        """A shaded vertical band over the whole height."""
        self.artists.append(_Span("x", a, b, color, alpha))

    def axhline(self, y: float, *, color: str, lw: float = 0.8, dash: str | None = None,
                label: str | None = None) -> None:
        """A horizontal reference line over the whole width."""
        self.artists.append(_Span("y", y, y, color, 1.0, lw, dash, label))

    def axvline(self, x: float, *, color: str, lw: float = 0.8,
                dash: str | None = None) -> None:
        """A vertical reference line over the whole height."""
        self.artists.append(_Span("x", x, x, color, 1.0, lw, dash))

    def scatter_colored(self, x: ArrayLike, y: ArrayLike, values: ArrayLike, *,
                        vmin: float, vmax: float, ms: float = 2.6) -> None:
        """Filled dots coloured by ``values`` on the viridis map over [vmin, vmax]."""
        v = _arr(values)
        t = (v - vmin) / (vmax - vmin) if vmax > vmin else np.zeros_like(v)
        self.artists.append(_Colored(_arr(x), _arr(y), viridis(np.round(t * 31) / 31), ms))

    def text(self, x: float, y: float, s: str, *, axes_coords: bool = False,
             ha: str = "left", va: str = "center", color: str = "#222",
             size: float = 7.5) -> None:
        """Text at data (or axes-fraction) coordinates."""
        self.artists.append(_Text(x, y, s, axes_coords, ha, va, color, size))

    # -- axes
    def set_xscale(self, s: Scale) -> None:
        self.xaxis.scale = s

    def set_yscale(self, s: Scale) -> None:
        self.yaxis.scale = s

    def set_xlim(self, lo: float, hi: float) -> None:
        self.xaxis.lim = (lo, hi)

    def set_ylim(self, lo: float, hi: float) -> None:
        self.yaxis.lim = (lo, hi)

    def set_xlabel(self, s: str) -> None:
        self.xaxis.label = s

    def set_ylabel(self, s: str) -> None:
        self.yaxis.label = s

    def set_title(self, s: str, size: float = 9.5) -> None:
        self.title, self.title_size = s, size

    def set_xticks(self, pos: Sequence[float], labels: Sequence[str]) -> None:
        self.xaxis.ticks = ([float(p) for p in pos], [str(s) for s in labels])

    def set_yticks(self, pos: Sequence[float], labels: Sequence[str]) -> None:
        self.yaxis.ticks = ([float(p) for p in pos], [str(s) for s in labels])

    def invert_yaxis(self) -> None:
        self.yaxis.inverted = True

    def set_aspect_equal(self) -> None:
        """Equal data units per pixel on both axes (the limits grow, the box stays)."""
        self.equal = True

    def legend(self, loc: str = "best", ncol: int = 1, size: float = 7.5) -> None:
        """A legend of the labelled artists: ``above`` / ``below`` the axes (outside,
        centred), or inside at ``upper right``, ``upper left``, ``lower left``, ``lower
        right`` or ``best`` (the corner with the fewest data points)."""
        self.legend_ = _Legend(loc, ncol, size)

    def has_data(self) -> bool:
        """True when a series with points was drawn."""
        return any(isinstance(a, _Line) and a.x.size for a in self.artists)


def _arr(v: ArrayLike) -> Array:
    return np.atleast_1d(np.asarray(v, dtype=float))


# ---------------------------------------------------------------------------- limits

def _extent(ax: Axes, which: Literal["x", "y"], log: bool) -> tuple[float, float, bool, bool]:
    """(lo, hi, sticky lo, sticky hi) of the data along ``which``."""
    vals: list[Array] = []
    sticky: list[float] = []
    for a in ax.artists:
        if isinstance(a, _Line | _Colored):
            vals.append(a.x if which == "x" else a.y)
        elif isinstance(a, _Rects):
            lo_, hi_ = (a.x0, a.x1) if which == "x" else (a.y0, a.y1)
            vals += [lo_, hi_]
            if lo_.size and np.all(lo_ == lo_.flat[0]):  # bars from a common base
                sticky.append(float(lo_.flat[0]))
        elif isinstance(a, _Fill):
            vals += [a.x] if which == "x" else [a.y0, a.y1]
        elif isinstance(a, _Span) and a.axis == which and a.alpha >= 0:
            if a.color == "none":
                sticky.append(a.a)
            if a.lw > 0 or a.color == "none":
                vals.append(np.array([a.a, a.b]))
    v = np.concatenate(vals) if vals else np.zeros(0)
    v = v[np.isfinite(v) & ((v > 0) if log else True)]
    if not v.size:
        return (1.0, 10.0, False, False) if log else (0.0, 1.0, False, False)
    lo, hi = float(v.min()), float(v.max())
    return lo, hi, any(s == lo for s in sticky), any(s == hi for s in sticky)


def _limits(ax: Axes, which: Literal["x", "y"]) -> tuple[float, float]:
    axis = ax.xaxis if which == "x" else ax.yaxis
    log = axis.scale == "log"
    if axis.lim is not None:
        lo, hi = axis.lim
    else:
        lo, hi, slo, shi = _extent(ax, which, log)
        if log:
            a, b = math.log10(lo), math.log10(hi)
            if b - a < 1e-9:
                a, b = a - 0.5, b + 0.5
            m = 0.05 * (b - a)
            lo, hi = 10 ** (a if slo else a - m), 10 ** (b if shi else b + m)
        else:
            if hi - lo <= 1e-12 * max(1.0, abs(hi)):
                d = max(abs(hi) * 0.05, 1e-9)
                lo, hi = lo - d, hi + d
            m = 0.05 * (hi - lo)
            lo, hi = (lo if slo else lo - m), (hi if shi else hi + m)
    if log and lo <= 0:
        lo = hi / 1e3 if hi > 0 else 1.0
        hi = max(hi, lo * 10)
    return float(lo), float(hi)


# ---------------------------------------------------------------------------- figure

@dataclass
class Figure:
    """A figure of ``w`` x ``h`` inches whose axes sit inside fixed ``margins`` (left,
    right, bottom, top; inches)."""

    w: float
    h: float
    margins: tuple[float, float, float, float]
    wspace: float = 0.3
    hspace: float = 0.5
    axes: list[Axes] = field(default_factory=list)

    def subplots(self, nrows: int = 1, ncols: int = 1) -> list[list[Axes]]:
        """A grid of axes (rows of columns); gaps are ``wspace``/``hspace`` times the mean
        axes width/height, as matplotlib's."""
        left, right, bottom, top = (m * DPI for m in self.margins)
        W, H = self.w * DPI - left - right, self.h * DPI - top - bottom
        aw = W / (ncols + (ncols - 1) * self.wspace)
        ah = H / (nrows + (nrows - 1) * self.hspace)
        grid = [[Axes((left + c * aw * (1 + self.wspace), top + r * ah * (1 + self.hspace),
                       aw, ah)) for c in range(ncols)] for r in range(nrows)]
        self.axes += [a for row in grid for a in row]
        return grid

    def add_subplot(self) -> Axes:
        """One axes filling the margins."""
        return self.subplots(1, 1)[0][0]

    def colorbar(self, ax: Axes, vmin: float, vmax: float, label: str) -> None:
        """A viridis colour bar at the right of ``ax`` (which gives up 28 % of its width to
        the bar, its tick labels and ``label``)."""
        x, y, w, h = ax.box
        ax.box = (x, y, w * _CB_AXES, h)
        ax.colorbar = (vmin, vmax, label)

    def svg(self, title: str = "") -> str:
        """The whole figure as an SVG document."""
        wpx, hpx = round(self.w * DPI), round(self.h * DPI)
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{wpx}" height="{hpx}" '
               f'viewBox="0 0 {wpx} {hpx}" font-family="{FONT}" font-size="{8 * PT:.2f}">',
               f"<title>{esc(title)}</title>" if title else "",
               '<defs><pattern id="hatch" patternUnits="userSpaceOnUse" width="6" height="6">'
               '<path d="M-1,1l2,-2M0,6l6,-6M5,7l2,-2" stroke="#fff" stroke-width="1"/>'
               '</pattern><linearGradient id="cmap" x1="0" y1="1" x2="0" y2="0">'
               + "".join(f'<stop offset="{k / (len(VIRIDIS) - 1):.3f}" '
                         f'stop-color="#{r:02x}{g:02x}{b:02x}"/>'
                         for k, (r, g, b) in enumerate(VIRIDIS))
               + "</linearGradient></defs>",
               f'<rect width="{wpx}" height="{hpx}" fill="#fff"/>']
        for k, ax in enumerate(self.axes):
            out.append(_draw_axes(ax, k))
        out.append("</svg>")
        return "".join(out)

    def data_uri(self, title: str = "") -> str:
        """The SVG as a base64 data URI for an ``<img>``."""
        return "data:image/svg+xml;base64," + base64.b64encode(
            self.svg(title).encode("utf-8")).decode("ascii")


class _Map:
    """Data to pixel coordinates of one axis."""

    def __init__(self, lo: float, hi: float, p0: float, p1: float, log: bool) -> None:
        self.log = log
        self.lo, self.hi = (math.log10(lo), math.log10(hi)) if log else (lo, hi)
        self.p0, self.p1 = p0, p1
        self.k = (p1 - p0) / (self.hi - self.lo) if self.hi != self.lo else 0.0

    def __call__(self, v: ArrayLike) -> Array:
        a = np.asarray(v, dtype=float)
        if self.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                a = np.where(a > 0, np.log10(np.where(a > 0, a, 1.0)), np.nan)
        return self.p0 + (a - self.lo) * self.k


def _equalise(ax: Axes, xl: tuple[float, float], yl: tuple[float, float]
              ) -> tuple[tuple[float, float], tuple[float, float]]:
    _, _, w, h = ax.box
    sx, sy = (xl[1] - xl[0]) / w, (yl[1] - yl[0]) / h
    if sx > sy:
        c, half = (yl[0] + yl[1]) / 2, sx * h / 2
        return xl, (c - half, c + half)
    c, half = (xl[0] + xl[1]) / 2, sy * w / 2
    return (c - half, c + half), yl


def _dash(d: str | None) -> str:
    return f' stroke-dasharray="{d}"' if d else ""


def _op(alpha: float, attr: str = "opacity") -> str:
    return f' {attr}="{alpha:.2f}"' if alpha < 1 else ""


def _draw_axes(ax: Axes, k: int) -> str:
    x0, y0, w, h = ax.box
    xl, yl = _limits(ax, "x"), _limits(ax, "y")
    if ax.equal and ax.xaxis.scale == ax.yaxis.scale == "linear":
        xl, yl = _equalise(ax, xl, yl)
    fx = _Map(*xl, x0, x0 + w, ax.xaxis.scale == "log")
    ybot, ytop = (y0, y0 + h) if ax.yaxis.inverted else (y0 + h, y0)
    fy = _Map(*yl, ybot, ytop, ax.yaxis.scale == "log")
    out = [f'<g id="ax{k}">']
    clip = f"c{k}"
    out.append(f'<clipPath id="{clip}"><rect x="{x0:.1f}" y="{y0:.1f}" width="{w:.1f}" '
               f'height="{h:.1f}"/></clipPath>')
    xt, xlab = _ticks(ax.xaxis, xl)
    yt, ylab = _ticks(ax.yaxis, yl)
    # grid
    grid = "".join(f"M{p:.1f},{y0:.1f}v{h:.1f}" for p in fx(xt).tolist()) + "".join(
        f"M{x0:.1f},{p:.1f}h{w:.1f}" for p in fy(yt).tolist())
    if grid:
        out.append(f'<path d="{grid}" stroke="#b0b0b0" stroke-opacity="0.3" '
                   'stroke-width="0.8" fill="none"/>')
    body: list[str] = []
    for a in ax.artists:
        body.append(_draw_artist(a, fx, fy, ax.box))
    out.append(f'<g clip-path="url(#{clip})">{"".join(body)}</g>')
    out += [a for a in (_draw_text(t, fx, fy, ax.box) for t in ax.artists
                        if isinstance(t, _Text)) if a]
    # spines, ticks, labels
    out.append(f'<path d="M{x0:.1f},{y0:.1f}V{y0 + h:.1f}H{x0 + w:.1f}" stroke="#000" '
               'stroke-width="1" fill="none"/>')
    fs = 8 * PT
    ticks = "".join(f"M{p:.1f},{y0 + h:.1f}v4.7" for p in fx(xt).tolist()) + "".join(
        f"M{x0:.1f},{p:.1f}h-4.7" for p in fy(yt).tolist())
    if ticks:
        out.append(f'<path d="{ticks}" stroke="#000" stroke-width="1"/>')
    out += [f'<text x="{p:.1f}" y="{y0 + h + 7 + fs * 0.8:.1f}" text-anchor="middle">'
            f"{esc(s)}</text>" for p, s in zip(fx(xt).tolist(), xlab, strict=True)]
    out += [f'<text x="{x0 - 7:.1f}" y="{p + fs * 0.35:.1f}" text-anchor="end">{esc(s)}</text>'
            for p, s in zip(fy(yt).tolist(), ylab, strict=True)]
    tw = max((text_width(s, fs) for s in ylab), default=0.0)
    if ax.xaxis.label:
        out.append(f'<text x="{x0 + w / 2:.1f}" y="{y0 + h + 9 + fs * 1.9:.1f}" '
                   f'text-anchor="middle">{esc(ax.xaxis.label)}</text>')
    if ax.yaxis.label:
        ylx, yly = x0 - 10 - tw - fs * 0.4, y0 + h / 2
        out.append(f'<text x="{ylx:.1f}" y="{yly:.1f}" text-anchor="middle" '
                   f'transform="rotate(-90 {ylx:.1f} {yly:.1f})">{esc(ax.yaxis.label)}</text>')
    if ax.title:
        out.append(f'<text x="{x0 + w / 2:.1f}" y="{y0 - 6:.1f}" text-anchor="middle" '
                   f'font-size="{ax.title_size * PT:.2f}">{esc(ax.title)}</text>')
    if ax.colorbar is not None:
        out.append(_draw_colorbar(ax))
    if ax.legend_ is not None:
        out.append(_draw_legend(ax, fx, fy))
    out.append("</g>")
    return "".join(out)


def _ticks(axis: _Axis, lim: tuple[float, float]) -> tuple[Array, list[str]]:
    lo, hi = min(lim), max(lim)
    if axis.ticks is not None:
        pos, labels = axis.ticks
        keep = [i for i, p in enumerate(pos) if lo - 1e-9 * abs(hi - lo) <= p <= hi + 1e-9
                * abs(hi - lo)]
        return np.array([pos[i] for i in keep]), [labels[i] for i in keep]
    return log_ticks(lo, hi) if axis.scale == "log" else linear_ticks(lo, hi)


Box = tuple[float, float, float, float]


def _draw_line(a: _Line, fx: _Map, fy: _Map, box: Box) -> str:
    px, py = fx(a.x), fy(a.y)
    s = []
    if a.linestyle and px.size:
        d = _polyline(px, py)
        if d:
            s.append(f'<path d="{d}" stroke="{a.color}" stroke-width="{a.lw * PT:.2f}" '
                     f'fill="none" stroke-linejoin="round"{_dash(a.dash)}{_op(a.alpha)}/>')
    if a.marker is not None:
        ok = np.isfinite(px) & np.isfinite(py)
        if ok.any():
            d, fillable = _points_path(px[ok], py[ok], a.marker, a.ms * PT / 2)
            fill = "none" if (a.hollow or not fillable) else a.color
            s.append(f'<path d="{d}" stroke="{a.color}" stroke-width="{a.mew * PT:.2f}" '
                     f'fill="{fill}"{_op(a.alpha)}/>')
    return "".join(s)


def _draw_rects(a: _Rects, fx: _Map, fy: _Map, box: Box) -> str:
    # a bar from 0 on a log axis starts at the axis' edge
    px0 = np.where(fx.log & (a.x0 <= 0), fx.p0, fx(a.x0))
    py0 = np.where(fy.log & (a.y0 <= 0), fy.p0, fy(a.y0))
    px1, py1 = fx(a.x1), fy(a.y1)
    good = np.isfinite(px0) & np.isfinite(px1) & np.isfinite(py0) & np.isfinite(py1)
    cols = np.array(a.colors)
    s = []
    for c in dict.fromkeys(a.colors):
        ok = good & (cols == c)
        if not ok.any():
            continue
        xa, xb = np.minimum(px0[ok], px1[ok]), np.maximum(px0[ok], px1[ok])
        ya, yb = np.minimum(py0[ok], py1[ok]), np.maximum(py0[ok], py1[ok])
        d = "".join(f"M{p:.1f},{q:.1f}h{r:.1f}v{t:.1f}h-{r:.1f}z" for p, q, r, t in
                    zip(xa.tolist(), ya.tolist(), (xb - xa).tolist(), (yb - ya).tolist(),
                        strict=True))
        edge = f' stroke="{a.edge}" stroke-width="0.7"' if a.edge else ""
        s.append(f'<path d="{d}" fill="{c}"{_op(a.alpha, "fill-opacity")}{edge}/>')
        if a.hatch:
            s.append(f'<path d="{d}" fill="url(#hatch)"/>')
    return "".join(s)


def _draw_fill(a: _Fill, fx: _Map, fy: _Map, box: Box) -> str:
    px, p0, p1 = fx(a.x), fy(a.y0), fy(a.y1)
    ok = np.isfinite(px) & np.isfinite(p0) & np.isfinite(p1)
    if not ok.any():
        return ""
    xs = np.concatenate([px[ok], px[ok][::-1]])
    ys = np.concatenate([p1[ok], p0[ok][::-1]])
    return f'<path d="{_polyline(xs, ys)}z" fill="{a.color}"{_op(a.alpha, "fill-opacity")}/>'


def _draw_span(a: _Span, fx: _Map, fy: _Map, box: Box) -> str:
    x0, y0, w, h = box
    if a.color == "none":
        return ""
    if a.axis == "x":
        pa, pb = sorted(fx(np.array([a.a, a.b])).tolist())
        if a.lw > 0:
            return (f'<path d="M{pa:.1f},{y0:.1f}v{h:.1f}" stroke="{a.color}" '
                    f'stroke-width="{a.lw * PT:.2f}"{_dash(a.dash)}/>')
        return (f'<rect x="{pa:.1f}" y="{y0:.1f}" width="{pb - pa:.1f}" height="{h:.1f}" '
                f'fill="{a.color}"{_op(a.alpha, "fill-opacity")}/>')
    (p,) = fy(np.array([a.a])).tolist()
    return (f'<path d="M{x0:.1f},{p:.1f}h{w:.1f}" stroke="{a.color}" '
            f'stroke-width="{a.lw * PT:.2f}"{_dash(a.dash)}/>')


def _draw_colored(a: _Colored, fx: _Map, fy: _Map, box: Box) -> str:
    px, py = fx(a.x), fy(a.y)
    ok = np.isfinite(px) & np.isfinite(py)
    cols = np.array(a.colors)
    s = []
    for c in dict.fromkeys(a.colors):
        sel = ok & (cols == c)
        if sel.any():
            d, _ = _points_path(px[sel], py[sel], "o", a.ms * PT / 2)
            s.append(f'<path d="{d}" fill="{c}"/>')
    return "".join(s)


_DRAW: dict[type, Any] = {_Line: _draw_line, _Rects: _draw_rects, _Fill: _draw_fill,
                          _Span: _draw_span, _Colored: _draw_colored}


def _draw_artist(a: Any, fx: _Map, fy: _Map, box: Box) -> str:
    draw = _DRAW.get(type(a))
    return draw(a, fx, fy, box) if draw is not None else ""


def _draw_text(t: _Text, fx: _Map, fy: _Map, box: tuple[float, float, float, float]) -> str:
    x0, y0, w, h = box
    if t.axes_coords:
        px, py = x0 + t.x * w, y0 + (1 - t.y) * h
    else:
        px, py = float(fx(np.array([t.x]))[0]), float(fy(np.array([t.y]))[0])
    if not (math.isfinite(px) and math.isfinite(py)):
        return ""
    fs = t.size * PT
    dy = {"center": 0.35, "top": 0.8, "bottom": 0.0}.get(t.va, 0.35) * fs
    anchor = {"left": "start", "center": "middle", "right": "end"}.get(t.ha, "start")
    return (f'<text x="{px:.1f}" y="{py + dy:.1f}" text-anchor="{anchor}" '
            f'font-size="{fs:.2f}" fill="{t.color}">{esc(t.s)}</text>')


def _draw_colorbar(ax: Axes) -> str:
    assert ax.colorbar is not None
    vmin, vmax, label = ax.colorbar
    x, y, w, h = ax.box
    bx, bw = x + w / _CB_AXES * 0.76, w / _CB_AXES * 0.035
    f = _Map(vmin, vmax, y + h, y, False) if vmax > vmin else _Map(0, 1, y + h, y, False)
    ticks, labels = linear_ticks(vmin, vmax, 5) if vmax > vmin else (np.zeros(0), [])
    fs = 8 * PT
    out = [f'<rect x="{bx:.1f}" y="{y:.1f}" width="{bw:.1f}" height="{h:.1f}" '
           'fill="url(#cmap)" stroke="#000" stroke-width="0.8"/>']
    out += [f'<path d="M{bx + bw:.1f},{p:.1f}h3.5" stroke="#000"/><text x="{bx + bw + 5:.1f}" '
            f'y="{p + fs * 0.35:.1f}">{esc(s)}</text>'
            for p, s in zip(f(ticks).tolist(), labels, strict=True)]
    lx = bx + bw + 8 + max((text_width(s, fs) for s in labels), default=0) + fs * 1.1
    out.append(f'<text x="{lx:.1f}" y="{y + h / 2:.1f}" text-anchor="middle" '
               f'transform="rotate(-90 {lx:.1f} {y + h / 2:.1f})">{esc(label)}</text>')
    return "".join(out)


def _entries(ax: Axes) -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for a in ax.artists:
        label = getattr(a, "label", None)
        if label:
            out.append((label, a))
    return out


def _best_corner(ax: Axes, fx: _Map, fy: _Map, lw: float, lh: float) -> str:
    x0, y0, w, h = ax.box
    pts = []
    for a in ax.artists:
        if isinstance(a, _Line) and a.x.size:
            px, py = fx(a.x), fy(a.y)
            if a.linestyle and a.x.size > 1:  # points along the segments, not just vertices
                t = np.linspace(0.0, a.x.size - 1.0, 40 * a.x.size)
                idx = np.arange(a.x.size, dtype=float)
                px, py = np.interp(t, idx, px), np.interp(t, idx, py)
            pts.append((px, py))
    if not pts:
        return "upper right"
    px = np.concatenate([p[0] for p in pts])
    py = np.concatenate([p[1] for p in pts])
    best, score = "upper right", math.inf
    for loc in ("upper right", "upper left", "lower left", "lower right"):
        lx = x0 + w - lw - 4 if "right" in loc else x0 + 4
        ly = y0 + 4 if "upper" in loc else y0 + h - lh - 4
        n = int(np.sum((px >= lx) & (px <= lx + lw) & (py >= ly) & (py <= ly + lh)))
        if n < score:
            best, score = loc, n
    return best


def _draw_legend(ax: Axes, fx: _Map, fy: _Map) -> str:
    assert ax.legend_ is not None
    entries = _entries(ax)
    if not entries:
        return ""
    lg = ax.legend_
    fs = lg.size * PT
    ncol = max(1, min(lg.ncol, len(entries)))
    nrow = -(-len(entries) // ncol)
    sw = 2.0 * fs  # swatch
    colw = sw + 6 + max(text_width(s, fs) for s, _ in entries) + 10
    lw, lh = ncol * colw, nrow * fs * 1.45
    x0, y0, w, h = ax.box
    loc = lg.loc if lg.loc != "best" else _best_corner(ax, fx, fy, lw, lh)
    if loc == "above":
        lx, ly = x0 + (w - lw) / 2, y0 - lh - 2
    elif loc == "below":
        lx, ly = x0 + (w - lw) / 2, y0 + h + 8 + 8 * PT * 2.4
    else:
        lx = x0 + w - lw - 4 if "right" in loc else x0 + 4
        ly = y0 + 4 if "upper" in loc else y0 + h - lh - 4
    out = []
    for i, (label, a) in enumerate(entries):
        r, c = divmod(i, ncol)
        ex, ey = lx + c * colw, ly + r * fs * 1.45 + fs * 0.75
        out.append(_swatch(a, ex, ey, sw))
        out.append(f'<text x="{ex + sw + 5:.1f}" y="{ey + fs * 0.35:.1f}" '
                   f'font-size="{fs:.2f}">{esc(label)}</text>')
    return "".join(out)


def _swatch(a: Any, x: float, y: float, sw: float) -> str:
    if isinstance(a, _Line):
        s = ""
        if a.linestyle:
            s += (f'<path d="M{x:.1f},{y:.1f}h{sw:.1f}" stroke="{a.color}" '
                  f'stroke-width="{a.lw * PT:.2f}"{_dash(a.dash)}/>')
        if a.marker is not None:
            d, fillable = _points_path(np.array([x + sw / 2]), np.array([y]), a.marker,
                                       a.ms * PT / 2)
            fill = "none" if (a.hollow or not fillable) else a.color
            s += (f'<path d="{d}" stroke="{a.color}" stroke-width="{a.mew * PT:.2f}" '
                  f'fill="{fill}"/>')
        return s
    if isinstance(a, _Rects):
        hatch = (f'<rect x="{x:.1f}" y="{y - 4:.1f}" width="{sw:.1f}" height="8" '
                 'fill="url(#hatch)"/>' if a.hatch else "")
        return (f'<rect x="{x:.1f}" y="{y - 4:.1f}" width="{sw:.1f}" height="8" '
                f'fill="{a.colors[0] if a.colors else "#888"}"{_op(a.alpha, "fill-opacity")}/>'
                + hatch)
    if isinstance(a, _Span):
        return (f'<path d="M{x:.1f},{y:.1f}h{sw:.1f}" stroke="{a.color}" '
                f'stroke-width="{a.lw * PT:.2f}"{_dash(a.dash)}/>')
    return ""
