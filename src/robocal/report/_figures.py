"""The report's plots: matplotlib figures rendered off-screen (Agg) into base64 PNG data URIs.

No pyplot, no global backend switch: each figure is a :class:`matplotlib.figure.Figure` drawn
on its own :class:`~matplotlib.backends.backend_agg.FigureCanvasAgg`, so nothing ever needs
a display and callers' matplotlib state is left alone.
"""

from __future__ import annotations

import base64
import io
import math
import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import AutoLocator, LogFormatter, LogLocator, MaxNLocator, NullLocator
from numpy.typing import NDArray

from robocal.report._analysis import SETS, Analysis
from robocal.report._coverage import Coverage
from robocal.report._metrics import IsoResult, JointCurves, Workspace

if TYPE_CHECKING:
    from matplotlib.typing import RcKeyType

Array = NDArray[np.float64]
DPI = 96
WIDE = 11.8  # inches: the page's content width at 96 dpi
COLORS = {"nominal": "#7f7f7f", "cpa": "#9467bd", "cpa-classical": "#c5b0d5",
          "constant": "#ff7f0e", "high-order": "#1f77b4", "auto": "#2ca02c"}
_EXTRA = ("#8c564b", "#e377c2", "#17becf", "#bcbd22", "#d62728")
# Markers tell the models apart where colours alone do not (grey/purple, blue/green, print).
MARKERS = {"nominal": "o", "cpa": "v", "cpa-classical": "<", "constant": "s",
           "high-order": "^", "auto": "x"}
_EXTRA_MARKERS = ("D", "P", "*", "h", "<")
COMP_COLORS = {"dx": "#1f77b4", "dy": "#ff7f0e", "dz": "#2ca02c",
               "ex": "#1f77b4", "ey": "#ff7f0e", "ez": "#2ca02c"}
COMP_LABEL = {"dx": "δx", "dy": "δy", "dz": "δz", "ex": "εx", "ey": "εy", "ez": "εz"}
# A fixed title height (no search for the tick labels above the axes) and PNGs compressed
# for speed rather than size (level 6 costs ~3x the time of level 1 for ~15 % fewer bytes).
_RC: dict[RcKeyType, Any] = {
    "font.size": 8.5, "axes.titlesize": 9.5, "axes.labelsize": 8.5, "legend.fontsize": 7.5,
    "xtick.labelsize": 8, "ytick.labelsize": 8, "axes.titley": 1.0}
_PNG = {"compress_level": 1}


@dataclass(frozen=True)
class Plot:
    """A rendered figure: PNG data URI, pixel size and a text alternative."""

    key: str
    uri: str
    width: int
    height: int
    alt: str


def color(name: str, i: int = 0) -> str:
    """Colour of a model name."""
    return COLORS.get(name, _EXTRA[i % len(_EXTRA)])


def marker(name: str, i: int = 0) -> str:
    """Marker of a model name."""
    return MARKERS.get(name, _EXTRA_MARKERS[i % len(_EXTRA_MARKERS)])


def _hollow(mk: str) -> dict[str, Any]:
    """Open markers where the marker has an inside, so overlapping points stay visible."""
    return {} if mk in ("x", "+", "P", "*") else {"markerfacecolor": "none"}


def _new(w: float, h: float, margins: tuple[float, float, float, float], *,
         wspace: float = 0.3, hspace: float = 0.5) -> Figure:
    """A figure on its own Agg canvas, laid out by fixed ``margins`` (left, right, bottom,
    top; inches): no constrained or tight layout, whose text measurements cost more than
    drawing the figure."""
    fig = Figure(figsize=(w, h), dpi=DPI)
    FigureCanvasAgg(fig)
    left, right, bottom, top = margins
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h,
                        top=1 - top / h, wspace=wspace, hspace=hspace)
    return fig


