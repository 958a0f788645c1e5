"""The report's figures (matplotlib, Agg backend): each function returns a figure, `to_png` renders it.

Errors come in mm / mrad, feature angles in rad (shown in degrees). matplotlib is imported
inside the functions, so that importing this module (and the CLI) stays cheap. The page
(`page`) embeds the PNGs; what counts as structure or as the best ledger entry comes from
`interpretation`, so a figure and the text beside it never disagree.
"""
from __future__ import annotations

import io
import math
import re
from typing import Any, Mapping, Sequence

import numpy as np

from .features import FEATURES
from .interpretation import effect_list, effects_step, is_structure
from .ledger import held_out, plan_name

DPI = 100
ANGLE_FEATURES = ("azimuth", "elevation", "incidence", "roll", "pitch", "yaw")
FEATURE_UNITS = {"x": "m", "y": "m", "z": "m", "range": "m", "t": "s", **{a: "deg" for a in ANGLE_FEATURES}}
BEFORE_COLOUR = "0.6"        # grey: raw measurements
AFTER_COLOUR = "#1f77b4"     # blue: corrected by the model
BEFORE_MEDIAN = {"color": "0.3", "lw": 1.4, "ls": "--"}
AFTER_MEDIAN = {"color": "#0b3d66", "lw": 2.0, "ls": "-"}
# A floor for log axes: an error of exactly zero (a pass-through orientation) has no log.
LOG_FLOOR_MM = 1e-4


