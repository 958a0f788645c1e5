"""The self-contained HTML report: measurements against a model (`posecorr report`).

One file, no external resources: figures are PNGs embedded as base64 data URIs, the CSS is
inline and there is no JavaScript. The page lets a user compare a model with the
measurements, see where it fails, read which physical effect the diagnosis says is missing,
and watch the held-out error fall across the ledger of models fitted on the same data.

Sections (HTML ids): summary, metrics, workspace, features, orientation, histograms, worst,
diagnosis, ledger. Units on the page: mm and mrad; angles of features in degrees. All
numbers handed in are SI (m, rad, s), as everywhere in posecorr.

matplotlib (Agg backend) is imported inside the plotting functions so that
`import posecorr.report` stays cheap for the CLI.
"""
from __future__ import annotations

import base64
import html
import io
import math
import shutil
import subprocess
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from .data import PoseTable
from .features import FEATURES, table_features
from .metrics import W_POS, W_ROT, metric_block, pose_errors, pose_metrics

SECTIONS = (("summary", "Summary"), ("metrics", "Metrics"), ("workspace", "Workspace"),
            ("features", "Error vs features"), ("orientation", "Orientation"),
            ("histograms", "Histograms"), ("worst", "Worst poses"), ("diagnosis", "Diagnosis"),
            ("ledger", "Ledger"), ("segments", "Still segments"))
N_WORST = 15
DPI = 100
ANGLE_FEATURES = ("azimuth", "elevation", "incidence", "roll", "pitch", "yaw")
FEATURE_UNITS = {"x": "m", "y": "m", "z": "m", "range": "m", "t": "s", **{a: "deg" for a in ANGLE_FEATURES}}
BEFORE_COLOUR = "0.6"        # grey: raw measurements
AFTER_COLOUR = "#1f77b4"     # blue: corrected by the model
# A floor for log axes: an error of exactly zero (a pass-through orientation) has no log.
LOG_FLOOR_MM = 1e-4

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,Helvetica,Arial,sans-serif;margin:0;
 color:#222;background:#fafafa;line-height:1.4}