def _render(key: str, fig: Figure, alt: str) -> Plot:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, pil_kwargs=_PNG)
    data = buf.getvalue()
    w, h = struct.unpack(">II", data[16:24])  # the PNG IHDR chunk: width, height
    uri = "data:image/png;base64," + base64.b64encode(data).decode("ascii")
    return Plot(key, uri, w, h, alt)


class _PlainLog(LogFormatter):
    """Log-axis tick labels as plain numbers ("0.01", not mathtext 10^-2: the mathtext
    parser costs more than the rest of a figure)."""

    def _num_to_string(self, x: float, vmin: float, vmax: float) -> str:
        return f"{x:g}"


def _style(fig: Figure) -> None:
    for ax in fig.axes:
        ax.grid(True, alpha=0.3, linewidth=0.6)
        for s in ("top", "right"):
            ax.spines[s].set_visible(False)
        for axis, lim in ((ax.xaxis, ax.get_xlim), (ax.yaxis, ax.get_ylim)):
            # Every tick is a handful of artists (a third of a figure's time): at most ~6
            # labelled values per axis, minor log ticks only where few decades show.
            if axis.get_scale() == "log":
                lo, hi = sorted(v for v in lim())
                few = hi <= 100 * lo
                axis.set_major_formatter(_PlainLog())
                axis.set_minor_locator(LogLocator(subs=(2.0, 5.0)) if few else NullLocator())
                axis.set_minor_formatter(_PlainLog(labelOnlyBase=False,
                                                   minor_thresholds=(2, 0.5)))
            elif type(axis.get_major_locator()) is AutoLocator:
                axis.set_major_locator(MaxNLocator(nbins=6, steps=[1, 2, 2.5, 5, 10]))


def render_all(an: Analysis) -> dict[str, Plot]:
    """Every plot the analysis supports, by key."""
    import matplotlib

    out: dict[str, Plot] = {}
    with matplotlib.rc_context(_RC):
        p = summary_plot(an)
        if p:
            out[p.key] = p
        if an.data and any(s.norms is not None for m in an.models.values()
                           for s in m.sets.values()):
            out["histograms"] = histograms(an)
            out["per_pose"] = per_pose(an)
        shared: JointFigure | None = None
        for jc in an.joints:
            if shared is None:
                shared = JointFigure(any(an.data.get(w) is not None for w in SETS))
            out[f"joint{jc.joint + 1}"] = joint_plot(an, jc, shared)
        if an.ident is not None and an.ident.singular_values is not None:
            out["singular_values"] = singular_values(an)
        if an.work is not None:
            out["workspace"] = workspace_plot(an, an.work)
        if an.coverage is not None:
            out["coverage"] = coverage_plot(an.coverage)
        if an.iso:
            out["iso"] = iso_plot(an.iso)
        out.update({p.key: p for p in thermal_plots(an)})
    return out


