"""The report's plots: inline SVG drawn by :mod:`robocal.report._svg` (ADR 0049).

Each figure keeps the layout of the matplotlib figures it replaced (sizes and margins in
inches at 96 px per inch) and its content: the same series, labels, legends, alt text and
log-axis decisions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal.report._analysis import SETS, Analysis
from robocal.report._coverage import Coverage
from robocal.report._metrics import IsoResult, JointCurves, Workspace
from robocal.report._svg import PX, TAB10, Axes, Figure, viridis

Array = NDArray[np.float64]
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
_PT = PX / 72  # px per typographic point (marker sizes and line widths were in points)


@dataclass(frozen=True)
class Plot:
    """A rendered figure: ``<svg>`` markup, pixel size and a text alternative."""

    key: str
    svg: str
    width: int
    height: int
    alt: str


def color(name: str, i: int = 0) -> str:
    """Colour of a model name."""
    return COLORS.get(name, _EXTRA[i % len(_EXTRA)])


def marker(name: str, i: int = 0) -> str:
    """Marker of a model name."""
    return MARKERS.get(name, _EXTRA_MARKERS[i % len(_EXTRA_MARKERS)])


def _ms(points: float) -> float:
    """Marker radius (px) of a marker ``points`` wide."""
    return points * _PT / 2


def new_figure(w: float, h: float) -> Figure:
    """A figure of ``w`` x ``h`` inches."""
    return Figure(round(w * PX), round(h * PX))


def grid(fig: Figure, rows: int, cols: int, margins: tuple[float, float, float, float], *,
         wspace: float = 0.3, hspace: float = 0.5) -> list[Axes]:
    """Axes in ``rows`` x ``cols`` inside ``margins`` (left, right, bottom, top; inches)."""
    return fig.subplots(rows, cols, tuple(m * PX for m in margins),  # type: ignore[arg-type]
                        wspace=wspace, hspace=hspace)


def render(key: str, fig: Figure, alt: str) -> Plot:
    """The figure as a :class:`Plot`."""
    return Plot(key, fig.svg(key, alt), int(fig.width), int(fig.height), alt)


def render_all(an: Analysis) -> dict[str, Plot]:
    """Every plot the analysis supports, by key."""
    out: dict[str, Plot] = {}
    p = summary_plot(an)
    if p:
        out[p.key] = p
    if an.data and any(s.norms is not None for m in an.models.values()
                       for s in m.sets.values()):
        out["histograms"] = histograms(an)
        out["per_pose"] = per_pose(an)
    for jc in an.joints:
        out[f"joint{jc.joint + 1}"] = joint_plot(an, jc)
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
    # the left margin fits the longest model name (~0.075 in per character at 8 pt)
    left = 0.25 + 0.075 * max(len(n) for n, _ in rows)
    fig = new_figure(4.6, 0.42 * len(rows) + 0.9)
    (ax,) = grid(fig, 1, 1, (left, 0.15, 0.45, 0.3))
    y = np.arange(len(rows), dtype=float)
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
    cols = [color(n, i) for i, (n, _) in enumerate(rows)]
    for k, ((which, off, alpha), vals) in enumerate(zip(sets, table, strict=True)):
        ax.barh(y + off, floor, vals, h, cols, alpha=alpha, hatch=not k, label=which)
        for yi, v in zip((y + off).tolist(), vals.tolist(), strict=True):
            if math.isfinite(v):
                ax.text(v, yi, f" {v:.3f}", size=10)
    ax.set_yticks(y, [n for n, _ in rows])
    ax.y_inverted = True
    ax.ylim = (-0.5, len(rows) - 0.5)
    if log:
        ax.xscale = "log"
        ax.xlim = (floor, vmax * 4)
        ax.xlabel = "RMS position error (mm, log scale)"
    else:
        ax.xlim = (0, vmax * 1.25 if vmax > 0 else 1)
        ax.xlabel = "RMS position error (mm)"
    ax.legend("above", ncol=2)
    alt = "RMS error per model: " + "; ".join(
        f"{n} " + ", ".join(f"{w} {st.rms_m * 1e3:.3f} mm" for w in SETS
                            if w in m.sets and (st := m.sets[w].stats)) for n, m in rows)
    return render("summary", fig, alt)


def _bins(an: Analysis) -> Array:
    vals = np.concatenate([s.norms[s.norms > 0] for m in an.models.values()
                           for s in m.sets.values() if s.norms is not None])
    lo = max(float(np.min(vals)), 1e-7) if vals.size else 1e-6
    hi = float(np.max(vals)) if vals.size else 1e-3
    return np.geomspace(lo * 0.9, hi * 1.1, 40) * 1e3


def histograms(an: Analysis) -> Plot:
    """Histograms of |measured - model| per model, calibration and validation side by side."""
    sets = [w for w in SETS if w in an.data]
    fig = new_figure(WIDE, 2.9)
    axes = grid(fig, 1, len(sets), (0.6, 0.1, 0.45, 0.3), wspace=0.18)
    bins = _bins(an)
    for ax, which in zip(axes, sets, strict=True):
        for i, (name, m) in enumerate(an.models.items()):
            s = m.sets.get(which)
            if s is None or s.norms is None:
                continue
            d = s.norms[s.inlier] * 1e3 if s.inlier is not None else s.norms * 1e3
            ax.step_hist(d, bins, color(name, i), width=1.6 * _PT,
                         label=f"{name} (RMS {s.stats.rms_m * 1e3:.3f})" if s.stats else name)
        ax.xscale = "log"
        ax.xlim = (float(bins[0]), float(bins[-1]))
        ax.xlabel = "position error |measured − model| (mm, log scale)"
        ax.ylabel = "poses"
        ax.title = f"{which} poses (n = {len(an.data[which])})"
        ax.legend("best")
    return render("histograms", fig, "Histograms of the position error of each model on "
                                     "calibration and validation poses")


def per_pose(an: Analysis) -> Plot:
    """Error magnitude per pose and model (log scale); outliers marked."""
    sets = [w for w in SETS if w in an.data]
    fig = new_figure(WIDE, 2.6 * len(sets))
    axes = grid(fig, len(sets), 1, (0.65, 0.1, 0.45, 0.35), hspace=0.55)
    for ax, which in zip(axes, sets, strict=True):
        for i, (name, m) in enumerate(an.models.items()):
            s = m.sets.get(which)
            if s is None or s.norms is None:
                continue
            idx = np.arange(s.norms.size, dtype=float)
            ax.markers(idx, s.norms * 1e3, color(name, i), marker(name, i), size=_ms(3.4),
                       width=0.8 * _PT, alpha=0.85, label=name)
            if s.inlier is not None and (~s.inlier).any() and name == (an.selected or name):
                ax.markers(idx[~s.inlier], s.norms[~s.inlier] * 1e3, "#d62728", "x",
                           size=_ms(7), width=1.6 * _PT, label="rejected outlier")
        ax.yscale = "log"
        ax.ylabel = "error (mm, log)"
        ax.xlabel = f"{which} pose (measurement order)"
        ax.legend("above", ncol=7)
    return render("per_pose", fig, "Position error per pose for every model")


def joint_plot(an: Analysis, jc: JointCurves) -> Plot:
    """One joint: translation and rotation error terms with ±2σ bands, residuals vs angle."""
    with_data = any(an.data.get(w) is not None for w in SETS)
    fig = new_figure(WIDE, 3.3)
    # legends go below the axes (never over the curves)
    axes = grid(fig, 1, 3 if with_data else 2, (0.8, 0.15, 1.0, 0.3), wspace=0.4)
    ang = np.degrees(jc.angle)
    for ax, kind, scale, unit in ((axes[0], "d", 1e3, "mm"), (axes[1], "e", 180 / math.pi,
                                                               "deg")):
        shown = False
        for c in jc.curves:
            if not c.component.startswith(kind):
                continue
            col = COMP_COLORS[c.component]
            if c.sigma is not None:
                ax.band(ang, (c.value - 2 * c.sigma) * scale, (c.value + 2 * c.sigma) * scale,
                        col, alpha=0.18)
            ax.line(ang, c.value * scale, col, width=1.4 * _PT,
                    label=f"{COMP_LABEL[c.component]} ({c.n_terms} terms)")
            shown = True
        _shade_uncovered(ax, jc)
        ax.xlabel = f"joint {jc.joint + 1} (deg)"
        ax.ylabel = f"error ({unit})"
        ax.title = ("translation δ (about its mean) ±2σ" if kind == "d"
                    else "rotation ε (about its mean) ±2σ")
        if shown:
            ax.legend("below", ncol=3)
        else:
            ax.note("no joint-dependent terms")
    if not with_data:  # a report from a model file alone: no empty residual panel
        return render(f"joint{jc.joint + 1}", fig,
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
            ax.markers(np.degrees(d.q[ok, jc.joint]), s.norms[ok] * 1e3, color(name, i),
                       marker(name, i), size=_ms(size), width=0.8 * _PT, alpha=alpha,
                       label=f"{name}, {which[:3]}.")
            if name == an.selected and (~ok).any():
                ax.markers(np.degrees(d.q[~ok, jc.joint]), s.norms[~ok] * 1e3, "#d62728",
                           "x", size=_ms(6), width=1.4 * _PT)
    ax.yscale = "log"
    ax.xlabel = f"joint {jc.joint + 1} (deg)"
    ax.ylabel = "|residual| (mm, log)"
    ax.title = "residuals vs joint angle"
    if ax.items:
        ax.legend("below", ncol=2)
    else:
        ax.note("no measurements of these poses")
    return render(f"joint{jc.joint + 1}", fig,
                  f"Joint {jc.joint + 1}: identified joint-dependent errors with 2-sigma bands "
                  f"and residuals against the joint angle")


def _shade_uncovered(ax: Axes, jc: JointCurves) -> None:
    """Grey the parts of the joint's range that no calibration pose covered."""
    if jc.covered is None:
        return
    lo, hi = np.degrees(jc.angle[[0, -1]])
    clo, chi = np.degrees(jc.covered)
    for a, b in ((lo, clo), (chi, hi)):
        if b > a:
            ax.vspan(float(a), float(b), "#000", alpha=0.06)