def to_png(fig: Any) -> bytes:
    """A matplotlib figure rendered as PNG bytes; the figure is closed."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    return buf.getvalue()


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


def feature_display(name: str, values: np.ndarray) -> np.ndarray:
    """Feature values in display units (angles in degrees)."""
    return np.degrees(values) if name in ANGLE_FEATURES else values


def _nice_length(x: float) -> float:
    """The round number (1, 2, 5 x 10^k) nearest to x > 0 on a log scale (a key arrow's length)."""
    if not x > 0 or not math.isfinite(x):
        return 1.0
    k = math.floor(math.log10(x))
    options = [m * 10.0 ** (k + d) for d in (0, 1) for m in (1, 2, 5)]
    return min(options, key=lambda v: abs(math.log(v / x)))


# The fewest poses a box or a point of a median line stands for: the median of one or two
# poses is those poses, and a line or a box per pose draws their noise as a trend.
MIN_PER_GROUP = 3


def _groups(values: np.ndarray, max_distinct: int = 13, n_bins: int = 8) -> tuple[list[str], list[np.ndarray]]:
    """Group indices by distinct value (rounded to 0.1) when few, else by equal-width bins; by
    equal-count bins where those groups would hold fewer than MIN_PER_GROUP poses. A bin is
    labelled "≈" its median in whole degrees: eight ranges ("-163.4…-108.9") overlap on a panel.

    A spread below 1 (deg) is one group: a fixed orientation seen through tracker noise (as in a
    position-only table, whose orientation is the measured one) is no variable to group by.
    """
    if np.ptp(values) < 1.0:
        return [f"≈{np.mean(values) + 0.0:.1f} (fixed)"], [np.arange(len(values))]
    rounded = np.round(values, 1)
    distinct = np.unique(rounded)
    if len(distinct) <= max_distinct:
        # + 0.0 turns -0.0 into 0.0, so no "-0" label
        labels, index = [f"{v + 0.0:g}" for v in distinct], [np.flatnonzero(rounded == v) for v in distinct]
    else:
        edges = np.linspace(values.min(), values.max(), n_bins + 1)
        which = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, n_bins - 1)
        labels, index = [], []
        for b in range(n_bins):
            idx = np.flatnonzero(which == b)
            if idx.size:
                labels.append(_bin_label(values[idx]))
                index.append(idx)
    if min(map(len, index)) >= MIN_PER_GROUP:
        return labels, index
    chunks = np.array_split(np.argsort(values, kind="stable"), max(1, min(n_bins, len(values) // MIN_PER_GROUP)))
    labels = [_bin_label(values[c]) for c in chunks]
    if len(set(labels)) < len(labels):  # bins within a degree of each other: a decimal tells them apart
        labels = [_bin_label(values[c], 1) for c in chunks]
    return labels, [np.sort(c) for c in chunks]


def _bin_label(values: np.ndarray, digits: int = 0) -> str:
    return f"≈{round(float(np.median(values)), digits) + 0.0:.{digits}f}"  # + 0.0: no "-0"


def _binned_median(x: np.ndarray, y: np.ndarray, n_bins: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Median of y per distinct x (if few, each of MIN_PER_GROUP poses or more), else per
    equal-count bin of x of MIN_PER_GROUP poses or more; empty where that makes fewer than two
    bins (no line)."""
    distinct, counts = np.unique(x, return_counts=True)
    if len(distinct) <= 15 and counts.min() >= MIN_PER_GROUP:
        return distinct, np.array([np.median(y[x == v]) for v in distinct])
    bins = min(n_bins, len(x) // MIN_PER_GROUP)
    if bins < 2:
        return np.empty(0), np.empty(0)
    chunks = np.array_split(np.argsort(x, kind="stable"), bins)
    return np.array([np.median(x[c]) for c in chunks]), np.array([np.median(y[c]) for c in chunks])


def _jitter(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Horizontal jitter for a feature with few distinct values, so stacked points show."""
    distinct = np.unique(x)
    if len(distinct) > 15 or len(x) < 2:
        return x
    gap = np.min(np.diff(distinct)) if len(distinct) > 1 else 1.0
    return x + rng.uniform(-0.15, 0.15, size=x.shape) * gap


def _arrow_length(ref_p: np.ndarray) -> float:
    """Drawn length (m) of a typical (95th-percentile) error arrow: 0.6 of the lattice spacing.

    The spacing is estimated from the number of distinct positions as if they filled a cube,
    so arrows of neighbouring lattice points rarely overlap; capped at a quarter of the span.
    """
    span = float(np.max(np.ptp(ref_p, axis=0))) or 0.1
    distinct = len(np.unique(np.round(ref_p, 4), axis=0))
    per_axis = max(distinct ** (1 / 3) - 1, 1.0)
    return min(0.6 * span / per_axis, 0.25 * span)


# The after row shares the before row's magnification where its arrows stay readable at it: a
# typical corrected arrow a third of a typical before arrow still shows its direction. The real
# sessions (after / before 0.6 and 1.0) share one; the loop guide's session, its error taken
# eight times down (0.12), would be dots: its after row is magnified more, and says so.
SHARED_SCALE_MIN_RATIO = 1 / 3


def arrow_typical_mm(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """The error (mm) each row's arrows are scaled to, drawn at one length, for (N, 3) error
    vectors (m) before and after: the larger row's typical (95th-percentile) magnitude for
    both where the smaller is at least SHARED_SCALE_MIN_RATIO of it, else each row's own."""
    typical = (_typical_mm(before), _typical_mm(after))
    if min(typical) >= SHARED_SCALE_MIN_RATIO * max(typical):
        return max(typical), max(typical)
    return typical


def arrow_keys_mm(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """The key arrows' lengths (mm), before and after, in `workspace_figure`: the round number
    nearest each row's `arrow_typical_mm`."""
    typical = arrow_typical_mm(before, after)
    return _nice_length(typical[0]), _nice_length(typical[1])


def _typical_mm(errors: np.ndarray) -> float:
    ref_mm = float(np.percentile(np.linalg.norm(errors, axis=1) * 1e3, 95))
    return ref_mm if ref_mm > 0 else 1.0


def _colour_limits(mag_mm: np.ndarray) -> tuple[float, float]:
    lo, hi = (float(v) for v in np.percentile(mag_mm, [1, 99]))
    return (lo, hi) if hi > lo else (0.0, max(hi, 1e-9))  # a 1-99 % range keeps colour contrast


def magnification_words(factor: float, other: str) -> str:
    """"magnified 8.2× more than the before row" for a row magnified `factor` times the other's."""
    more = factor >= 1
    times = float(f"{factor if more else 1 / factor:.2g}")
    return f"magnified {times:g}× {'more' if more else 'less'} than the {other} row"


def workspace_figure(ref_p: np.ndarray, before: np.ndarray, after: np.ndarray,
                     before_label: str = "before correction", after_label: str = "after correction") -> Any:
    """Quiver of position error vectors (m) at the reference positions, 3 projections x 2 rows,
    at one magnification and colour scale unless the after's arrows would be too small to see
    at the before's (`arrow_typical_mm`): then each row has its own, every title says how the
    row's magnification compares with the other's and each row has its own colour bar."""
    plt = _pyplot()
    span = float(np.max(np.ptp(ref_p, axis=0))) or 0.1
    length = _arrow_length(ref_p)
    projections = ((0, 1), (0, 2), (1, 2))
    names = "xyz"
    fig, axes = plt.subplots(2, 3, figsize=(12, 8.4), layout="constrained")
    typical = arrow_typical_mm(before, after)
    shared = typical[0] == typical[1]
    mags = [np.linalg.norm(d, axis=1) * 1e3 for d in (before, after)]
    clims = [_colour_limits(np.concatenate(mags))] * 2 if shared else [_colour_limits(m) for m in mags]
    # a row's magnification over the other's: the other's typical error over its own
    words = ("", "") if shared else (f"\n{magnification_words(typical[1] / typical[0], 'after')}",
                                     f"\n{magnification_words(typical[0] / typical[1], 'before')}")
    for row, (label, d) in enumerate(((before_label, before), (after_label, after))):
        scale = (typical[row] / 1e3) / length
        key_mm = _nice_length(typical[row])
        order = np.argsort(mags[row])  # largest arrows on top
        for col, (i, j) in enumerate(projections):
            ax = axes[row, col]
            q = ax.quiver(ref_p[order, i], ref_p[order, j], d[order, i], d[order, j], mags[row][order],
                          angles="xy", scale_units="xy", scale=scale, cmap="viridis", clim=clims[row],
                          width=0.0045, headwidth=3.5, headlength=4, headaxislength=3.5, alpha=0.9)
            pad = 0.12 * span + length
            ax.set_xlim(ref_p[:, i].min() - pad, ref_p[:, i].max() + pad)
            ax.set_ylim(ref_p[:, j].min() - pad, ref_p[:, j].max() + pad)
            ax.set_aspect("equal", adjustable="box")
            ax.set_xlabel(f"{names[i]} [m]")
            ax.set_ylabel(f"{names[j]} [m]")
            ax.set_title(f"{names[i]}-{names[j]}, {label}{words[row]}")
            # Inside the lower right corner, in the margin the limits leave: on the title's line
            # it overlapped the longer titles (a y-z panel's). The arrow starts at X: its end stays inside.
            reach = (key_mm / 1e3 / scale) / (np.ptp(ref_p[:, i]) + 2 * pad)
            ax.quiverkey(q, 0.96 - reach, 0.05, key_mm / 1e3, f"{key_mm:g} mm", labelpos="W", coordinates="axes",
                         color="#d62728", fontproperties={"size": 8})
        if not shared:
            fig.colorbar(q, ax=axes[row, :], shrink=0.85, pad=0.01).set_label(f"|error| [mm], {label} only")
    if shared:
        fig.colorbar(q, ax=axes, shrink=0.6, pad=0.01).set_label("|error| [mm], both rows")
    fig.suptitle("Position error vectors at the reference positions, magnified (red key arrow per panel; "
                 + ("the same magnification and colours in both rows)" if shared else
                    "the rows differ in magnification and colours, as their titles say)"), fontsize=10)
    return fig


def features_figure(features: Mapping[str, np.ndarray], before_mm: np.ndarray, after_mm: np.ndarray,
                     quantity: str, unit: str, before_label: str = "raw", after_label: str = "corrected") -> Any:
    """Scatter of per-pose error (log y) against each feature, before grey, after blue."""
    from matplotlib.ticker import MaxNLocator

    plt = _pyplot()
    names = [f for f in FEATURES if f in features]
    ncols = 4
    nrows = math.ceil(len(names) / ncols)
    spare = len(names) < nrows * ncols
    # Without a spare panel the legend takes a strip between the title and the panels.
    top = 0.4 if spare else 0.7
    height = 2.55 * nrows + top
    # Fixed margins instead of constrained layout: that layout engine costs seconds per figure
    # here (it measures every tick label), and this grid has the same layout every time.
    fig, axes = plt.subplots(nrows, ncols, figsize=(12, height), sharey=True, squeeze=False,
                             gridspec_kw=_margins(12, height, left=0.75, right=0.15, top=top, bottom=0.5,
                                                  wspace=0.16, hspace=0.42))
    rng = np.random.default_rng(0)  # fixed jitter: the same page for the same data
    b = np.maximum(before_mm, LOG_FLOOR_MM)
    a = np.maximum(after_mm, LOG_FLOOR_MM)
    size = 6 if len(b) > 1000 else 10
    medians = False
    for k, name in enumerate(names):
        ax = axes.flat[k]
        x = feature_display(name, np.asarray(features[name], float))
        xj = _jitter(x, rng)
        ax.scatter(xj, b, s=size, c=BEFORE_COLOUR, alpha=0.35, linewidths=0, rasterized=True, label="before")
        ax.scatter(xj, a, s=size, c=AFTER_COLOUR, alpha=0.45, linewidths=0, rasterized=True, label="after")
        # before dashed, after solid: where the model changes little the two lie on each other
        for y, style in ((b, BEFORE_MEDIAN), (a, AFTER_MEDIAN)):
            mx, my = _binned_median(x, y)
            if mx.size:
                ax.plot(mx, my, marker="o", ms=3, **style)
                medians = True
        ax.set_yscale("log")
        _plain_log(ax, "y", (1.0, 2.0, 5.0), minor=False)
        ax.set_xlabel(f"{name} [{FEATURE_UNITS.get(name, '')}]")
        # a panel is 2.6 inches wide: at most 5 labels, or '-0.025' runs into '-0.020'; the gap
        # between panels (wspace) leaves room for an edge label on each side, '2.4' beside '-0.032'
        ax.xaxis.set_major_locator(MaxNLocator(nbins=5))
        if k % ncols == 0:
            ax.set_ylabel(f"{quantity} [{unit}]")
        ax.grid(True, which="major", alpha=0.3)
    for k in range(len(names), nrows * ncols):
        ax = axes.flat[k]
        ax.axis("off")
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], ls="", marker="o", color=BEFORE_COLOUR, label=f"before ({before_label})"),
               Line2D([], [], ls="", marker="o", color=AFTER_COLOUR, label=f"after ({after_label})"),
               Line2D([], [], label="binned median, before (dashed)", **BEFORE_MEDIAN),
               Line2D([], [], label="binned median, after (solid)", **AFTER_MEDIAN)][:4 if medians else 2]
    if spare:
        axes.flat[len(names)].legend(handles=handles, loc="center")
    else:
        fig.legend(handles=handles, loc="upper center", ncols=len(handles), bbox_to_anchor=(0.5, 1 - 0.3 / height))
    fig.suptitle(f"Per-pose {quantity} against features (log scale)", fontsize=10)
    return fig


def orientation_figure(features: Mapping[str, np.ndarray], pos_mm: np.ndarray, rot_mrad: np.ndarray | None,
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
            binned = any(label.startswith("≈") and not label.endswith("(fixed)") for label in labels)
            ax.set_xlabel(f"{angle} [deg]" + (", ≈ median of a bin" if binned else ""))
            ax.set_ylabel(f"{quantity} after [{unit}]")
            ax.set_ylim(bottom=0)
            if len(labels) > 8:
                ax.tick_params(axis="x", labelrotation=45)
            ax.grid(True, axis="y", alpha=0.3)
            fewest, most = min(map(len, index)), max(map(len, index))
            ax.set_title(f"{quantity} by {angle} (n per box: {fewest}{f'–{most}' if most > fewest else ''})")
    fig.suptitle("Corrected error grouped by orientation (boxes: quartiles, whiskers 1.5 IQR)", fontsize=10)
    return fig


def histogram_figure(pos: tuple[np.ndarray, np.ndarray], rot: tuple[np.ndarray, np.ndarray] | None,
                     before_label: str = "raw", after_label: str = "corrected") -> Any:
    """Histograms on log-spaced bins so raw and corrected (20x apart) are both readable."""
    plt = _pyplot()
    from matplotlib.ticker import MaxNLocator

    panels = [("position error", "mm", pos)]
    if rot is not None:
        panels.append(("rotation error", "mrad", rot))
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 3.9), layout="constrained", squeeze=False)
    for ax, (quantity, unit, (before, after)) in zip(axes.flat, panels):
        b = np.maximum(before, LOG_FLOOR_MM)
        a = np.maximum(after, LOG_FLOOR_MM)
        lo = max(min(b.min(), a.min()), LOG_FLOOR_MM)
        hi = max(b.max(), a.max(), lo * 10)
        # About two bins per square root of the poses: 50 bins over 11 poses are 11 spikes.
        bins = np.logspace(np.log10(lo), np.log10(hi), int(np.clip(2 * np.sqrt(len(b)), 8, 50)) + 1)
        ax.hist(b, bins=bins, color=BEFORE_COLOUR, alpha=0.7, label=f"before ({before_label})")
        ax.hist(a, bins=bins, color=AFTER_COLOUR, alpha=0.7, label=f"after ({after_label})")
        # dashed before, solid after, as the feature panels' medians
        for v, colour, style, name in ((before, "0.3", "--", "before"), (after, "#0b3d66", "-", "after")):
            r = float(np.sqrt(np.mean(np.square(v))))
            if r > 0:
                ax.axvline(r, color=colour, ls=style, lw=1.2, label=f"RMSE {name}: {r:.3g} {unit}")
        ax.set_xscale("log")
        # within two decades a label per decade leaves one or two labels: 1, 2 and 5 too
        _plain_log(ax, "x", (1.0,) if bins[-1] / bins[0] > 100 else (1.0, 2.0, 5.0), minor=False)
        ax.set_xlabel(f"{quantity} [{unit}] (log scale)")
        ax.set_ylabel("poses")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))  # a count of poses
        # Above the panel, not inside it: the tallest bars or an RMSE line stood under any corner
        # (the loop's before bars reach the top right, a real session's the top left). Two
        # columns: a row per before and after, its bars beside its RMSE.
        ax.legend(loc="lower left", bbox_to_anchor=(0, 1.02, 1, 0.2), mode="expand", ncols=2, borderaxespad=0)
        ax.grid(True, alpha=0.3)
    return fig