def needs_log_axis(values: Array, ratio: float = 20.0) -> bool:
    """True when the positive finite ``values`` span more than ``ratio`` (then a linear axis
    would shrink the small bars to nothing)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v) & (v > 0)]
    return bool(v.size) and float(v.max()) / float(v.min()) > ratio


def summary_plot(an: Analysis) -> Plot | None:
    """Grouped bars: RMS error per model on calibration and validation poses."""
    rows = [(name, m) for name, m in an.models.items() if m.sets]
    if not rows:
        return None
    # the left margin fits the longest model name (~0.07 in per character at 8 pt)
    left = 0.2 + 0.07 * max(len(n) for n, _ in rows)
    fig = _new(4.6, 0.42 * len(rows) + 0.9, (left, 0.15, 0.45, 0.3))
    ax = fig.add_subplot()
    y = np.arange(len(rows))
    h = 0.38
    sets = (("calibration", -h / 2, 0.55), ("validation", h / 2, 1.0))
    table = [np.array([st.rms_m * 1e3 if which in m.sets and (st := m.sets[which].stats)
                       else np.nan for _, m in rows]) for which, _, _ in sets]
    shown = np.concatenate(table)
    shown = shown[np.isfinite(shown) & (shown > 0)]
    vmax = float(shown.max()) if shown.size else 0.0
    # a calibrated 0.009 mm next to a nominal 2.5 mm: a log axis keeps both visible
    log = needs_log_axis(shown)
    floor = float(shown.min()) / 3 if log else 0.0
    for k, ((which, off, alpha), vals) in enumerate(zip(sets, table, strict=True)):
        cols = [color(n, i) for i, (n, _) in enumerate(rows)]
        ax.barh(y + off, vals - floor, left=floor, height=h, color=cols, alpha=alpha,
                hatch=None if k else "///", edgecolor="white", linewidth=0.5,
                label=which)
        for yi, v in zip(y + off, vals, strict=True):
            if np.isfinite(v):
                ax.text(v, yi, f" {v:.3f}", va="center", fontsize=7.5)
    ax.set_yticks(y, [n for n, _ in rows])
    ax.invert_yaxis()
    if log:
        ax.set_xscale("log")
        ax.set_xlim(floor, vmax * 4)
        ax.set_xlabel("RMS position error (mm, log scale)")
    else:
        ax.set_xlim(0, vmax * 1.25 if vmax > 0 else 1)
        ax.set_xlabel("RMS position error (mm)")
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2, frameon=False)
    _style(fig)
    alt = "RMS error per model: " + "; ".join(
        f"{n} " + ", ".join(f"{w} {st.rms_m * 1e3:.3f} mm" for w in SETS
                            if w in m.sets and (st := m.sets[w].stats)) for n, m in rows)
    return _render("summary", fig, alt)


def _bins(an: Analysis) -> Array:
    vals = np.concatenate([s.norms[s.norms > 0] for m in an.models.values()
                           for s in m.sets.values() if s.norms is not None])
    lo = max(float(np.min(vals)), 1e-7) if vals.size else 1e-6
    hi = float(np.max(vals)) if vals.size else 1e-3
    return np.geomspace(lo * 0.9, hi * 1.1, 40) * 1e3


def histograms(an: Analysis) -> Plot:
    """Histograms of |measured - model| per model, calibration and validation side by side."""
    sets = [w for w in SETS if w in an.data]
    fig = _new(WIDE, 2.9, (0.6, 0.1, 0.45, 0.3), wspace=0.18)
    axes = fig.subplots(1, len(sets), squeeze=False, sharey=False)[0]
    bins = _bins(an)
    for ax, which in zip(axes, sets, strict=True):
        for i, (name, m) in enumerate(an.models.items()):
            s = m.sets.get(which)
            if s is None or s.norms is None:
                continue
            d = s.norms[s.inlier] * 1e3 if s.inlier is not None else s.norms * 1e3
            ax.hist(d, bins=bins, histtype="step", linewidth=1.6, color=color(name, i),
                    label=f"{name} (RMS {s.stats.rms_m * 1e3:.3f})" if s.stats else name)
        ax.set_xscale("log")
        ax.set_xlabel("position error |measured − model| (mm, log scale)")
        ax.set_ylabel("poses")
        ax.set_title(f"{which} poses (n = {len(an.data[which])})")
        ax.legend(frameon=False)  # "best" is cheap here: a step outline has few vertices
    _style(fig)
    return _render("histograms", fig, "Histograms of the position error of each model on "
                                      "calibration and validation poses")


def per_pose(an: Analysis) -> Plot:
    """Error magnitude per pose and model (log scale); outliers marked."""
    sets = [w for w in SETS if w in an.data]
    fig = _new(WIDE, 2.6 * len(sets), (0.65, 0.1, 0.45, 0.35), hspace=0.55)
    axes = fig.subplots(len(sets), 1, squeeze=False)[:, 0]
    for ax, which in zip(axes, sets, strict=True):
        for i, (name, m) in enumerate(an.models.items()):
            s = m.sets.get(which)
            if s is None or s.norms is None:
                continue
            idx = np.arange(s.norms.size)
            mk = marker(name, i)
            ax.plot(idx, s.norms * 1e3, mk, ms=3.4, mew=0.8, color=color(name, i),
                    label=name, alpha=0.85, **_hollow(mk))
            if s.inlier is not None and (~s.inlier).any() and name == (an.selected or name):
                ax.plot(idx[~s.inlier], s.norms[~s.inlier] * 1e3, "x", ms=7, mew=1.6,
                        color="#d62728", label="rejected outlier")
        ax.set_yscale("log")
        ax.set_ylabel("error (mm, log)")
        ax.set_xlabel(f"{which} pose (measurement order)")
        ax.legend(frameon=False, ncol=6, loc="upper center", bbox_to_anchor=(0.5, 1.16))
    _style(fig)
    return _render("per_pose", fig, "Position error per pose for every model")


class JointFigure:
    """The figure of the joint plots, built once and reused for every joint: creating the
    axes, their ticks and spines is ~40 % of a joint plot, so each joint replaces only the
    data artists and legends (``with_data``: the residual panel is there)."""

    def __init__(self, with_data: bool) -> None:
        # legends go below the axes (never over the curves); the left margin fits "-0.075"
        self.fig = _new(WIDE, 3.3, (0.8, 0.15, 1.0, 0.3), wspace=0.4)
        self.axes = self.fig.subplots(1, 3 if with_data else 2)
        self.with_data = with_data

    def clear(self) -> None:
        """Remove the previous joint's data and legends; the next artists set the limits."""
        for ax in self.axes:
            for artist in [*ax.lines, *ax.collections, *ax.patches, *ax.texts]:
                artist.remove()
            legend = ax.get_legend()
            if legend is not None:
                legend.remove()
            ax.ignore_existing_data_limits = True
            ax.relim()  # nothing left: resets the data limits; new artists extend them


