"""The report's plots: SVG figures drawn by :mod:`robocal.report._svg` (ADR 0049) and
embedded as base64 data URIs, so a report is one self-contained HTML file."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal.report._analysis import SETS, Analysis
from robocal.report._coverage import Coverage
from robocal.report._metrics import IsoResult, JointCurves, Workspace
from robocal.report._svg import DPI, Axes, Figure

Array = NDArray[np.float64]
WIDE = 11.8  # inches: the page's content width at 96 dpi
COLORS = {"nominal": "#7f7f7f", "cpa": "#9467bd", "cpa-classical": "#c5b0d5",
          "constant": "#ff7f0e", "high-order": "#1f77b4", "auto": "#2ca02c"}
_EXTRA = ("#8c564b", "#e377c2", "#17becf", "#bcbd22", "#d62728")
# matplotlib's default colour cycle, for series without a meaning of their own (joints)
CYCLE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
         "#7f7f7f", "#bcbd22", "#17becf")
# Markers tell the models apart where colours alone do not (grey/purple, blue/green, print).
MARKERS = {"nominal": "o", "cpa": "v", "cpa-classical": "<", "constant": "s",
           "high-order": "^", "auto": "x"}
_EXTRA_MARKERS = ("D", "P", "*", "h", "<")
COMP_COLORS = {"dx": "#1f77b4", "dy": "#ff7f0e", "dz": "#2ca02c",
               "ex": "#1f77b4", "ey": "#ff7f0e", "ez": "#2ca02c"}
COMP_LABEL = {"dx": "δx", "dy": "δy", "dz": "δz", "ex": "εx", "ey": "εy", "ez": "εz"}


@dataclass(frozen=True)
class Plot:
    """A rendered figure: SVG data URI, pixel size and a text alternative."""

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


def new_figure(w: float, h: float, margins: tuple[float, float, float, float], *,
               wspace: float = 0.3, hspace: float = 0.5) -> Figure:
    """A figure of ``w`` x ``h`` inches laid out by fixed ``margins`` (left, right, bottom,
    top; inches)."""
    return Figure(w, h, margins, wspace, hspace)


def render(key: str, fig: Figure, alt: str) -> Plot:
    """``fig`` as a :class:`Plot` under ``key`` with the text alternative ``alt``."""
    return Plot(key, fig.data_uri(alt), round(fig.w * DPI), round(fig.h * DPI), alt)


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
    # the left margin fits the longest model name (~0.07 in per character at 8 pt)
    left = 0.2 + 0.07 * max(len(n) for n, _ in rows)
    fig = new_figure(4.6, 0.42 * len(rows) + 0.9, (left, 0.15, 0.45, 0.3))
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
    cols = [color(n, i) for i, (n, _) in enumerate(rows)]
    for k, ((which, off, alpha), vals) in enumerate(zip(sets, table, strict=True)):
        ax.barh(y + off, vals - floor, left=floor, height=h, color=cols, alpha=alpha,
                hatch=not k, edgecolor="#fff", label=which)
        for yi, v in zip(y + off, vals, strict=True):
            if np.isfinite(v):
                ax.text(float(v), float(yi), f" {v:.3f}")
    ax.set_yticks(list(y), [n for n, _ in rows])
    ax.invert_yaxis()
    if log:
        ax.set_xscale("log")
        ax.set_xlim(floor, vmax * 4)
        ax.set_xlabel("RMS position error (mm, log scale)")
    else:
        ax.set_xlim(0, vmax * 1.25 if vmax > 0 else 1)
        ax.set_xlabel("RMS position error (mm)")
    ax.set_ylim(-0.6, len(rows) - 0.4)
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
    fig = new_figure(WIDE, 2.9, (0.6, 0.1, 0.45, 0.3), wspace=0.18)
    axes = fig.subplots(1, len(sets))[0]
    bins = _bins(an)
    for ax, which in zip(axes, sets, strict=True):
        for i, (name, m) in enumerate(an.models.items()):
            s = m.sets.get(which)
            if s is None or s.norms is None:
                continue
            d = s.norms[s.inlier] * 1e3 if s.inlier is not None else s.norms * 1e3
            ax.hist(d, bins=bins, color=color(name, i), lw=1.6,
                    label=f"{name} (RMS {s.stats.rms_m * 1e3:.3f})" if s.stats else name)
        ax.set_xscale("log")
        ax.set_xlabel("position error |measured − model| (mm, log scale)")
        ax.set_ylabel("poses")
        ax.set_title(f"{which} poses (n = {len(an.data[which])})")
        ax.legend("best")
    return render("histograms", fig, "Histograms of the position error of each model on "
                                     "calibration and validation poses")


def _points(ax: Axes, x: Array, y: Array, name: str, i: int, **kw: object) -> None:
    ax.plot(x, y, color=color(name, i), marker=marker(name, i), **kw)  # type: ignore[arg-type]


def per_pose(an: Analysis) -> Plot:
    """Error magnitude per pose and model (log scale); outliers marked."""
    sets = [w for w in SETS if w in an.data]
    fig = new_figure(WIDE, 2.6 * len(sets), (0.65, 0.1, 0.45, 0.35), hspace=0.55)
    axes = [row[0] for row in fig.subplots(len(sets), 1)]
    for ax, which in zip(axes, sets, strict=True):
        for i, (name, m) in enumerate(an.models.items()):
            s = m.sets.get(which)
            if s is None or s.norms is None:
                continue
            idx = np.arange(s.norms.size, dtype=float)
            _points(ax, idx, s.norms * 1e3, name, i, ms=3.4, label=name, alpha=0.85)
            if s.inlier is not None and (~s.inlier).any() and name == (an.selected or name):
                ax.plot(idx[~s.inlier], s.norms[~s.inlier] * 1e3, marker="x", ms=7, mew=1.6,
                        color="#d62728", label="rejected outlier")
        ax.set_yscale("log")
        ax.set_ylabel("error (mm, log)")
        ax.set_xlabel(f"{which} pose (measurement order)")
        ax.legend("above", ncol=6)
    return render("per_pose", fig, "Position error per pose for every model")


def joint_plot(an: Analysis, jc: JointCurves) -> Plot:
    """One joint: translation and rotation error terms with ±2σ bands, residuals vs angle."""
    with_data = any(an.data.get(w) is not None for w in SETS)
    # legends go below the axes (never over the curves); the left margin fits "-0.075"
    fig = new_figure(WIDE, 3.3, (0.8, 0.15, 1.0, 0.3), wspace=0.4)
    axes = fig.subplots(1, 3 if with_data else 2)[0]
    ang = np.degrees(jc.angle)
    for ax, kind, scale, unit in ((axes[0], "d", 1e3, "mm"), (axes[1], "e", 180 / math.pi,
                                                               "deg")):
        shown = False
        for c in jc.curves:
            if not c.component.startswith(kind):
                continue
            col = COMP_COLORS[c.component]
            if c.sigma is not None:
                ax.fill_between(ang, (c.value - 2 * c.sigma) * scale,
                                (c.value + 2 * c.sigma) * scale, color=col, alpha=0.18)
            ax.plot(ang, c.value * scale, color=col, lw=1.4,
                    label=f"{COMP_LABEL[c.component]} ({c.n_terms} terms)")
            shown = True
        _shade_uncovered(ax, jc)
        ax.set_xlabel(f"joint {jc.joint + 1} (deg)")
        ax.set_ylabel(f"error ({unit})")
        ax.set_title("translation δ (about its mean) ±2σ" if kind == "d"
                     else "rotation ε (about its mean) ±2σ")
        if shown:
            ax.legend("below", ncol=3, size=7)
        else:
            ax.text(0.5, 0.5, "no joint-dependent terms", axes_coords=True, ha="center",
                    color="#777", size=8.5)
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
            _points(ax, np.degrees(d.q[ok, jc.joint]), s.norms[ok] * 1e3, name, i, ms=size,
                    alpha=alpha, label=f"{name}, {which[:3]}.")
            if name == an.selected and (~ok).any():
                ax.plot(np.degrees(d.q[~ok, jc.joint]), s.norms[~ok] * 1e3, marker="x", ms=6,
                        mew=1.4, color="#d62728")
    ax.set_yscale("log")
    ax.set_xlabel(f"joint {jc.joint + 1} (deg)")
    ax.set_ylabel("|residual| (mm, log)")
    ax.set_title("residuals vs joint angle")
    if ax.has_data():
        ax.legend("below", ncol=2, size=7)
    else:
        ax.text(0.5, 0.5, "no measurements of these poses", axes_coords=True, ha="center",
                color="#777", size=8.5)
    return render(f"joint{jc.joint + 1}", fig,
                  f"Joint {jc.joint + 1}: identified joint-dependent errors with 2-sigma bands "
                  f"and residuals against the joint angle")


def _shade_uncovered(ax: Axes, jc: JointCurves) -> None:
    if jc.covered is None:
        return
    lo, hi = np.degrees(jc.angle[[0, -1]])
    clo, chi = np.degrees(jc.covered)
    for a, b in ((lo, clo), (chi, hi)):
        if b > a:
            ax.axvspan(float(a), float(b), color="#000", alpha=0.06)


def singular_values(an: Analysis) -> Plot:
    """Normalised singular values of the scaled identification Jacobian."""
    assert an.ident is not None and an.ident.singular_values is not None
    s = an.ident.singular_values
    rank = an.ident.rank if an.ident.rank is not None else s.size
    fig = new_figure(5.2, 2.6, (0.7, 0.1, 0.45, 0.3))
    ax = fig.add_subplot()
    rel = np.maximum(s / s[0], np.finfo(float).tiny)  # exact zeros cannot sit on a log axis
    k = np.arange(1, s.size + 1, dtype=float)
    ax.set_yscale("log")
    ax.plot(k[:rank], rel[:rank], color="#1f77b4", lw=0.8, marker=".", ms=3, hollow=False,
            line=True, label=f"identified ({rank})")
    if rank < s.size:
        ax.plot(k[rank:], rel[rank:], marker="x", ms=3, color="#d62728",
                label=f"removed ({s.size - rank})")
        ax.axvline(rank + 0.5, color="#888", lw=0.6, dash="4 3")
        ax.legend("lower left", size=7)
    ax.set_xlabel("index")
    ax.set_ylabel("σ_k / σ_1")
    cond = "–" if an.ident.condition is None else f"{an.ident.condition:.3g}"
    ax.set_title(f"rank {rank} of {s.size} parameters, cond {cond}", size=9)
    return render("singular_values", fig, "Singular values of the identification Jacobian")


def workspace_plot(an: Analysis, w: Workspace) -> Plot:
    """Histogram of predicted 1σ uncertainty, and top/side maps in the robot base frame."""
    assert an.selected is not None
    cm = an.models[an.selected].entry.calibrated
    assert cm is not None
    T = cm.model.base_transform(cm.params)
    pb = (w.position - T[:3, 3]) @ T[:3, :3] * 1e3
    s = w.sigma * 1e3
    fig = new_figure(WIDE, 2.9, (0.65, 0.1, 0.45, 0.3), wspace=0.35)
    axes = fig.subplots(1, 3)[0]
    axes[0].hist(s, bins=40, color="#1f77b4", alpha=0.8, step=False)
    axes[0].set_xlabel("predicted 1σ position uncertainty (mm)")
    axes[0].set_ylabel("configurations")
    axes[0].set_title(f"{s.size} random configurations, {w.within}")
    order = np.argsort(s)
    lo, hi = (float(s.min()), float(s.max())) if s.size else (0.0, 1.0)
    for ax, (i, j, lab) in zip(axes[1:], ((0, 1, "top view: x–y"), (0, 2, "side view: x–z")),
                               strict=True):
        ax.scatter_colored(pb[order, i], pb[order, j], s[order], vmin=lo, vmax=hi)
        ax.set_aspect_equal()
        ax.set_xlabel(f"{'xyz'[i]} base (mm)")
        ax.set_ylabel(f"{'xyz'[j]} base (mm)")
        ax.set_title(lab)
    fig.colorbar(axes[2], lo, hi, "1σ (mm)")
    return render("workspace", fig, "Predicted position uncertainty over the workspace")


def coverage_plot(cov: Coverage) -> Plot:
    """Per joint: robot limits (grey), calibrated range (blue), measured range (black line)
    and the program's targets (orange ticks; red outside the calibrated range)."""
    n = len(cov.rows)
    fig = new_figure(WIDE, 0.36 * n + 0.9, (0.5, 0.15, 0.45, 0.3))
    ax = fig.add_subplot()
    for k, r in enumerate(cov.rows):
        y = float(n - 1 - k)
        lo, hi = r.limits_deg
        ax.barh(y, hi - lo, left=lo, height=0.7, color="#e0e0e0")
        if r.calibrated_deg is not None:
            c0, c1 = r.calibrated_deg
            ax.barh(y, c1 - c0, left=c0, height=0.45, color="#1f77b4", alpha=0.7)
        if r.measured_deg is not None:
            ax.plot(list(r.measured_deg), [y, y], color="black", lw=1.2)
        if cov.targets is not None:
            t = np.degrees(cov.targets[:, k])
            out = ((t < r.calibrated_deg[0]) | (t > r.calibrated_deg[1])
                   if r.calibrated_deg is not None else np.zeros(t.size, dtype=bool))
            ax.plot(t[~out], np.full(int((~out).sum()), y), marker="|", ms=7.7, mew=1.0,
                    color="#ff7f0e")
            ax.plot(t[out], np.full(int(out.sum()), y), marker="|", ms=8.9, mew=1.4,
                    color="#d62728")
    ax.set_yticks(list(range(n)), [f"J{r.joint}" for r in reversed(cov.rows)])
    ax.set_ylim(-0.6, n - 0.4)
    ax.set_xlabel("joint value (deg)")
    title = "grey: limits, blue: calibrated range, black: measured"
    if cov.targets is not None:
        title += f", ticks: {len(cov.targets)} program targets ({cov.outside} outside, red)"
    ax.set_title(title, size=9)
    return render("coverage", fig, "Per-joint coverage with the program targets")