def r2_figure(features: Sequence[Mapping[str, Any]]) -> Any:
    """Horizontal bars of the cross-validated R^2 of the residual per feature."""
    plt = _pyplot()
    names = [str(f.get("feature", "?")) for f in features]
    r2 = np.array([float(f["r2"]) if f.get("r2") is not None else np.nan for f in features])
    fig, ax = plt.subplots(figsize=(6.5, 0.28 * len(names) + 1.0), layout="constrained")
    y = np.arange(len(names))
    colours = [("#d95f02" if is_structure(v) else AFTER_COLOUR) for v in np.nan_to_num(r2)]
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


def _mm(block: Any, key: str = "rmse_pos") -> float:
    v = block.get(key) if isinstance(block, Mapping) else None
    return float(v) * 1e3 if isinstance(v, (int, float)) and v > 0 else np.nan


def _wrap_at_commas(text: str, width: int) -> str:
    """Each line of `text` broken after its commas into lines of at most `width` characters
    where it can be (a single longer item stays whole)."""
    out = []
    for line in text.split("\n"):
        current = ""
        for item in re.split(r"(?<=,)", line):
            if current and len(current) + len(item) > width:
                out.append(current)
                item = item.lstrip()
                current = ""
            current += item
        out.append(current)
    return "\n".join(out)