def joint_plot(an: Analysis, jc: JointCurves, into: JointFigure | None = None) -> Plot:
    """One joint: translation and rotation error terms with ±2σ bands, residuals vs angle.
    ``into``: a :class:`JointFigure` to draw into (cleared first), else a new one."""
    with_data = any(an.data.get(w) is not None for w in SETS)
    if into is None or into.with_data != with_data:
        into = JointFigure(with_data)
    else:
        into.clear()
    fig, axes = into.fig, into.axes
    ang = np.degrees(jc.angle)
    for ax, kind, scale, unit in ((axes[0], "d", 1e3, "mm"), (axes[1], "e", 180 / math.pi,
                                                               "deg")):
        shown = False
        for c in jc.curves:
            if not c.component.startswith(kind):
                continue
            col = COMP_COLORS[c.component]
            ax.plot(ang, c.value * scale, color=col, linewidth=1.4,
                    label=f"{COMP_LABEL[c.component]} ({c.n_terms} terms)")
            if c.sigma is not None:
                ax.fill_between(ang, (c.value - 2 * c.sigma) * scale,
                                (c.value + 2 * c.sigma) * scale, color=col, alpha=0.18,
                                linewidth=0)
            shown = True
        _shade_uncovered(ax, jc)
        ax.set_xlabel(f"joint {jc.joint + 1} (deg)")
        ax.set_ylabel(f"error ({unit})")
        ax.set_title("translation δ (about its mean) ±2σ" if kind == "d"
                     else "rotation ε (about its mean) ±2σ")
        if shown:
            ax.legend(fontsize=7, frameon=False, loc="upper center",
                      bbox_to_anchor=(0.5, -0.2), ncol=3)
        else:
            ax.text(0.5, 0.5, "no joint-dependent terms", transform=ax.transAxes,
                    ha="center", va="center", color="#777")
    if not with_data:  # a report from a model file alone: no empty residual panel
        _style(fig)
        return _render(f"joint{jc.joint + 1}", fig,
                       f"Joint {jc.joint + 1}: identified joint-dependent errors with 2-sigma "
                       "bands")
    ax = axes[2]
    for i, name in enumerate(dict.fromkeys(["constant", an.joint_model, an.selected])):
        m = an.models.get(name) if name else None
        if not name or m is None:
            continue
        for which, size, alpha in (("calibration", 3.2, 0.55), ("validation", 4.5, 0.95)):
            s = m.sets.get(which)
            d = an.data.get(which)
            if s is None or s.norms is None or d is None:
                continue
            ok = s.inlier if s.inlier is not None else np.ones(s.norms.size, dtype=bool)
            mk = marker(name, i)
            ax.plot(np.degrees(d.q[ok, jc.joint]), s.norms[ok] * 1e3, mk, ms=size, mew=0.8,
                    color=color(name, i), alpha=alpha, label=f"{name}, {which[:3]}.",
                    **_hollow(mk))
            if name == an.selected and (~ok).any():
                ax.plot(np.degrees(d.q[~ok, jc.joint]), s.norms[~ok] * 1e3, "x", ms=6,
                        mew=1.4, color="#d62728")
    ax.set_yscale("log")
    ax.set_xlabel(f"joint {jc.joint + 1} (deg)")
    ax.set_ylabel("|residual| (mm, log)")
    ax.set_title("residuals vs joint angle")
    if ax.lines:
        ax.legend(fontsize=7, ncol=2, frameon=False, loc="upper center",
                  bbox_to_anchor=(0.5, -0.2))
    else:
        ax.text(0.5, 0.5, "no measurements of these poses", transform=ax.transAxes,
                ha="center", va="center", color="#777")
    _style(fig)
    return _render(f"joint{jc.joint + 1}", fig,
                   f"Joint {jc.joint + 1}: identified joint-dependent errors with 2-sigma bands "
                   f"and residuals against the joint angle")