def singular_values(an: Analysis) -> Plot:
    """Normalised singular values of the scaled identification Jacobian."""
    assert an.ident is not None and an.ident.singular_values is not None
    s = an.ident.singular_values
    rank = an.ident.rank if an.ident.rank is not None else s.size
    fig = new_figure(5.2, 2.6)
    (ax,) = grid(fig, 1, 1, (0.7, 0.1, 0.45, 0.3))
    rel = np.maximum(s / s[0], np.finfo(float).tiny)  # exact zeros cannot sit on a log axis
    k = np.arange(1, s.size + 1, dtype=float)
    ax.line(k[:rank], rel[:rank], "#1f77b4", width=0.8 * _PT, marker=".", size=_ms(3),
            label=f"identified ({rank})")
    if rank < s.size:
        ax.markers(k[rank:], rel[rank:], "#d62728", "x", size=_ms(3) + 1,
                   label=f"removed ({s.size - rank})")
        ax.vline(rank + 0.5, "#888", width=0.6 * _PT, dash="--")
        ax.legend("lower left")
    ax.yscale = "log"
    ax.xlabel = "index"
    ax.ylabel = "σ_k / σ_1"
    cond = "–" if an.ident.condition is None else f"{an.ident.condition:.3g}"
    ax.title = f"rank {rank} of {s.size} parameters, cond {cond}"
    return render("singular_values", fig, "Singular values of the identification Jacobian")