def iso_plot(iso: list[IsoResult]) -> Plot:
    """AP (and AP after calibration when known) and RP per ISO pose; log scale when the
    values span more than a decade."""
    fig = new_figure(5.2, 2.5, (0.6, 0.1, 0.3, 0.3))
    ax = fig.add_subplot()
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
        ax.bar(x + (k - (len(bars) - 1) / 2) * w, mmv, w, label=label, color=col)
    if needs_log_axis(np.concatenate(vals)):
        ax.set_yscale("log")
    ax.set_xticks(list(x), [r.name for r in iso])
    ax.set_xlim(-0.6, len(iso) - 0.4)
    ax.set_ylabel("mm")
    ax.legend("above", ncol=len(bars), size=7)  # above the axes, never over the bars
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
        fig = new_figure(WIDE, 2.8, (0.65, 0.1, 0.45, 0.35))
        ax = fig.add_subplot()
        for j in range(temps.shape[1]):
            ax.plot(t, temps[:, j], color=CYCLE[j % len(CYCLE)], lw=1.2, label=f"J{j + 1}")
        ax.set_xlabel(label)
        ax.set_ylabel("joint temperature (°C)")
        ax.legend("above", ncol=temps.shape[1])
        out.append(render("temperatures", fig, "Joint temperatures against time"))
    sel = an.models.get(an.selected) if an.selected else None
    sets = [(w, an.data[w], sel.sets[w]) for w in SETS if sel is not None
            and w in an.data and an.data[w].temps is not None and w in sel.sets
            and sel.sets[w].norms is not None]
    if sets:
        fig = new_figure(WIDE / 2, 3.0, (0.65, 0.1, 0.45, 0.35))
        ax = fig.add_subplot()
        for i, (which, ds, res) in enumerate(sets):
            assert ds.temps is not None and res.norms is not None
            ax.plot(ds.temps.mean(axis=1), res.norms * 1e3, marker="os"[i], ms=3.4,
                    color=_EXTRA[i], label=which)
        ax.set_xlabel("mean joint temperature of the pose (°C)")
        ax.set_ylabel(f"{an.selected} error (mm)")
        ax.legend("above", ncol=2)
        out.append(render("residual_temperature", fig,
                          "Position error of the selected model against temperature"))
    return out