def _shade_uncovered(ax: object, jc: JointCurves) -> None:
    if jc.covered is None:
        return
    lo, hi = np.degrees(jc.angle[[0, -1]])
    clo, chi = np.degrees(jc.covered)
    for a, b in ((lo, clo), (chi, hi)):
        if b > a:
            ax.axvspan(a, b, color="#000", alpha=0.06, linewidth=0)  # type: ignore[attr-defined]


def singular_values(an: Analysis) -> Plot:
    """Normalised singular values of the scaled identification Jacobian."""
    assert an.ident is not None and an.ident.singular_values is not None
    s = an.ident.singular_values
    rank = an.ident.rank if an.ident.rank is not None else s.size
    fig = _new(5.2, 2.6, (0.7, 0.1, 0.45, 0.3))
    ax = fig.add_subplot()
    rel = np.maximum(s / s[0], np.finfo(float).tiny)  # exact zeros cannot sit on a log axis
    k = np.arange(1, s.size + 1)
    ax.semilogy(k[:rank], rel[:rank], ".-", ms=3, color="#1f77b4", linewidth=0.8,
                label=f"identified ({rank})")
    if rank < s.size:
        ax.semilogy(k[rank:], rel[rank:], "x", ms=3, color="#d62728",
                    label=f"removed ({s.size - rank})")
        ax.axvline(rank + 0.5, color="#888", linewidth=0.6, linestyle="--")
        ax.legend(loc="lower left", fontsize=7, frameon=False)
    ax.set_xlabel("index")
    ax.set_ylabel("σ_k / σ_1")
    cond = "–" if an.ident.condition is None else f"{an.ident.condition:.3g}"
    ax.set_title(f"rank {rank} of {s.size} parameters, cond {cond}", fontsize=9)
    _style(fig)
    return _render("singular_values", fig, "Singular values of the identification Jacobian")