def workspace_plot(an: Analysis, w: Workspace) -> Plot:
    """Histogram of predicted 1σ uncertainty, and top/side maps in the robot base frame
    (two orthogonal projections of the 3-D workspace, coloured by the uncertainty)."""
    assert an.selected is not None
    cm = an.models[an.selected].entry.calibrated
    assert cm is not None
    T = cm.model.base_transform(cm.params)
    pb = (w.position - T[:3, 3]) @ T[:3, :3] * 1e3
    s = w.sigma * 1e3
    fig = new_figure(WIDE, 2.9)
    axes = grid(fig, 1, 3, (0.65, 1.0, 0.45, 0.3), wspace=0.35)
    axes[0].hist(s, 40, "#1f77b4", alpha=0.8)
    axes[0].xlabel = "predicted 1σ position uncertainty (mm)"
    axes[0].ylabel = "configurations"
    axes[0].title = f"{s.size} random configurations, {w.within}"
    finite = s[np.isfinite(s)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    # 32 colour levels: one path per level, drawn in order of increasing uncertainty
    level = np.rint(np.nan_to_num((s - lo) / (hi - lo) if hi > lo else s * 0.0) * 31)
    palette = viridis(np.arange(32) / 31)
    for ax, (i, j, lab) in zip(axes[1:], ((0, 1, "top view: x–y"), (0, 2, "side view: x–z")),
                               strict=True):
        for k in np.unique(level).astype(int).tolist():
            sel = level == k
            ax.markers(pb[sel, i], pb[sel, j], palette[k], "o", size=1.6, filled=True,
                       width=0.5)
        ax.equal = True
        ax.xlabel = f"{'xyz'[i]} base (mm)"
        ax.ylabel = f"{'xyz'[j]} base (mm)"
        ax.title = lab
    fig.colorbar(axes[2], lo, hi, "1σ (mm)")
    return render("workspace", fig, "Predicted position uncertainty over the workspace")


def coverage_plot(cov: Coverage) -> Plot:
    """Per joint: robot limits (grey), calibrated range (blue), measured range (black line)
    and the program's targets (orange ticks; red outside the calibrated range)."""
    n = len(cov.rows)
    fig = new_figure(WIDE, 0.36 * n + 0.9)
    (ax,) = grid(fig, 1, 1, (0.5, 0.15, 0.45, 0.3))
    for k, r in enumerate(cov.rows):
        y = n - 1 - k
        lo, hi = r.limits_deg
        ax.barh(y, lo, hi, 0.7, "#e0e0e0")
        if r.calibrated_deg is not None:
            c0, c1 = r.calibrated_deg
            ax.barh(y, c0, c1, 0.45, "#1f77b4", alpha=0.7)
        if r.measured_deg is not None:
            ax.line(r.measured_deg, [y, y], "black", width=1.2 * _PT)
        if cov.targets is not None:
            t = np.degrees(cov.targets[:, k])
            out = ((t < r.calibrated_deg[0]) | (t > r.calibrated_deg[1])
                   if r.calibrated_deg is not None else np.zeros(t.size, dtype=bool))
            ax.markers(t[~out], np.full(int((~out).sum()), y), "#ff7f0e", "|", size=5,
                       width=1.0 * _PT)
            ax.markers(t[out], np.full(int(out.sum()), y), "#d62728", "|", size=6,
                       width=1.4 * _PT)
    ax.set_yticks(np.arange(n), [f"J{r.joint}" for r in reversed(cov.rows)])
    ax.ylim = (-0.6, n - 0.4)
    ax.xlabel = "joint value (deg)"
    title = "grey: limits, blue: calibrated range, black: measured"
    if cov.targets is not None:
        title += f", ticks: {len(cov.targets)} program targets ({cov.outside} outside, red)"
    ax.title = title
    ax.title_size = 12.0
    return render("coverage", fig, "Per-joint coverage with the program targets")


def iso_plot(iso: list[IsoResult]) -> Plot:
    """AP (and AP after calibration when known) and RP per ISO pose; log scale when the
    values span more than a decade."""
    fig = new_figure(5.2, 2.5)
    (ax,) = grid(fig, 1, 1, (0.6, 0.1, 0.3, 0.3))
    x = np.arange(len(iso), dtype=float)
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
        ax.bar(x + (k - (len(bars) - 1) / 2) * w, mmv, w, col, label=label)
    if needs_log_axis(np.concatenate(vals)):
        ax.yscale = "log"
    ax.set_xticks(x, [r.name for r in iso])
    ax.xlim = (-0.5, len(iso) - 0.5)
    ax.ylabel = "mm"
    ax.legend("above", ncol=len(bars))  # above the axes, never over the bars
    return render("iso", fig, "ISO 9283 pose accuracy and repeatability per pose")


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
        fig = new_figure(WIDE, 2.8)
        (ax,) = grid(fig, 1, 1, (0.65, 0.1, 0.45, 0.35))
        for j in range(temps.shape[1]):
            ax.line(t, temps[:, j], TAB10[j % 10], width=1.2 * _PT, label=f"J{j + 1}")
        ax.xlabel = label
        ax.ylabel = "joint temperature (°C)"
        ax.legend("above", ncol=temps.shape[1])
        out.append(render("temperatures", fig, "Joint temperatures against time"))
    sel = an.models.get(an.selected) if an.selected else None
    sets = [(w, an.data[w], sel.sets[w]) for w in SETS if sel is not None
            and w in an.data and an.data[w].temps is not None and w in sel.sets
            and sel.sets[w].norms is not None]
    if sets:
        fig = new_figure(WIDE / 2, 3.0)
        (ax,) = grid(fig, 1, 1, (0.65, 0.1, 0.45, 0.35))
        for i, (which, ds, res) in enumerate(sets):
            assert ds.temps is not None and res.norms is not None
            ax.markers(ds.temps.mean(axis=1), res.norms * 1e3, _EXTRA[i], "os"[i],
                       size=_ms(3.4), width=0.8 * _PT, label=which)
        ax.xlabel = "mean joint temperature of the pose (°C)"
        ax.ylabel = f"{an.selected} error (mm)"
        ax.legend("above", ncol=2)
        out.append(render("residual_temperature", fig,
                           "Position error of the selected model against temperature"))
    return out