main{max-width:1240px;margin:0 auto;padding:0 16px 40px}
header{background:#1f3b57;color:#fff;padding:14px 16px}
header h1{margin:0;font-size:1.45em;max-width:1240px;margin:0 auto}
nav{background:#e8edf2;padding:6px 16px;position:sticky;top:0;z-index:1;border-bottom:1px solid #ccd}
nav a{margin-right:14px;color:#1f3b57;text-decoration:none;font-size:.92em}
section{background:#fff;border:1px solid #dde;border-radius:6px;padding:10px 18px;margin:16px 0}
h2{font-size:1.2em;margin:6px 0 8px;color:#1f3b57}
p.note{color:#555;font-size:.9em;margin:4px 0 8px}
table{border-collapse:collapse;font-size:.88em;margin:6px 0}
th,td{border:1px solid #ccd;padding:3px 7px;text-align:right;white-space:nowrap}
th{background:#eef1f5;white-space:normal;vertical-align:bottom}
table.compact{font-size:.8em}
table.compact th,table.compact td{padding:2px 5px}
td.l,th.l{text-align:left}
tr.present td{background:#fde8d7;font-weight:600}
tr.best td{background:#e3f3e3}
img{max-width:100%;height:auto;display:block;margin:6px 0}
dl.kv{display:grid;grid-template-columns:max-content auto;gap:2px 14px;margin:4px 0;font-size:.92em}
dl.kv dt{color:#555}dl.kv dd{margin:0}
.takeaway{font-size:1.08em;background:#fff6d9;border-left:5px solid #e0a800;padding:8px 12px;margin:8px 0}
.scroll{overflow-x:auto}
code{background:#f0f0f0;padding:0 3px;border-radius:3px}
"""


# --------------------------------------------------------------------------- helpers

def _e(value: Any) -> str:
    """HTML-escaped text of any value."""
    return html.escape(str(value), quote=True)


def _num(value: Any, scale: float = 1.0, digits: int = 3) -> str:
    """A number (times scale) with `digits` significant digits; '–' for None/NaN."""
    if value is None:
        return "–"
    try:
        v = float(value) * scale
    except (TypeError, ValueError):
        return _e(value)
    if math.isnan(v):
        return "–"
    if math.isinf(v):
        return "∞"
    if v != 0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
        return f"{v:.{max(digits - 1, 0)}e}"
    return f"{v:.{digits}g}" if abs(v) >= 10 ** digits else f"{v:#.{digits}g}".rstrip(".")


def _p_value(p: Any) -> str:
    """p-value as text: 'p < 1e-6' when tiny."""
    if p is None:
        return "–"
    try:
        v = float(p)
    except (TypeError, ValueError):
        return str(p)
    if math.isnan(v):
        return "–"
    return "< 1e-6" if v < 1e-6 else f"{v:.2g}"


def _table(header: Sequence[str], rows: Iterable[Sequence[str]], left: int = 1,
           row_classes: Sequence[str] | None = None, compact: bool = False) -> str:
    """An HTML table; cells must already be escaped. The first `left` columns align left."""
    head = "".join(f'<th class="l">{h}</th>' if i < left else f"<th>{h}</th>" for i, h in enumerate(header))
    body = []
    for k, row in enumerate(rows):
        cls = f' class="{row_classes[k]}"' if row_classes and row_classes[k] else ""
        cells = "".join(f'<td class="l">{c}</td>' if i < left else f"<td>{c}</td>" for i, c in enumerate(row))
        body.append(f"<tr{cls}>{cells}</tr>")
    cls_table = ' class="compact"' if compact else ""
    return (f'<div class="scroll"><table{cls_table}><thead><tr>{head}</tr></thead>'
            f'<tbody>{"".join(body)}</tbody></table></div>')


def _img(fig: Any, alt: str) -> str:
    """Render a matplotlib figure to an <img> with a PNG data URI, and close it."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{data}">'


def _pyplot() -> Any:
    import matplotlib
    matplotlib.use("Agg")  # no display on a controller PC or CI box
    import matplotlib.pyplot as plt
    plt.rcParams.update({"font.size": 9, "axes.titlesize": 10, "axes.labelsize": 9,
                         "legend.fontsize": 8, "figure.dpi": DPI})
    return plt


def _plain_log(ax: Any, axis: str = "y", subs: Sequence[float] = (1.0, 2.0, 5.0), minor: bool = True) -> None:
    """Log axis with plain tick labels at subs x 10^k (no mathtext: readable and fast).

    minor=False drops the minor ticks, which dominate drawing time in many-panel figures.
    """
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter, NullLocator

    target = ax.yaxis if axis == "y" else ax.xaxis
    target.set_major_locator(LogLocator(base=10, subs=subs))
    target.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    target.set_minor_formatter(NullFormatter())
    if not minor:
        target.set_minor_locator(NullLocator())


def _margins(width: float, height: float, left: float, right: float, top: float, bottom: float,
             wspace: float, hspace: float) -> dict[str, float]:
    """gridspec keywords from margins in inches (figure size in inches)."""
    return {"left": left / width, "right": 1 - right / width, "top": 1 - top / height,
            "bottom": bottom / height, "wspace": wspace, "hspace": hspace}


def _feature_display(name: str, values: np.ndarray) -> np.ndarray:
    """Feature values in display units (angles in degrees)."""
    return np.degrees(values) if name in ANGLE_FEATURES else values


def _nice_length(x: float) -> float:
    """The round number (1, 2, 5 x 10^k) nearest to x > 0 on a log scale (a key arrow's length)."""
    if not x > 0 or not math.isfinite(x):
        return 1.0
    k = math.floor(math.log10(x))
    options = [m * 10.0 ** (k + d) for d in (0, 1) for m in (1, 2, 5)]
    return min(options, key=lambda v: abs(math.log(v / x)))


def _groups(values: np.ndarray, max_distinct: int = 13, n_bins: int = 8) -> tuple[list[str], list[np.ndarray]]:
    """Group indices by distinct value (rounded to 0.1) when few, else by equal-width bins.

    A spread below 1 (deg) is one group: a fixed orientation seen through tracker noise (as in a
    position-only table, whose orientation is the measured one) is no variable to group by.
    """
    if np.ptp(values) < 1.0:
        return [f"≈{np.mean(values) + 0.0:.1f} (fixed)"], [np.arange(len(values))]
    rounded = np.round(values, 1)
    distinct = np.unique(rounded)
    if len(distinct) <= max_distinct:
        # + 0.0 turns -0.0 into 0.0, so no "-0" label
        return [f"{v + 0.0:g}" for v in distinct], [np.flatnonzero(rounded == v) for v in distinct]
    edges = np.linspace(values.min(), values.max(), n_bins + 1)
    which = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, n_bins - 1)
    labels, index = [], []
    for b in range(n_bins):
        idx = np.flatnonzero(which == b)
        if idx.size:
            labels.append(f"{edges[b]:.0f}…{edges[b + 1]:.0f}")
            index.append(idx)
    return labels, index


def _binned_median(x: np.ndarray, y: np.ndarray, n_bins: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Median of y per distinct x (if few) or per equal-count bin of x."""
    distinct = np.unique(x)
    if len(distinct) <= 15:
        return distinct, np.array([np.median(y[x == v]) for v in distinct])
    order = np.argsort(x, kind="stable")
    chunks = [c for c in np.array_split(order, min(n_bins, len(x))) if c.size]
    return np.array([np.median(x[c]) for c in chunks]), np.array([np.median(y[c]) for c in chunks])


def _jitter(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Horizontal jitter for a feature with few distinct values, so stacked points show."""
    distinct = np.unique(x)
    if len(distinct) > 15 or len(x) < 2:
        return x
    gap = np.min(np.diff(distinct)) if len(distinct) > 1 else 1.0
    return x + rng.uniform(-0.15, 0.15, size=x.shape) * gap


def _held_out(entry: Mapping[str, Any]) -> tuple[str, Mapping[str, Any]]:
    """("cv" | "test" | "", block) of a ledger entry."""
    for key in ("cv", "test"):
        block = entry.get(key)
        if isinstance(block, Mapping):
            return key, block
    return "", {}


def _as_list(value: Any) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        return [v.strip() for v in value.split(",") if v.strip()]
    if isinstance(value, Mapping):
        return [str(k) for k in value]
    try:
        return [str(v) for v in value]
    except TypeError:
        return [str(value)]


# --------------------------------------------------------------------------- figures

def _arrow_length(ref_p: np.ndarray) -> float:
    """Drawn length (m) of a typical (95th-percentile) error arrow: 0.6 of the lattice spacing.

    The spacing is estimated from the number of distinct positions as if they filled a cube,
    so arrows of neighbouring lattice points rarely overlap; capped at a quarter of the span.
    """
    span = float(np.max(np.ptp(ref_p, axis=0))) or 0.1
    distinct = len(np.unique(np.round(ref_p, 4), axis=0))
    per_axis = max(distinct ** (1 / 3) - 1, 1.0)
    return min(0.6 * span / per_axis, 0.25 * span)


def _workspace_figure(ref_p: np.ndarray, before: np.ndarray, after: np.ndarray) -> Any:
    """Quiver of position error vectors (m) at the reference positions, 3 projections x 2 rows."""
    plt = _pyplot()
    span = float(np.max(np.ptp(ref_p, axis=0))) or 0.1
    length = _arrow_length(ref_p)
    projections = ((0, 1), (0, 2), (1, 2))
    names = "xyz"
    fig, axes = plt.subplots(2, 3, figsize=(12, 8.4), layout="constrained")
    for row, (label, d) in enumerate((("before correction", before), ("after correction", after))):
        mag_mm = np.linalg.norm(d, axis=1) * 1e3
        ref_mm = float(np.percentile(mag_mm, 95))
        ref_mm = ref_mm if ref_mm > 0 else 1.0
        # Each row has its own magnification (corrected errors are ~20x smaller); the key says it.
        scale = (ref_mm / 1e3) / length
        key_mm = _nice_length(ref_mm)
        order = np.argsort(mag_mm)  # largest arrows on top
        lo, hi = (float(v) for v in np.percentile(mag_mm, [1, 99]))
        clim = (lo, hi) if hi > lo else (0.0, max(hi, 1e-9))  # a 1-99 % range keeps colour contrast
        for col, (i, j) in enumerate(projections):
            ax = axes[row, col]
            q = ax.quiver(ref_p[order, i], ref_p[order, j], d[order, i], d[order, j], mag_mm[order],
                          angles="xy", scale_units="xy", scale=scale, cmap="viridis", clim=clim,
                          width=0.0045, headwidth=3.5, headlength=4, headaxislength=3.5, alpha=0.9)
            pad = 0.12 * span + length
            ax.set_xlim(ref_p[:, i].min() - pad, ref_p[:, i].max() + pad)
            ax.set_ylim(ref_p[:, j].min() - pad, ref_p[:, j].max() + pad)
            ax.set_aspect("equal", adjustable="box")
            ax.set_xlabel(f"{names[i]} [m]")
            ax.set_ylabel(f"{names[j]} [m]")
            ax.set_title(f"{names[i]}-{names[j]}, {label}")
            ax.quiverkey(q, 0.90, 1.015, key_mm / 1e3, f"{key_mm:g} mm", labelpos="W", coordinates="axes",
                         color="#d62728", fontproperties={"size": 8})
            ax.title.set_position((0.36, 1.0))  # leave the right of the title line to the key
        cb = fig.colorbar(q, ax=axes[row, :], shrink=0.85, pad=0.01)
        cb.set_label(f"|error| [mm], {label.split()[0]}")
    fig.suptitle("Position error vectors at the reference positions, magnified "
                 "(red key arrow per panel; the two rows have different magnifications)", fontsize=10)
    return fig


def _features_figure(features: Mapping[str, np.ndarray], before_mm: np.ndarray, after_mm: np.ndarray,
                     quantity: str, unit: str) -> Any:
    """Scatter of per-pose error (log y) against each feature, before grey, after blue."""
    plt = _pyplot()
    names = [f for f in FEATURES if f in features]
    ncols = 4
    nrows = math.ceil(len(names) / ncols)
    height = 2.55 * nrows + 0.4
    # Fixed margins instead of constrained layout: that layout engine costs seconds per figure
    # here (it measures every tick label), and this grid has the same layout every time.
    fig, axes = plt.subplots(nrows, ncols, figsize=(12, height), sharey=True, squeeze=False,
                             gridspec_kw=_margins(12, height, left=0.75, right=0.15, top=0.4, bottom=0.5,
                                                  wspace=0.06, hspace=0.42))
    rng = np.random.default_rng(0)  # fixed jitter: the same page for the same data
    b = np.maximum(before_mm, LOG_FLOOR_MM)
    a = np.maximum(after_mm, LOG_FLOOR_MM)
    size = 6 if len(b) > 1000 else 10
    for k, name in enumerate(names):
        ax = axes.flat[k]
        x = _feature_display(name, np.asarray(features[name], float))
        xj = _jitter(x, rng)
        ax.scatter(xj, b, s=size, c=BEFORE_COLOUR, alpha=0.35, linewidths=0, rasterized=True, label="before")
        ax.scatter(xj, a, s=size, c=AFTER_COLOUR, alpha=0.45, linewidths=0, rasterized=True, label="after")
        for y, colour in ((b, "0.25"), (a, "#0b3d66")):
            mx, my = _binned_median(x, y)
            ax.plot(mx, my, "-o", color=colour, lw=1.6, ms=3)
        ax.set_yscale("log")
        _plain_log(ax, "y", (1.0, 2.0, 5.0), minor=False)
        ax.set_xlabel(f"{name} [{FEATURE_UNITS.get(name, '')}]")
        if k % ncols == 0:
            ax.set_ylabel(f"{quantity} [{unit}]")
        ax.grid(True, which="major", alpha=0.3)
    for k in range(len(names), nrows * ncols):
        ax = axes.flat[k]
        ax.axis("off")
    # The legend goes into the spare panel when there is one.
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], ls="", marker="o", color=BEFORE_COLOUR, label="before (raw)"),
               Line2D([], [], ls="", marker="o", color=AFTER_COLOUR, label="after (corrected)"),
               Line2D([], [], color="0.25", lw=1.6, label="binned median, before"),
               Line2D([], [], color="#0b3d66", lw=1.6, label="binned median, after")]
    target = axes.flat[len(names)] if len(names) < nrows * ncols else axes.flat[0]
    target.legend(handles=handles, loc="center" if len(names) < nrows * ncols else "upper right")
    fig.suptitle(f"Per-pose {quantity} against features (log scale)", fontsize=10)
    return fig


def _orientation_figure(features: Mapping[str, np.ndarray], pos_mm: np.ndarray, rot_mrad: np.ndarray | None,
                        pos_before: np.ndarray, rot_before: np.ndarray | None) -> Any:
    """Box plots of corrected error grouped by roll / pitch / yaw (grey dots: raw median)."""
    plt = _pyplot()
    rows = [("position error", "mm", pos_mm, pos_before)]
    if rot_mrad is not None and rot_before is not None:
        rows.append(("rotation error", "mrad", rot_mrad, rot_before))
    height = 3.3 * len(rows) + 0.5
    fig, axes = plt.subplots(len(rows), 3, figsize=(12, height), squeeze=False,
                             gridspec_kw=_margins(12, height, left=0.65, right=0.15, top=0.55, bottom=0.8,
                                                  wspace=0.25, hspace=0.62))  # room for slanted labels
    for r, (quantity, unit, err, err_before) in enumerate(rows):
        for c, angle in enumerate(("roll", "pitch", "yaw")):
            ax = axes[r, c]
            labels, index = _groups(np.degrees(features[angle]))
            data = [err[i] for i in index]
            ax.boxplot(data, tick_labels=labels, showfliers=True, widths=0.6,
                       flierprops={"markersize": 2, "alpha": 0.5},
                       medianprops={"color": "#0b3d66", "lw": 1.6},
                       boxprops={"color": AFTER_COLOUR}, whiskerprops={"color": AFTER_COLOUR},
                       capprops={"color": AFTER_COLOUR})
            ax.set_xlabel(f"{angle} [deg]")
            ax.set_ylabel(f"{quantity} after [{unit}]")
            ax.set_ylim(bottom=0)
            if len(labels) > 8:
                ax.tick_params(axis="x", labelrotation=45)
            ax.grid(True, axis="y", alpha=0.3)
            ax.set_title(f"{quantity} by {angle} (n per box: {min(map(len, index))}–{max(map(len, index))})")
    fig.suptitle("Corrected error grouped by orientation (boxes: quartiles, whiskers 1.5 IQR)", fontsize=10)
    return fig


def _histogram_figure(pos: tuple[np.ndarray, np.ndarray], rot: tuple[np.ndarray, np.ndarray] | None) -> Any:
    """Histograms on log-spaced bins so raw and corrected (20x apart) are both readable."""
    plt = _pyplot()
    panels = [("position error", "mm", pos)]
    if rot is not None:
        panels.append(("rotation error", "mrad", rot))
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 3.4), layout="constrained", squeeze=False)
    for ax, (quantity, unit, (before, after)) in zip(axes.flat, panels):
        b = np.maximum(before, LOG_FLOOR_MM)
        a = np.maximum(after, LOG_FLOOR_MM)
        lo = max(min(b.min(), a.min()), LOG_FLOOR_MM)
        hi = max(b.max(), a.max(), lo * 10)
        bins = np.logspace(np.log10(lo), np.log10(hi), 50)
        ax.hist(b, bins=bins, color=BEFORE_COLOUR, alpha=0.7, label="before (raw)")
        ax.hist(a, bins=bins, color=AFTER_COLOUR, alpha=0.7, label="after (corrected)")
        for v, colour, name in ((before, "0.3", "before"), (after, "#0b3d66", "after")):
            r = float(np.sqrt(np.mean(np.square(v))))
            if r > 0:
                ax.axvline(r, color=colour, ls="--", lw=1.2, label=f"RMSE {name}: {r:.3g} {unit}")
        ax.set_xscale("log")
        _plain_log(ax, "x", (1.0,), minor=False)
        ax.set_xlabel(f"{quantity} [{unit}] (log scale)")
        ax.set_ylabel("poses")
        ax.legend(loc="upper left")
        ax.grid(True, alpha=0.3)
    return fig


def _r2_figure(features: Sequence[Mapping[str, Any]]) -> Any:
    """Horizontal bars of the cross-validated R^2 of the residual per feature."""
    plt = _pyplot()
    names = [str(f.get("feature", "?")) for f in features]
    r2 = np.array([float(f["r2"]) if f.get("r2") is not None else np.nan for f in features])
    fig, ax = plt.subplots(figsize=(6.5, 0.28 * len(names) + 1.0), layout="constrained")
    y = np.arange(len(names))
    colours = [("#d95f02" if v >= 0.1 else AFTER_COLOUR) for v in np.nan_to_num(r2)]
    ax.barh(y, np.nan_to_num(r2), color=colours)
    ax.set_yticks(y, names)
    ax.invert_yaxis()
    finite = r2[np.isfinite(r2)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    ax.set_xlim(min(-0.05, lo), max(1.0, hi))
    ax.axvline(0, color="k", lw=0.8)
    ax.set_xlabel("cross-validated R² of the residual explained by the feature")
    ax.grid(True, axis="x", alpha=0.3)
    return fig


def _effects_step(previous: list[str] | None, effects: list[str]) -> str:
    """What a ledger entry changed: its effects for the first, '+added -removed' after."""
    if previous is None:
        return ",".join(effects) or "no effects"
    added = [e for e in effects if e not in previous]
    removed = [e for e in previous if e not in effects]
    parts = (["+" + ",".join(added)] if added else []) + (["-" + ",".join(removed)] if removed else [])
    return "\n".join(parts) or "same effects"


def _ledger_figure(ledger: Sequence[Mapping[str, Any]]) -> Any | None:
    """Step plot of the held-out rmse_total per ledger entry (log y)."""
    values, labels = [], []
    previous: list[str] | None = None
    for k, entry in enumerate(ledger, start=1):
        _, block = _held_out(entry)
        v = block.get("rmse_total")
        values.append(float(v) * 1e3 if isinstance(v, (int, float)) and v > 0 else np.nan)
        effects = [str(e) for e in _as_list(entry.get("effects"))]
        labels.append(f"{k}: {_effects_step(previous, effects)}\n{entry.get('method', '')}")
        previous = effects
    y = np.array(values)
    if not np.isfinite(y).any():
        return None
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(max(6.0, min(12.0, 1.3 * len(y) + 3)), 3.4), layout="constrained")
    x = np.arange(1, len(y) + 1)
    ax.step(x, y, where="mid", color=AFTER_COLOUR, lw=1.8)
    ax.plot(x, y, "o", color="#0b3d66")
    best = np.nanargmin(y)
    ax.plot(x[best], y[best], "*", color="#d95f02", ms=13, label=f"best: {y[best]:.3g} mm+mrad")
    for xi, yi in zip(x, y):
        if np.isfinite(yi):
            ax.annotate(f"{yi:.3g}", (xi, yi), textcoords="offset points", xytext=(6, 4), fontsize=8)
    ax.set_yscale("log")
    _plain_log(ax, "y")
    if np.isfinite(y).any():
        lo, hi = np.nanmin(y), np.nanmax(y)
        ax.set_ylim(lo / 1.6, hi * 1.8)  # room for the value labels
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_xlim(0.5, len(y) + 0.5)
    ax.set_ylabel("held-out rmse_total [mm + mrad]")
    ax.set_xlabel("ledger entry (effects, method)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper right")
    return fig


# --------------------------------------------------------------------------- sections

def _section(sid: str, title: str, body: str, note: str = "") -> str:
    note_html = f'<p class="note">{note}</p>' if note else ""
    return f'<section id="{sid}"><h2>{_e(title)}</h2>{note_html}{body}</section>'


def _model_effects(model_info: Mapping[str, Any] | None, diagnosis: Mapping[str, Any] | None) -> list[str]:
    if diagnosis and diagnosis.get("model_effects") is not None:
        return _as_list(diagnosis.get("model_effects"))
    if model_info:
        return _as_list(model_info.get("effects"))
    return []


def takeaway(diagnosis: Mapping[str, Any] | None, model_effects: Sequence[str] = ()) -> str:
    """The diagnosis in one plain-language line (plain text, not escaped)."""
    if not diagnosis:
        return "No diagnosis given (run `posecorr diagnose` to rank missing effects)."
    candidates = sorted([c for c in diagnosis.get("candidates") or [] if isinstance(c, Mapping)],
                        key=lambda c: (c.get("rank") if isinstance(c.get("rank"), (int, float)) else 1e9))
    present = [c for c in candidates if c.get("present")]
    test = f" ({diagnosis['test']})" if diagnosis.get("test") else ""
    if present:
        top = present[0]
        effect = str(top.get("effect", "?"))
        p = top.get("p_value")
        p_text = f", p {_p_value(p)}" if p is not None and _p_value(p).startswith("<") else (
            f", p = {_p_value(p)}" if p is not None else "")
        effects = list(model_effects)
        if effect not in effects:
            effects.append(effect)
        gain = ""
        b, a = top.get("cv_rmse_before"), top.get("cv_rmse_after")
        if isinstance(b, (int, float)) and isinstance(a, (int, float)) and a > 0:
            gain = f"; it cuts the cross-validated RMSE {b / a:.2g}×"
        return (f"Most likely missing: {effect} (present: yes{p_text}{gain}). "
                f"Add it with --effects {','.join(effects)}")
    r2 = [f for f in diagnosis.get("features") or []
          if isinstance(f, Mapping) and isinstance(f.get("r2"), (int, float))]
    if r2:
        best = max(r2, key=lambda f: f["r2"])
        if best["r2"] >= 0.1:
            return (f"No catalogue effect is missing{test}, but {best['r2']:.2f} of the residual is explained "
                    f"by {best.get('feature')}: an effect outside the catalogue (add your own with --effect-file).")
    top = f" (best candidate: {candidates[0].get('effect')}, not present)" if candidates else ""
    return f"No catalogue effect is missing{test}{top}; the residual looks like noise."


def _summary_section(table: PoseTable, model_info: Mapping[str, Any] | None, title: str) -> str:
    extras = [c for c in ("id", "t", "session", "jitter_mm") if c in table.extras]
    items = [("data file", table.path or "(in memory)"), ("poses", str(table.n)),
             ("kind", "full pose (position and orientation)" if table.has_orientation
              else "position only (rotation panels skipped)"),
             ("optional columns", ", ".join(extras) or "none")]
    if model_info:
        effects = ",".join(_as_list(model_info.get("effects"))) or "none"
        items += [("model file", model_info.get("file", "?")),
                  ("method", model_info.get("method", "?")),
                  ("representation", model_info.get("representation", "?")),
                  ("effects in the model", effects)]
        for key in ("architecture", "activation", "trainer", "posecorr_version"):
            if model_info.get(key) not in (None, ""):
                items.append((key.replace("_", " "), model_info[key]))
        if isinstance(model_info.get("fixed"), Mapping):
            for name, reason in model_info["fixed"].items():
                items.append((f"held (not determined): {name}", reason))
        if isinstance(model_info.get("file_size"), int):
            items.append(("file size", f"{model_info['file_size']:,} bytes"))
        if isinstance(model_info.get("op_counts"), Mapping):
            ops = ", ".join(f"{k} {v}" for k, v in model_info["op_counts"].items())
            items.append(("operators", ops))
    else:
        items.append(("model", "(none given: 'after' is the corrected poses handed in)"))
    items.append(("generated", datetime.now(timezone.utc).isoformat(timespec="seconds")))
    body = '<dl class="kv">' + "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in items) + "</dl>"
    return _section("summary", "Summary", body)


def _metrics_section(raw: Mapping[str, Any], corr: Mapping[str, Any], block: Mapping[str, Any],
                     pos: tuple[np.ndarray, np.ndarray], rot: tuple[np.ndarray, np.ndarray] | None,
                     model_info: Mapping[str, Any] | None) -> str:
    # Position-only data has no rotation columns at all (rather than columns of dashes).
    if rot is not None:
        header = ["", "rmse_pos [mm]", "rmse_rot [mrad]", "rmse_total [mm + mrad]",
                  "median pos [mm]", "p95 pos [mm]", "max pos [mm]", "median rot [mrad]", "max rot [mrad]"]
    else:
        header = ["", "rmse_pos [mm]", "rmse_total [mm]", "median pos [mm]", "p95 pos [mm]", "max pos [mm]"]
    rows = []
    for k, (name, m) in enumerate((("raw (measured)", raw), ("corrected (model)", corr))):
        p = pos[k] * 1e3
        row = [_e(name), _num(m["rmse_pos"], 1e3)]
        if rot is not None:
            row.append(_num(m["rmse_rot"], 1e3))
        row += [_num(m["rmse_total"], 1e3), _num(np.median(p)), _num(np.percentile(p, 95)), _num(p.max())]
        if rot is not None:
            row += [_num(np.median(rot[k]) * 1e3), _num(rot[k].max() * 1e3)]
        rows.append(row)
    improvement = ["improvement (raw / corrected)", _num(block.get("improvement_pos")) + "×"]
    if rot is not None:
        improvement.append(_num(block.get("improvement_rot")) + "×")
    improvement.append(_num(block.get("improvement_total")) + "×")
    rows.append(improvement + [""] * (len(header) - len(improvement)))
    body = _table(header, rows, row_classes=["", "best", ""])
    note = (f"Over all {len(pos[0])} poses of this file (paper eqs. 39-43, w_pos = {W_POS:g}/m, w_rot = {W_ROT:g}). "
            "These may include the model's training poses; held-out figures are in the ledger below.")
    tm = (model_info or {}).get("test_metrics")
    if isinstance(tm, Mapping) and tm.get("rmse_pos") is not None:
        n = f" on {tm['n']} held-out poses" if tm.get("n") else ""
        rot_text = f", rmse_rot {_num(tm.get('rmse_rot'), 1e3)} mrad" if tm.get("rmse_rot") is not None else ""
        body += (f'<p class="note">The model\'s own test metrics{_e(n)} (from its metadata): rmse_pos '
                 f"{_num(tm.get('rmse_pos'), 1e3)} mm{rot_text}, rmse_total {_num(tm.get('rmse_total'), 1e3)}"
                 f"{' mm + mrad' if rot_text else ' mm'}.</p>")
    return _section("metrics", "Metrics", body, _e(note))


def _worst_section(table: PoseTable, feats: Mapping[str, np.ndarray], pos: tuple[np.ndarray, np.ndarray],
                   rot: tuple[np.ndarray, np.ndarray] | None) -> str:
    total = worst_order(pos[1], None if rot is None else rot[1])[:N_WORST]
    ids = table.extras.get("id")
    shown = [f for f in ("range", "azimuth", "elevation", "incidence", "roll", "pitch", "yaw", "t") if f in feats]
    header = ["#", "id", "row", "x [m]", "y [m]", "z [m]", "pos err [mm]"]
    if rot is not None:
        header.append("rot err [mrad]")
    header.append("raw pos [mm]")
    if rot is not None:
        header.append("raw rot [mrad]")
    header += [f"{f} [{FEATURE_UNITS[f]}]" for f in shown]
    rows = []
    for rank, i in enumerate(total, start=1):
        row = [str(rank), _e(ids[i]) if ids is not None else "–", str(int(i)),
               *(f"{v:.3f}" for v in table.ref_p[i]), f"{pos[1][i] * 1e3:.3f}"]
        if rot is not None:
            row.append(f"{rot[1][i] * 1e3:.3f}")
        row.append(f"{pos[0][i] * 1e3:.3f}")
        if rot is not None:
            row.append(f"{rot[0][i] * 1e3:.3f}")
        for f in shown:
            v = _feature_display(f, np.asarray(feats[f][i:i + 1], float))[0]
            row.append(f"{round(v, 1) + 0.0:.1f}" if f != "range" else f"{v:.3f}")  # + 0.0: no "-0.0"
        rows.append(row)
    crit = "position error + rotation error (1 mm ≙ 1 mrad, paper eq. 43)" if rot is not None else "position error"
    note = (f"The {len(total)} poses with the largest corrected error, ranked by {crit}. "
            "row: 0-based data row of the table; x, y, z: reference position.")
    return _section("worst", "Worst poses after correction", _table(header, rows, left=2, compact=True), _e(note))


def _diagnosis_section(diagnosis: Mapping[str, Any] | None, model_effects: Sequence[str]) -> str:
    line = takeaway(diagnosis, model_effects)
    body = f'<p class="takeaway" id="takeaway">{_e(line)}</p>'
    if not diagnosis:
        return _section("diagnosis", "Diagnosis", body)
    candidates = sorted([c for c in diagnosis.get("candidates") or [] if isinstance(c, Mapping)],
                        key=lambda c: (c.get("rank") if isinstance(c.get("rank"), (int, float)) else 1e9))
    if candidates:
        header = ["rank", "effect", "present", "score", "p-value", "cv RMSE before", "cv RMSE after", "gain"]
        rows, classes = [], []
        for c in candidates:
            b, a = c.get("cv_rmse_before"), c.get("cv_rmse_after")
            numbers = isinstance(b, (int, float)) and isinstance(a, (int, float))
            gain = f"{b / a:.2f}×" if numbers and a > 0 else "–"
            rows.append([_e(c.get("rank", "")), _e(c.get("effect", "?")), "yes" if c.get("present") else "no",
                         _num(c.get("score")), _e(_p_value(c.get("p_value"))),
                         _num(b, 1e3), _num(a, 1e3), gain])
            classes.append("present" if c.get("present") else "")
        body += "<h3>Candidate effects the model lacks</h3>" + _table(header, rows, left=3, row_classes=classes)
        body += ('<p class="note">Highlighted: present (the test says adding the effect helps). '
                 "cv RMSE: cross-validated, shown ×1000 (mm, or mm + mrad for full poses).")
        if diagnosis.get("test"):
            body += " Test: " + _e(diagnosis["test"]) + "."
        body += "</p>"
    aliases = [a for a in diagnosis.get("aliases") or [] if a]
    if aliases:
        body += ("<h3>Aliases</h3><p>Effects this data cannot tell apart (fitting one absorbs the other): "
                 + "; ".join(" ≈ ".join(_e(x) for x in a) for a in aliases) + "</p>")
    undetermined = [u for u in diagnosis.get("undetermined") or [] if isinstance(u, Mapping)]
    if undetermined:
        body += ("<h3>Not ranked: this data cannot determine them</h3><ul>"
                 + "".join(f"<li><b>{_e(u.get('effect', '?'))}</b>: {_e(u.get('reason', ''))}</li>"
                           for u in undetermined) + "</ul>")
    feats = [f for f in diagnosis.get("features") or [] if isinstance(f, Mapping)]
    if feats:
        body += "<h3>Residual structure by feature</h3>"
        rows = [[_e(f.get("feature", "?")),
                 f"{f['r2']:.3f}" if isinstance(f.get("r2"), (int, float)) else "–"] for f in feats]
        classes = ["present" if isinstance(f.get("r2"), (int, float)) and f["r2"] >= 0.1 else "" for f in feats]
        body += ('<div style="display:flex;gap:24px;align-items:flex-start;flex-wrap:wrap"><div>'
                 + _table(["feature", "cv R²"], rows, row_classes=classes) + "</div><div>"
                 + _img(_r2_figure(feats), "cross-validated R² of the residual per feature") + "</div></div>")
        body += ('<p class="note">R² near 0: the feature explains nothing of what is left; highlighted '
                 "(R² ≥ 0.1): structure that the model misses along that feature.</p>")
    known = {"candidates", "features", "aliases", "model_effects", "test", "undetermined"}
    other = {k: v for k, v in diagnosis.items() if k not in known and isinstance(v, (str, int, float))}
    if other:
        body += '<dl class="kv">' + "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in other.items()) + "</dl>"
    return _section("diagnosis", "Diagnosis", body)


def _segments_section(segments: Mapping[str, Any] | None) -> str:
    """Where the robot stood still in the recording the table came from (`posecorr ingest`):
    every segment found, the rejected ones with their reason, and the clock offset."""
    if not segments:
        return _section("segments", "Still segments",
                        _e("The table does not come from `posecorr ingest` (no TABLE.csv.segments.json beside it)."))
    rows, classes = [], []
    for seg in segments.get("segments") or []:
        rows.append([_e(seg.get("segment", "")), _e(seg.get("row", "–")), _e(seg.get("status", "")),
                     _e(seg.get("reason") or ""), f"{seg.get('start_s', float('nan')):.2f}",
                     f"{seg.get('duration_s', float('nan')):.2f}", _e(seg.get("kept_samples", "")),
                     f"{seg['jitter_mm']:.3f}" if isinstance(seg.get("jitter_mm"), (int, float)) else "–"])
        classes.append("present" if seg.get("status") == "rejected" else "")
    offset = segments.get("offset_s")
    head = (f"{segments.get('segments_found', len(rows))} still segments found, "
            f"{segments.get('segments_rejected', 0)} rejected (highlighted, with the reason); clock offset "
            + (f"{offset:+.4f} s ({segments.get('offset_source', '?')})" if isinstance(offset, (int, float)) else "?"))
    table = _table(["segment", "row", "status", "reason", "start [s]", "duration [s]", "samples kept", "jitter [mm]"],
                   rows, left=4, row_classes=classes)
    return _section("segments", "Still segments", f"<p>{_e(head)}</p>" + table)


def _ledger_section(ledger: Sequence[Mapping[str, Any]]) -> str:
    if not ledger:
        return _section("ledger", "Ledger", "<p>No models fitted on this data yet (the ledger is empty).</p>")
    header = ["#", "time", "model", "effects", "method", "representation", "held-out",
              "rmse_pos [mm]", "rmse_rot [mrad]", "rmse_total [mm + mrad]", "improvement (total)"]
    rows = []
    totals = []
    for k, entry in enumerate(ledger, start=1):
        kind, block = _held_out(entry)
        totals.append(block.get("rmse_total") if isinstance(block.get("rmse_total"), (int, float)) else math.inf)
        imp = block.get("improvement_total")
        when = str(entry.get("time", "")).replace("T", " ").removesuffix("+00:00")
        model = str(entry.get("model", ""))
        rows.append([str(k), _e(when), f'<span title="{_e(model)}">{_e(Path(model).name if model else "")}</span>',
                     _e(",".join(_as_list(entry.get("effects"))) or "none"), _e(entry.get("method", "")),
                     _e(entry.get("representation", "")), _e(kind or "–"),
                     _num(block.get("rmse_pos"), 1e3), _num(block.get("rmse_rot"), 1e3),
                     _num(block.get("rmse_total"), 1e3), (_num(imp) + "×") if imp is not None else "–"])
    best = int(np.argmin(totals)) if any(math.isfinite(t) for t in totals) else -1
    classes = ["best" if k == best else "" for k in range(len(rows))]
    body = _table(header, rows, left=7, row_classes=classes, compact=True)
    fig = _ledger_figure(ledger)
    if fig is not None:
        body += _img(fig, "held-out rmse_total per ledger entry")
    note = "Every model fitted on this data, oldest first; highlighted: the lowest held-out rmse_total."
    return _section("ledger", "Ledger: models fitted on this data", body, _e(note))


# --------------------------------------------------------------------------- API

def worst_order(pos_err: np.ndarray, rot_err: np.ndarray | None = None) -> np.ndarray:
    """Row indices sorted worst first by w_pos * pos_err (m) + w_rot * rot_err (rad) (eq. 43 per pose)."""
    score = W_POS * np.asarray(pos_err, float)
    if rot_err is not None:
        score = score + W_ROT * np.asarray(rot_err, float)
    return np.argsort(-score, kind="stable")


def write_report(output_path: str | Path, table: PoseTable, corrected: np.ndarray,
                 model_info: Mapping[str, Any] | None = None, diagnosis: Mapping[str, Any] | None = None,
                 ledger: Sequence[Mapping[str, Any]] = (), title: str | None = None,
                 segments: Mapping[str, Any] | None = None) -> Path:
    """Write the self-contained HTML report of `table` against its (N, 7) `corrected` poses.

    model_info: `onnx_meta.read_info` of the model (optional); diagnosis: the `diagnose --json`
    dict (optional, unknown keys are shown or ignored); ledger: `ledger.read_ledger` records;
    segments: the sidecar `posecorr ingest` writes beside the table (TABLE.csv.segments.json).
    Returns the written path. Raises ValueError when `corrected` does not fit the table.
    """
    corrected = np.asarray(corrected, dtype=float)
    if corrected.shape != (table.n, 7):
        raise ValueError(f"corrected has shape {corrected.shape}, expected ({table.n}, 7) "
                         f"for {table.path or 'the table'}")
    if not np.all(np.isfinite(corrected)):
        raise ValueError("corrected poses contain NaN or inf")
    if table.n == 0:
        raise ValueError(f"{table.path or 'the table'}: no poses to report on")
    with_rot = table.has_orientation
    reference, measured = table.reference, table.measured
    pos_b, rot_b = pose_errors(reference, measured, with_rot)
    pos_a, rot_a = pose_errors(reference, corrected, with_rot)
    pos = (pos_b, pos_a)
    rot = (rot_b, rot_a) if with_rot and rot_b is not None and rot_a is not None else None
    raw = pose_metrics(reference, measured, with_rot)
    corr = pose_metrics(reference, corrected, with_rot)
    block = metric_block(raw, corr)
    feats = table_features(table)
    name = title or f"posecorr report: {Path(table.path).name if table.path else 'table'}"
    if model_info and model_info.get("file"):
        name = title or f"{name} vs {Path(str(model_info['file'])).name}"

    parts = [_summary_section(table, model_info, name),
             _metrics_section(raw, corr, block, pos, rot, model_info)]

    fig = _workspace_figure(table.ref_p, measured[:, :3] - table.ref_p, corrected[:, :3] - table.ref_p)
    parts.append(_section("workspace", "Residual arrows over the workspace",
                          _img(fig, "position error vectors in x-y, x-z, y-z, before and after"),
                          _e("Arrow = measured (top) or corrected (bottom) minus reference position, drawn at the "
                             "reference position, in three projections; colour = 3D error magnitude. "
                             "Arrows are magnified; the key in each panel gives the scale.")))

    body = _img(_features_figure(feats, pos_b * 1e3, pos_a * 1e3, "position error", "mm"),
                "position error against features")
    if rot is not None:
        body += _img(_features_figure(feats, rot[0] * 1e3, rot[1] * 1e3, "rotation error", "mrad"),
                     "rotation error against features")
    note = ("Features of the reference pose (angles in degrees; azimuth/elevation as seen from the station, "
            "incidence: tracker z axis vs line of sight). A trend in the blue median line is structure "
            "the model misses." + ("" if "t" in feats else " No time column: t is not shown."))
    parts.append(_section("features", "Error against features", body, _e(note)))

    fig = _orientation_figure(feats, pos_a * 1e3, None if rot is None else rot[1] * 1e3,
                              pos_b * 1e3, None if rot is None else rot[0] * 1e3)
    parts.append(_section("orientation", "Error by orientation",
                          _img(fig, "corrected error grouped by roll, pitch, yaw"),
                          _e("Roll, pitch, yaw of the reference orientation relative to upright (Z-Y-X); "
                             "distinct values when there are few, else equal-width bins.")))

    fig = _histogram_figure((pos_b * 1e3, pos_a * 1e3), None if rot is None else (rot[0] * 1e3, rot[1] * 1e3))
    parts.append(_section("histograms", "Error histograms", _img(fig, "error histograms before and after"),
                          _e("Log-spaced bins so both the raw and the corrected errors are readable.")))

    parts.append(_worst_section(table, feats, pos, rot))
    parts.append(_diagnosis_section(diagnosis, _model_effects(model_info, diagnosis)))
    parts.append(_ledger_section(list(ledger)))
    parts.append(_segments_section(segments))

    nav = "".join(f'<a href="#{sid}">{_e(label)}</a>' for sid, label in SECTIONS)
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><title>{_e(name)}</title>"
            f"<style>{_CSS}</style></head><body><header><h1>{_e(name)}</h1></header><nav>{nav}</nav><main>"
            + "".join(parts) + "</main></body></html>\n")
    from .safeio import write_text

    out = Path(output_path)
    write_text(out, page)  # atomic: an interrupted report leaves the previous page
    return out


def screenshot(html_path: str | Path, png_path: str | Path, width: int = 1280, height: int = 2400) -> bool:
    """Screenshot a page with headless Chromium; False when no Chromium is installed or it fails."""
    browser = next((shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome", "chrome")
                    if shutil.which(b)), None)
    if browser is None:
        return False
    png = Path(png_path).resolve()
    cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           f"--screenshot={png}", f"--window-size={int(width)},{int(height)}",
           Path(html_path).resolve().as_uri()]
    try:
        subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    except (OSError, subprocess.SubprocessError):
        return False
    return png.exists() and png.stat().st_size > 0