def workspace_plot(an: Analysis, w: Workspace) -> Plot:
    """Histogram of predicted 1σ uncertainty, and top/side maps in the robot base frame."""
    assert an.selected is not None
    cm = an.models[an.selected].entry.calibrated
    assert cm is not None
    T = cm.model.base_transform(cm.params)
    pb = (w.position - T[:3, 3]) @ T[:3, :3] * 1e3
    s = w.sigma * 1e3
    fig = _new(WIDE, 2.9, (0.65, 0.1, 0.45, 0.3), wspace=0.35)
    axes = fig.subplots(1, 3)
    axes[0].hist(s, bins=40, color="#1f77b4", alpha=0.8)
    axes[0].set_xlabel("predicted 1σ position uncertainty (mm)")
    axes[0].set_ylabel("configurations")
    axes[0].set_title(f"{s.size} random configurations, {w.within}")
    order = np.argsort(s)
    for ax, (i, j, lab) in zip(axes[1:], ((0, 1, "top view: x–y"), (0, 2, "side view: x–z")),
                               strict=True):
        sc = ax.scatter(pb[order, i], pb[order, j], c=s[order], s=6, cmap="viridis")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{'xyz'[i]} base (mm)")
        ax.set_ylabel(f"{'xyz'[j]} base (mm)")
        ax.set_title(lab)
    fig.colorbar(sc, ax=axes[2], label="1σ (mm)")
    _style(fig)
    return _render("workspace", fig, "Predicted position uncertainty over the workspace")


def coverage_plot(cov: Coverage) -> Plot:
    """Per joint: robot limits (grey), calibrated range (blue), measured range (black line)
    and the program's targets (orange ticks; red outside the calibrated range)."""
    n = len(cov.rows)
    fig = _new(WIDE, 0.36 * n + 0.9, (0.5, 0.15, 0.45, 0.3))
    ax = fig.add_subplot()
    for k, r in enumerate(cov.rows):
        y = n - 1 - k
        lo, hi = r.limits_deg
        ax.barh(y, hi - lo, left=lo, height=0.7, color="#e0e0e0")
        if r.calibrated_deg is not None:
            c0, c1 = r.calibrated_deg
            ax.barh(y, c1 - c0, left=c0, height=0.45, color="#1f77b4", alpha=0.7)
        if r.measured_deg is not None:
            ax.plot(r.measured_deg, [y, y], color="black", linewidth=1.2)
        if cov.targets is not None:
            t = np.degrees(cov.targets[:, k])
            out = ((t < r.calibrated_deg[0]) | (t > r.calibrated_deg[1])
                   if r.calibrated_deg is not None else np.zeros(t.size, dtype=bool))
            ax.scatter(t[~out], np.full(int((~out).sum()), y), marker="|", s=60,
                       color="#ff7f0e", linewidths=1.0)
            ax.scatter(t[out], np.full(int(out.sum()), y), marker="|", s=80,
                       color="#d62728", linewidths=1.4)
    ax.set_yticks(range(n), [f"J{r.joint}" for r in reversed(cov.rows)])
    ax.set_xlabel("joint value (deg)")
    title = "grey: limits, blue: calibrated range, black: measured"
    if cov.targets is not None:
        title += f", ticks: {len(cov.targets)} program targets ({cov.outside} outside, red)"
    ax.set_title(title, fontsize=9)
    _style(fig)
    return _render("coverage", fig, "Per-joint coverage with the program targets")