def ledger_figure(ledger: Sequence[Mapping[str, Any]]) -> Any | None:
    """The loop's history: the held-out rmse_pos of each fit in the ledger, oldest first (log y),
    with the best rigid fit on the same poses (the ledger line's `baseline`) as a dashed line."""
    values, floor, labels = [], [], []
    previous: list[str] | None = None
    for k, entry in enumerate(ledger, start=1):
        values.append(_mm(held_out(entry)[1]))
        floor.append(_mm(entry.get("baseline")))
        effects = [str(e) for e in effect_list(entry.get("effects"))]
        labels.append(f"{k}: {effects_step(previous, effects)}\n{entry.get('method', '')}, {plan_name(entry) or '?'}")
        previous = effects
    y, rigid = np.array(values), np.array(floor)
    if not np.isfinite(y).any():
        return None
    plt = _pyplot()
    width = max(6.0, min(12.0, 1.3 * len(y) + 3))
    # A 7 pt character is about 0.055 in: a label wider than its fit's share of the axis ran
    # into its neighbour's ("5: -mount,session_strain,sweep6: +mount,...").
    labels = [_wrap_at_commas(label, int((width - 1.0) / len(y) / 0.055)) for label in labels]
    fig, ax = plt.subplots(figsize=(width, 3.6), layout="constrained")
    x = np.arange(1, len(y) + 1)
    if np.isfinite(rigid).any():
        ax.step(x, rigid, where="mid", color="0.45", ls="--", lw=1.4, label="best rigid fit, same poses")
    ax.step(x, y, where="mid", color=AFTER_COLOUR, lw=1.8, label="model, held-out")
    ax.plot(x, y, "o", color="#0b3d66")
    best = np.nanargmin(y)
    ax.plot(x[best], y[best], "*", color="#d95f02", ms=13, ls="", label=f"best: {y[best]:.3g} mm")
    for xi, yi in zip(x, y):
        if np.isfinite(yi):
            ax.annotate(f"{yi:.3g}", (xi, yi), textcoords="offset points", xytext=(6, 4), fontsize=8)
    ax.set_yscale("log")
    _plain_log(ax, "y")
    both = np.concatenate([y[np.isfinite(y)], rigid[np.isfinite(rigid)]])
    ax.set_ylim(both.min() / 1.6, both.max() * 1.8)  # room for the value labels
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_xlim(0.5, len(y) + 0.5)
    ax.set_ylabel("held-out rmse_pos [mm]")
    ax.set_xlabel("fit in the ledger (effects added or removed, method, held-out plan)")
    ax.grid(True, which="both", alpha=0.3)
    # Above the axes in one row: inside, the first fits (the highest errors, left) or the rigid
    # line (across the top) stood under any corner.
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.01), ncols=3, borderaxespad=0)
    return fig