def iso_plot(iso: list[IsoResult]) -> Plot:
    """AP (and AP after calibration when known) and RP per ISO pose; log scale when the
    values span more than a decade."""
    fig = _new(5.2, 2.5, (0.6, 0.1, 0.3, 0.3))
    ax = fig.add_subplot()
    x = np.arange(len(iso))
    after = any(r.ap_model_m is not None for r in iso)
    bars = [("AP", [r.ap_m for r in iso], "#1f77b4")]
    if after:
        bars.append(("AP after calibration",
                     [np.nan if r.ap_model_m is None else r.ap_model_m for r in iso], "#2ca02c"))
    if any(r.rp_m is not None for r in iso):
        bars.append(("RP", [np.nan if r.rp_m is None else r.rp_m for r in iso], "#ff7f0e"))
    w = 0.8 / len(bars)
    vals = []
    for k, (label, v, col) in enumerate(bars):
        mmv = np.array(v, dtype=float) * 1e3
        vals.append(mmv)
        ax.bar(x + (k - (len(bars) - 1) / 2) * w, mmv, w, label=label, color=col)
    if needs_log_axis(np.concatenate(vals)):
        ax.set_yscale("log")
    ax.set_xticks(x, [r.name for r in iso])
    ax.set_ylabel("mm")
    # above the axes, never over the bars
    ax.legend(frameon=False, fontsize=7, ncol=len(bars), loc="lower center",
              bbox_to_anchor=(0.5, 1.0))
    _style(fig)
    return _render("iso", fig, "ISO 9283 pose accuracy and repeatability per pose")


def _temperature_series(an: Analysis) -> tuple[Array, Array, str] | None:
    """Joint temperatures (n, dof) °C against time (n,) and the axis label: the measurement
    log's series (minutes since the first measurement), else the calibration poses' in
    measurement order; None without temperatures."""
    lg = an.inp.log
    if lg is not None and len(lg.joint_temps) > 1:
        t = np.asarray(lg.joint_temps_t_s, dtype=float)
        temps = np.asarray(lg.joint_temps, dtype=float)
        if t.shape == (temps.shape[0],):
            return t / 60.0, temps, "time since the first measurement (min)"
    cal = an.inp.calibration
    if cal is not None and cal.temps is not None and len(cal) > 1:
        return (np.arange(len(cal), dtype=float), cal.temps,
                "calibration pose (measurement order)")
    return None


def thermal_plots(an: Analysis) -> list[Plot]:
    """Joint temperature against time, and the selected model's error against the mean
    joint temperature of each pose (ADR 0042); none when the data has no temperatures."""
    out: list[Plot] = []
    series = _temperature_series(an)
    if series is not None:
        t, temps, label = series
        fig = _new(WIDE, 2.8, (0.65, 0.1, 0.45, 0.35))
        ax = fig.add_subplot(1, 1, 1)
        for j in range(temps.shape[1]):
            ax.plot(t, temps[:, j], "-", lw=1.2, color=f"C{j % 10}", label=f"J{j + 1}")
        ax.set_xlabel(label)
        ax.set_ylabel("joint temperature (°C)")
        ax.legend(frameon=False, ncol=temps.shape[1], loc="upper center",
                  bbox_to_anchor=(0.5, 1.16))
        _style(fig)
        out.append(_render("temperatures", fig, "Joint temperatures against time"))
    sel = an.models.get(an.selected) if an.selected else None
    sets = [(w, an.data[w], sel.sets[w]) for w in SETS if sel is not None
            and w in an.data and an.data[w].temps is not None and w in sel.sets
            and sel.sets[w].norms is not None]
    if sets:
        fig = _new(WIDE / 2, 3.0, (0.65, 0.1, 0.45, 0.35))
        ax = fig.add_subplot(1, 1, 1)
        for i, (which, ds, res) in enumerate(sets):
            assert ds.temps is not None and res.norms is not None
            ax.plot(ds.temps.mean(axis=1), res.norms * 1e3, "os"[i], ms=3.4, mew=0.8,
                    markerfacecolor="none", color=_EXTRA[i], label=which)
        ax.set_xlabel("mean joint temperature of the pose (°C)")
        ax.set_ylabel(f"{an.selected} error (mm)")
        ax.legend(frameon=False, ncol=2, loc="upper center", bbox_to_anchor=(0.5, 1.16))
        _style(fig)
        out.append(_render("residual_temperature", fig,
                           "Position error of the selected model against temperature"))
    return out
