"""The self-contained HTML report: measurements against a model (`posecorr report`).

One file, no external resources: figures are PNGs embedded as base64 data URIs, the CSS is
inline and there is no JavaScript (the tests load it in headless Chromium:
`screenshot.check_page`). The page lets a user compare a model with the measurements, see
where it fails, read which physical effect the diagnosis says is missing, and watch the
held-out error fall across the ledger of models fitted on the same data.

Sections (HTML ids): summary, metrics, workspace, features, orientation, histograms, worst,
diagnosis, ledger, and segments for a table from `posecorr ingest`. Units on the page: mm and
mrad; angles of features in degrees. All numbers handed in are SI (m, rad, s), as everywhere
in posecorr.

What the page compares comes from `comparison`: the before is raw where the frames are
registered, the best rigid fit's residual where they are not; the after is held-out where the
ledger holds the fit that wrote the model, in-sample otherwise (said in the metrics table).

This module assembles the HTML; the plots are drawn by `figures` (matplotlib, imported only
when a figure is drawn, so `import posecorr.analysis.page` stays cheap for the CLI) and
the words that read the diagnosis, the ledger and the worst poses come from `interpretation`.
"""
from __future__ import annotations

import base64
import html
import math
import re
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from ..controller.onnx_meta import describe_corrector, stated_metrics
from ..data import PoseTable
from ..metrics import RULE, W_POS, W_ROT, block_name, pose_errors
from ..safeio import write_text
from . import figures
from .comparison import Comparison, compare, rigid_label
from .features import UNPLACED_STATION, table_features
from .interpretation import (STRUCTURE_R2, alias_text, cv_gain, effect_list, is_structure, model_effects,
                             not_ranked_why, p_value_text, ranked_candidates, split_features, takeaway, worst_order)
from .ledger import held_out, plan_name

SECTIONS = (("summary", "Summary"), ("metrics", "Metrics"), ("workspace", "Workspace"),
            ("features", "Error vs features"), ("orientation", "Orientation"),
            ("histograms", "Histograms"), ("worst", "Worst poses"), ("diagnosis", "Diagnosis"),
            ("ledger", "History"), ("segments", "Still segments"))
N_WORST = 15

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
dl.kv{display:grid;grid-template-columns:fit-content(17em) minmax(0,1fr);gap:2px 14px;margin:4px 0;font-size:.92em}
dl.kv dt{color:#555;overflow-wrap:anywhere}dl.kv dd{margin:0;overflow-wrap:anywhere}
dl.kv details ul{margin:2px 0;padding-left:1.4em}dl.kv summary{cursor:pointer}
.takeaway{font-size:1.08em;background:#fff6d9;border-left:5px solid #e0a800;padding:8px 12px;margin:8px 0}
.scroll{overflow-x:auto}
code{background:#f0f0f0;padding:0 3px;border-radius:3px}
"""


# --------------------------------------------------------------------------- helpers

def _e(value: Any) -> str:
    """HTML-escaped text of any value."""
    return html.escape(str(value), quote=True)


def _t(value: Any) -> str:
    """HTML-escaped prose, its `code` spans (the Markdown of the words that say them) as <code>."""
    return re.sub(r"`([^`\n]+)`", r"<code>\1</code>", _e(value))


def _proposal_gain(proposal: Mapping) -> str:
    """`proposal.gain_words` of a diagnosis's proposal as the ledger or --json keeps it; its
    gain alone where the figures it reads are not there (a record of an older posecorr)."""
    from .proposal import gain_words

    try:
        return gain_words(dict(proposal))
    except (KeyError, TypeError, ValueError):
        return f"the held-out whitened error falls by {_num(proposal.get('gain'), 100)} %"


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


def _img(fig: Any, alt: str, attributes: Mapping[str, str] | None = None) -> str:
    """A figure as an <img> with a PNG data URI (and any further `attributes`, e.g. data-*)."""
    data = base64.b64encode(figures.to_png(fig)).decode("ascii")
    extra = "".join(f' {k}="{_e(v)}"' for k, v in (attributes or {}).items())
    return f'<img alt="{_e(alt)}"{extra} src="data:image/png;base64,{data}">'


# --------------------------------------------------------------------------- sections

def _section(sid: str, title: str, body: str, note: str = "") -> str:
    note_html = f'<p class="note">{note}</p>' if note else ""
    return f'<section id="{sid}"><h2>{_e(title)}</h2>{note_html}{body}</section>'


def _summary_section(table: PoseTable, model_info: Mapping[str, Any] | None, title: str) -> str:
    extras = [c for c in ("id", "t", "session", "jitter_mm") if c in table.extras]
    items = [("data file", _t(table.path or "(in memory)")), ("poses", str(table.n)),
             ("kind", "full pose (position and orientation)" if table.has_orientation
              else "position only (rotation panels skipped)"),
             ("optional columns", _t(", ".join(extras) or "none"))]   # (label, HTML)
    if model_info:
        effects = ", ".join(effect_list(model_info.get("effects"))) or "none"
        items += [("model file", _t(model_info.get("file", "?"))),
                  ("corrector", _t(describe_corrector(dict(model_info)))),
                  ("effects in the model", _t(effects))]
        if model_info.get("posecorr_version") not in (None, ""):
            items.append(("posecorr version", _t(model_info["posecorr_version"])))
        items += _station_rows(model_info.get("station_pose"))
        if isinstance(model_info.get("fixed"), Mapping):
            items += _held_rows(model_info["fixed"])
        if isinstance(model_info.get("file_size"), int):
            items.append(("file size", f"{model_info['file_size']:,} bytes"))
        if isinstance(model_info.get("op_counts"), Mapping):
            ops = ", ".join(f"{k} {v}" for k, v in model_info["op_counts"].items())
            items.append(("operators", _t(ops)))
    else:
        items.append(("model", _t("(none given: 'after' is the corrected poses handed in)")))
    items.append(("generated", datetime.now(timezone.utc).isoformat(timespec="seconds")))
    body = '<dl class="kv">' + "".join(f"<dt>{_e(k)}</dt><dd>{v}</dd>" for k, v in items) + "</dl>"
    return _section("summary", "Summary", body)


def _station_rows(placed: Any) -> list[tuple[str, str]]:
    """The base station the model's effects bend about, where its fit was told
    (`--station-pose`, metadata `station_pose`): as stated, and where the fit placed it."""
    if not isinstance(placed, Mapping) or not isinstance(placed.get("stated"), str):
        return []
    where = placed.get("reference")
    at = (f"; placed at ({', '.join(f'{v:.3f}' for v in where[:3])}) m in the reference frame"
          if isinstance(where, list) and len(where) == 7 and all(isinstance(v, (int, float)) for v in where) else "")
    return [("base station", _t(f"--station-pose {placed['stated']}{at}"))]


def _held_rows(fixed: Mapping[str, Any]) -> list[tuple[str, str]]:
    """(label, HTML) rows of the parameters the fit held, one per parameter. A block of many
    dimensions is held along directions ("quadratic.q along [18 numbers]"): a 9-pose session
    held 11 of quadratic.q's, a row each made the summary a page tall. Several directions are
    one row, their reason's shared opening (the block's, `identify`) said once, the directions
    in a collapsed list."""
    groups: dict[str, list[tuple[str, str]]] = {}
    for key, reason in fixed.items():
        name, _, direction = str(key).partition(" along ")
        groups.setdefault(name, []).append((direction, str(reason)))
    rows = []
    for name, held in groups.items():
        label = f"held (not determined): {name}"
        if len(held) == 1:
            direction, reason = held[0]
            rows.append((label, _t(f"along {direction}: {reason}" if direction else reason)))
            continue
        openings = {reason.partition(": ")[0] for _, reason in held}
        shared = openings.pop() if len(openings) == 1 and all(": " in r for _, r in held) else ""
        lines = "".join(f"<li>{_t(f'along {d}: ' if d else '')}{_t(r.partition(': ')[2] if shared else r)}</li>"
                        for d, r in held)
        summary = f"{len(held)} directions held" + (f": {shared}" if shared else "")
        rows.append((label, f"<details><summary>{_t(summary)}</summary><ul>{lines}</ul></details>"))
    return rows


def _metrics_section(comparison: Comparison, pos: tuple[np.ndarray, np.ndarray],
                     rot: tuple[np.ndarray, np.ndarray] | None, model_info: Mapping[str, Any] | None) -> str:
    # Position-only data has no rotation columns at all (rather than columns of dashes).
    if rot is not None:
        header = ["", "scored on", "rmse_pos [mm]", "rmse_rot [mrad]", "rmse_total [mm + mrad]",
                  "median pos [mm]", "p95 pos [mm]", "max pos [mm]", "median rot [mrad]", "max rot [mrad]"]
    else:
        header = ["", "scored on", "rmse_pos [mm]", "rmse_total [mm]", "median pos [mm]", "p95 pos [mm]",
                  "max pos [mm]"]
    n = len(comparison.rows)
    before_name = (f"before: {comparison.baseline}" if comparison.unregistered else "raw (measured)")
    before_scored = (comparison.scored if comparison.unregistered else f"all {n} shown, no fit") \
        if comparison.held_out else ("in-sample" if comparison.unregistered else "no fit")
    rows = []
    for k, (name, scored, m) in enumerate(((before_name, before_scored, comparison.before_metrics),
                                           ("corrected (model)", comparison.scored, comparison.after_metrics))):
        p = pos[k] * 1e3
        row = [_e(name), _e(scored), _num(m["rmse_pos"], 1e3)]
        if rot is not None:
            row.append(_num(m["rmse_rot"], 1e3))
        row += [_num(m["rmse_total"], 1e3), _num(np.median(p)), _num(np.percentile(p, 95)), _num(p.max())]
        if rot is not None:
            row += [_num(np.median(rot[k]) * 1e3), _num(rot[k].max() * 1e3)]
        rows.append(row)
    block = comparison.block
    versus = comparison.baseline if comparison.unregistered else "raw"
    improvement = [_e(f"improvement ({versus} / corrected)"), ""] + [_num(block.get("improvement_pos")) + "×"]
    if rot is not None:
        improvement.append(_num(block.get("improvement_rot")) + "×")
    improvement.append(_num(block.get("improvement_total")) + "×")
    rows.append(improvement + [""] * (len(header) - len(improvement)))
    # "best" only for a strict improvement, one the figures shown tell: a model that changes
    # nothing (equal rows) is no better than before.
    totals = [comparison.before_metrics["rmse_total"], comparison.after_metrics["rmse_total"]]
    better = totals[1] < totals[0] and _num(totals[1], 1e3) != _num(totals[0], 1e3)
    body = _table(header, rows, left=2, row_classes=["", "best" if better else "", ""])
    note = (f"Over {n} poses of this file (paper eqs. 39-43, w_pos = {W_POS:g}/m, w_rot = {W_ROT:g}). "
            f"The before is the raw measurement unless the {RULE}; here raw rmse_pos is "
            f"{_num(comparison.raw['rmse_pos'], 1e3)} mm against {_num(comparison.rigid['rmse_pos'], 1e3)} mm for "
            f"the {rigid_label(comparison.rigid_name)}. Unregistered frames differ by an unknown rigid motion that raw "
            "measures, so there the before is the best rigid fit's residual. "
            + ("Held-out: every pose predicted by a fit that never saw it, as `posecorr fit` scored it."
               if comparison.held_out else f"{comparison.scored[0].upper()}{comparison.scored[1:]}: {comparison.reason}."))
    stated = stated_metrics(dict(model_info or {}))
    if stated is not None:
        kind, tm, _ = stated
        n_text = (", cross-validated" if kind == "cv" else
                  f" on {tm['n']} held-out poses" if isinstance(tm.get("n"), int) else " on its test split")
        rot_text = f", rmse_rot {_num(tm.get('rmse_rot'), 1e3)} mrad" if tm.get("rmse_rot") is not None else ""
        body += (f'<p class="note">From its metadata, the model\'s own held-out figures{_e(n_text)}: rmse_pos '
                 f"{_num(tm.get('rmse_pos'), 1e3)} mm{rot_text}, rmse_total {_num(tm.get('rmse_total'), 1e3)}"
                 f"{' mm + mrad' if rot_text else ' mm'}.</p>")
    return _section("metrics", "Metrics", body, _t(note))


def _pose_place(table: PoseTable) -> tuple[np.ndarray, str, str]:
    """How the page names a pose: (each pose's name, the column's header, its note). A table
    read from a file names it by the file's row, as every other message of posecorr does."""
    if table.rows is not None:
        name = f"row in {Path(table.path).name if table.path else 'the file'}"
        return table.rows, _e(name), f"{name}: the row of the file as an editor shows it (its line number)"
    return (np.arange(table.n), "index",
            "index: the pose's 0-based place in the table, which was made in memory, not read from a file")


def _worst_section(table: PoseTable, rows_shown: np.ndarray, feats: Mapping[str, np.ndarray],
                   pos: tuple[np.ndarray, np.ndarray], rot: tuple[np.ndarray, np.ndarray] | None,
                   before: str) -> str:
    total = worst_order(pos[1], None if rot is None else rot[1])[:N_WORST]
    ids = table.extras.get("id")
    shown = [f for f in ("range", "azimuth", "elevation", "incidence", "roll", "pitch", "yaw", "t") if f in feats]
    where, where_header, where_note = _pose_place(table)
    header = ["#", "id", where_header, "x [m]", "y [m]", "z [m]", "pos err [mm]"]
    if rot is not None:
        header.append("rot err [mrad]")
    header.append(f"{before} pos [mm]")
    if rot is not None:
        header.append(f"{before} rot [mrad]")
    header += [f"{f} [{figures.FEATURE_UNITS[f]}]" for f in shown]
    rows = []
    for rank, i in enumerate(total, start=1):
        r = int(rows_shown[i])
        row = [str(rank), _e(ids[r]) if ids is not None else "–", str(where[r]),
               *(f"{v:.3f}" for v in table.ref_p[r]), f"{pos[1][i] * 1e3:.3f}"]
        if rot is not None:
            row.append(f"{rot[1][i] * 1e3:.3f}")
        row.append(f"{pos[0][i] * 1e3:.3f}")
        if rot is not None:
            row.append(f"{rot[0][i] * 1e3:.3f}")
        for f in shown:
            v = figures.feature_display(f, np.asarray(feats[f][i:i + 1], float))[0]
            row.append(f"{round(v, 1) + 0.0:.1f}" if f != "range" else f"{v:.3f}")  # + 0.0: no "-0.0"
        rows.append(row)
    crit = "position error + rotation error (1 mm ≙ 1 mrad, paper eq. 43)" if rot is not None else "position error"
    note = (f"The {len(total)} poses with the largest corrected error, ranked by {crit}. "
            f"{where_note}; x, y, z: reference position"
            + ("." if rot is not None else "; the angles are of the measured orientation, in the tracker's frame "
               "(the table has no reference orientation)."))
    return _section("worst", "Worst poses after correction", _table(header, rows, left=2, compact=True), _t(note))


def _core_note(model_info: Mapping[str, Any] | None, effects: Sequence[str]) -> str:
    """Where the model has a data-driven core: the diagnosis's base is its physical effects
    alone, so its "cv RMSE before" is not the model's held-out figure."""
    from posecorr.train.methods import METHODS

    method = (model_info or {}).get("method")
    if not isinstance(method, str) or method not in METHODS or not METHODS[method].has_core:
        return ""
    core = f"{method}-{(model_info or {}).get('representation')}"
    return (f" The diagnosis refits the model's physical effects ({', '.join(effects) or 'none'}) in each fold; "
            f"its data-driven core ({core}) is not part of that base, so cv RMSE before is the effects' alone, "
            "not the model's.")


def _candidates_html(diagnosis: Mapping[str, Any], core_note: str) -> str:
    """The diagnosis's ranked candidates as a table, with its note."""
    candidates = ranked_candidates(diagnosis)
    if not candidates:
        return ""
    header = ["rank", "candidate", "kind", "present", "score", "p-value", "cv RMSE before", "cv RMSE after", "gain"]
    rows, classes = [], []
    for c in candidates:
        gain = cv_gain(c)
        rows.append([_e(c.get("rank", "")), _e(c.get("effect", "?")), _e(c.get("kind", "effect")),
                     "yes" if c.get("present") else "no",
                     _num(c.get("score")), _e(p_value_text(c.get("p_value"))),
                     _num(c.get("cv_rmse_before"), 1e3), _num(c.get("cv_rmse_after"), 1e3),
                     f"{gain:.2f}×" if gain is not None else "–"])
        classes.append("present" if c.get("present") else "")
    body = ("<h3>Candidate effects and forms the model lacks</h3>"
            + _table(header, rows, left=4, row_classes=classes))
    folds = diagnosis.get("folds")
    body += ('<p class="note">Highlighted: present (the test says adding the effect helps). '
             f"cv RMSE: held-out rmse_total over the diagnosis's {_e(folds) + ' ' if folds else ''}folds "
             "(not the fit's own held-out figure in the metrics, whose folds may differ), shown ×1000 (mm, "
             "or mm + mrad for full poses).")
    if diagnosis.get("test"):
        body += " Test: " + _t(diagnosis["test"]) + "."
    body += _t(core_note) + "</p>"
    return body


def _diagnosis_section(diagnosis: Mapping[str, Any] | None, effects: Sequence[str], why_none: str | None = None,
                       core_note: str = "") -> str:
    line = takeaway(diagnosis, effects, why_none)
    body = f'<p class="takeaway" id="takeaway">{_t(line)}</p>'
    if not diagnosis:
        return _section("diagnosis", "Diagnosis", body)
    body += _candidates_html(diagnosis, core_note)
    body += _proposal_html(diagnosis)
    notes = [note for note in diagnosis.get("notes") or [] if isinstance(note, str)]
    if notes:   # what the selection decided beyond the table (a form that gave way, a pair it cannot tell apart)
        body += "<h3>Notes</h3><ul>" + "".join(f"<li>{_t(note)}</li>" for note in notes) + "</ul>"
    aliases = [a for a in diagnosis.get("aliases") or [] if isinstance(a, Mapping) and a.get("effects")]
    if aliases:
        body += ("<h3>Aliases</h3><p>Effects that move these poses alike (fitting one absorbs that part of "
                 "the other):</p><ul>" + "".join(f"<li>{_e(alias_text(a))}</li>" for a in aliases) + "</ul>")
    undetermined = [u for u in diagnosis.get("undetermined") or [] if isinstance(u, Mapping)]
    for title, group in (("already in the model", [u for u in undetermined if u.get("in_model")]),
                         ("this data cannot determine them", [u for u in undetermined if not u.get("in_model")])):
        if group:
            body += (f"<h3>Not ranked: {title}</h3><ul>"
                     + "".join(f"<li><b>{_e(u.get('effect', '?'))}</b> {_e(not_ranked_why(u))}: "
                               f"{_t(u.get('reason', ''))}</li>" for u in group) + "</ul>")
    feats, others = split_features(diagnosis.get("features") or [])
    if feats:
        body += "<h3>Residual structure by feature</h3>"
        rows = [[_e(f.get("feature", "?")), f"{f['r2']:.3f}", _e(f.get("error", ""))] for f in feats]
        classes = ["present" if is_structure(f.get("r2")) else "" for f in feats]
        body += ('<div style="display:flex;gap:24px;align-items:flex-start;flex-wrap:wrap"><div>'
                 + _table(["feature", "cv R²", "of the error in"], rows, row_classes=classes) + "</div><div>"
                 + _img(figures.r2_figure(feats), "cross-validated R² of the residual per feature") + "</div></div>")
        body += ('<p class="note">The cross-validated R² of a smooth fit of the residual along each feature; '
                 f"highlighted (R² ≥ {STRUCTURE_R2:g}): structure that the model misses along that feature."
                 + (f" R² 0 along {_e(', '.join(others))}." if others else "") + "</p>")
    elif others:
        body += ("<h3>Residual structure by feature</h3><p>None: a smooth fit along a feature explains none of "
                 f"the held-out residual (cross-validated R² 0 along {_e(', '.join(others))}).</p>")
    known = {"candidates", "features", "aliases", "model_effects", "test", "undetermined", "proposal", "no_proposal",
             "absorbed", "absent"}
    other = {k: v for k, v in diagnosis.items() if k not in known and isinstance(v, (str, int, float))}
    if other:
        body += '<dl class="kv">' + "".join(f"<dt>{_e(k)}</dt><dd>{_t(v)}</dd>" for k, v in other.items()) + "</dl>"
    return _section("diagnosis", "Diagnosis", body)


def _proposal_html(diagnosis: Mapping[str, Any]) -> str:
    """The diagnosis's proposal (a generic form that explains what the catalogue does not), or
    why there is none, the catalogue effects that take part of a proposed form's gain, and
    those that lower the error and still fail the test."""
    proposal = diagnosis.get("proposal")
    if isinstance(proposal, Mapping):
        html = (f"<h3>Proposal</h3><p><b>{_e(', '.join(proposal.get('forms') or []))}</b> "
                f"({_e(proposal.get('parameters', '?'))} parameters): {_t(_proposal_gain(proposal))}.")
        causes = proposal.get("causes") or {}
        html += "".join(f" Causes of the {_e(form)} shape: {_t(text)}." for form, text in causes.items())
        if proposal.get("file"):
            html += f" Written to <code>{_e(proposal['file'])}</code>."
        html += "</p>"
    elif diagnosis.get("no_proposal"):
        html = f"<h3>Proposal</h3><p>None: {_t(diagnosis['no_proposal'])}.</p>"
    else:
        return ""
    absorbed = [a for a in diagnosis.get("absorbed") or [] if isinstance(a, Mapping)]
    if absorbed:
        html += "<ul>" + "".join(f"<li><b>{_e(a.get('effect', '?'))}</b> takes {_num(a.get('share'), 100)} % of "
                                 f"{_e(a.get('form', '?'))}'s gain alone, but {_t(a.get('why', ''))}</li>"
                                 for a in absorbed) + "</ul>"
    absent = [a for a in diagnosis.get("absent") or [] if isinstance(a, Mapping)]
    if absent:
        html += "<ul>" + "".join(f"<li><b>{_e(a.get('effect', '?'))}</b> lowers the held-out whitened error by "
                                 f"{_num(a.get('score'), 100)} % and is not present: {_t(a.get('why', ''))}</li>"
                                 for a in absent) + "</ul>"
    return html


def _segments_section(segments: Mapping[str, Any]) -> str:
    """Where the robot stood still in the recording the table came from (`posecorr ingest`):
    every segment found, the rejected ones with their reason, and the clock offset."""
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
    return _section("segments", "Still segments", f"<p>{_t(head)}</p>" + table)


def _core_representation(entry: Mapping[str, Any]) -> str:
    """A ledger line's representation where its method has a data-driven core (a physics or
    rigid model's is internal), else "–"."""
    from posecorr.train.methods import METHODS

    method = METHODS.get(str(entry.get("method")))
    return str(entry.get("representation") or "–") if method is not None and method.has_core else "–"


def _ledger_section(ledger: Sequence[Mapping[str, Any]]) -> str:
    if not ledger:
        return _section("ledger", "Ledger", "<p>No models fitted on this data yet (the ledger is empty).</p>")
    header = ["#", "time", "model", "effects", "method", "representation", "held-out",
              "rmse_pos [mm]", "rmse_rot [mrad]", "rmse_total [mm + mrad]",
              "best rigid fit, same poses: rmse_pos [mm]", "gain over the rigid fit (total)"]
    rows = []
    totals = []
    for k, entry in enumerate(ledger, start=1):
        block = held_out(entry)[1]
        totals.append(block.get("rmse_total") if isinstance(block.get("rmse_total"), (int, float)) else math.inf)
        gain = _gain(entry.get("baseline"), block)
        when = str(entry.get("time", "")).replace("T", " ").removesuffix("+00:00")
        model = str(entry.get("model", ""))
        rows.append([str(k), _e(when), f'<span title="{_e(model)}">{_e(Path(model).name if model else "")}</span>',
                     _e(", ".join(effect_list(entry.get("effects"))) or "none"), _e(entry.get("method", ""))
                     + _asked_words(entry.get("asked")),
                     _e(_core_representation(entry)), _e(plan_name(entry) or "–"),
                     _num(block.get("rmse_pos"), 1e3), _num(block.get("rmse_rot"), 1e3),
                     _num(block.get("rmse_total"), 1e3), _rigid_cell(entry.get("baseline")),
                     (_num(gain) + "×") if gain is not None else "–"])
    best = int(np.argmin(totals)) if any(math.isfinite(t) for t in totals) else -1
    classes = ["best" if k == best else "" for k in range(len(rows))]
    body = _table(header, rows, left=7, row_classes=classes, compact=True)
    fig = figures.ledger_figure(ledger)
    if fig is not None:
        body += _img(fig, "held-out rmse_pos of each fit in the ledger, with the rigid fit")
    note = ("The loop's history: every model fitted on this data (the ledger beside it), oldest first; "
            "highlighted: the lowest held-out rmse_total. The plot: each fit's held-out rmse_pos against the "
            "best rigid fit on the same poses (dashed).")
    return _section("ledger", "History: models fitted on this data", body, _t(note))


def _asked_words(asked: Any) -> str:
    """' (asked: pmc-zhou, 333 mm + mrad held-out rmse_total; worse than the rigid fit)' of a ledger line
    whose fit fell back to the rigid fit, the figure in mm + mrad, the reason where it was not
    the score (`asked["why"]`); '' otherwise."""
    if not isinstance(asked, Mapping) or not isinstance(asked.get("rmse_total"), (int, float)):
        return ""
    return _e(f" (asked: {asked.get('name', '?')}, {_num(asked['rmse_total'], 1e3)} mm + mrad {asked.get('on', 'held-out')}"
              f" rmse_total; {asked.get('why', 'worse than the rigid fit')})")


def _gain(baseline: Any, block: Mapping[str, Any]) -> float | None:
    """The rigid fit's held-out rmse_total over the model's, None where either is missing."""
    rigid = baseline.get("rmse_total") if isinstance(baseline, Mapping) else None
    model = block.get("rmse_total")
    if isinstance(rigid, (int, float)) and isinstance(model, (int, float)) and model > 0:
        return float(rigid) / float(model)
    return None


def _rigid_cell(baseline: Any) -> str:
    """The ledger line's best rigid fit: 'rmse_pos (variant)', '–' for a line without it."""
    if not isinstance(baseline, Mapping) or baseline.get("rmse_pos") is None:
        return "–"
    return f"{_num(baseline.get('rmse_pos'), 1e3)} ({_e((block_name(baseline) or '').removeprefix('rigid-'))})"


def _workspace_section(comparison: Comparison, before: str, after: str) -> str:
    """The residual arrows, before above after, and what their magnifications are."""
    ref_p = comparison.reference[:, :3]
    errors = (comparison.before[:, :3] - ref_p, comparison.after[:, :3] - ref_p)
    keys, typical = figures.arrow_keys_mm(*errors), figures.arrow_typical_mm(*errors)
    fig = figures.workspace_figure(ref_p, *errors, f"before: {before}", "after: " + after.removeprefix("corrected, "))
    if typical[0] == typical[1]:
        scale = "Both rows have one magnification and one colour scale."
    else:
        scale = (f"The rows do not share a magnification: at one, one row's arrows would be too small to see, so "
                 f"the after row is {figures.magnification_words(typical[0] / typical[1], 'before')} (compare the "
                 f"keys: {keys[0]:g} mm above, {keys[1]:g} mm below), and each row has its own colour scale.")
    note = (f"Arrow = {before} (top) or {comparison.scored} correction (bottom) minus reference position, drawn at "
            "the reference position, in three projections; colour = 3D error magnitude. Arrows are magnified; the "
            f"red key in each panel gives the scale. {scale}")
    return _section("workspace", "Residual arrows over the workspace",
                    _img(fig, "position error vectors in x-y, x-z, y-z, before and after",
                         {"data-before-key-mm": f"{keys[0]:g}", "data-after-key-mm": f"{keys[1]:g}"}), _t(note))


def _figure_sections(comparison: Comparison, feats: Mapping[str, np.ndarray], pos: tuple[np.ndarray, np.ndarray],
                     rot: tuple[np.ndarray, np.ndarray] | None) -> list[str]:
    """Workspace arrows, error against features, by orientation, histograms: before against after."""
    before = comparison.baseline if comparison.unregistered else "raw"
    after = "corrected, " + ("held-out" if comparison.held_out else comparison.scored)
    sections = [_workspace_section(comparison, before, after)]
    body = _img(figures.features_figure(feats, pos[0] * 1e3, pos[1] * 1e3, "position error", "mm", before, after),
                "position error against features")
    if rot is not None:
        body += _img(figures.features_figure(feats, rot[0] * 1e3, rot[1] * 1e3, "rotation error", "mrad",
                                             before, after), "rotation error against features")
    # A position-only table's poses take the measured orientation, in the tracker's own frame.
    whose = ("the reference pose" if rot is not None else
             "the reference position and the measured orientation (the table has no reference orientation; the "
             "measured one is in the tracker's frame)")
    station = (UNPLACED_STATION if "range" not in feats else
               "azimuth/elevation as seen from the station, incidence: tracker z axis vs line of sight")
    note = (f"Features of {whose} (angles in degrees; {station}). A trend in the solid blue median line (after) is structure "
            f"the model misses; each of its points is the median of {figures.MIN_PER_GROUP} poses or more, "
            "so a session of fewer than twice that has none." + ("" if "t" in feats else " No time column: t is not shown."))
    sections.append(_section("features", "Error against features", body, _t(note)))
    fig = figures.orientation_figure(feats, pos[1] * 1e3, None if rot is None else rot[1] * 1e3,
                                     pos[0] * 1e3, None if rot is None else rot[0] * 1e3)
    sections.append(_section("orientation", "Error by orientation",
                             _img(fig, "corrected error grouped by roll, pitch, yaw"),
                             _t(f"Roll, pitch, yaw of the {'reference' if rot is not None else 'measured'} "
                                f"orientation {'as the table gives it' if comparison.unregistered else 'relative to upright'} "
                                "(Z-Y-X); "
                                "distinct values when there are few, else equal-width bins, or bins of equal "
                                f"counts where those would hold fewer than {figures.MIN_PER_GROUP} poses; "
                                "a bin is labelled ≈ its median angle.")))
    fig = figures.histogram_figure((pos[0] * 1e3, pos[1] * 1e3), None if rot is None else (rot[0] * 1e3, rot[1] * 1e3),
                                   before, after)
    sections.append(_section("histograms", "Error histograms", _img(fig, "error histograms before and after"),
                             _t(f"Log-spaced bins so both the {before} and the corrected errors are readable.")))
    return sections


def write_report(output_path: str | Path, table: PoseTable, corrected: np.ndarray,
                 model_info: Mapping[str, Any] | None = None, diagnosis: Mapping[str, Any] | None = None,
                 ledger: Sequence[Mapping[str, Any]] = (), title: str | None = None,
                 segments: Mapping[str, Any] | None = None, comparison: Comparison | None = None,
                 no_diagnosis: str | None = None) -> Path:
    """Write the self-contained HTML report of `table` against its (N, 7) `corrected` poses.

    model_info: `onnx_meta.read_info` of the model (optional); diagnosis: the `diagnose --json`
    dict (optional, unknown keys are shown or ignored); ledger: `ledger.read_ledger` records;
    segments: the sidecar `posecorr ingest` writes beside the table (TABLE.csv.segments.json);
    comparison: the before and after the page shows (`comparison.compare`; by default of
    `corrected` on every pose, in-sample); no_diagnosis: why there is no diagnosis, where the
    data cannot have one.
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
    if comparison is None:
        comparison = compare(table, corrected, model_info=model_info)
    with_rot = table.has_orientation
    pos_b, rot_b = pose_errors(comparison.reference, comparison.before, with_rot)
    pos_a, rot_a = pose_errors(comparison.reference, comparison.after, with_rot)
    pos = (pos_b, pos_a)
    rot = (rot_b, rot_a) if with_rot and rot_b is not None and rot_a is not None else None
    feats = {k: np.asarray(v)[comparison.rows]
             for k, v in table_features(table, registered=not comparison.unregistered).items()}
    name = title or f"posecorr report: {Path(table.path).name if table.path else 'table'}"
    if model_info and model_info.get("file"):
        name = title or f"{name} vs {Path(str(model_info['file'])).name}"

    parts = [_summary_section(table, model_info, name), _metrics_section(comparison, pos, rot, model_info),
             *_figure_sections(comparison, feats, pos, rot)]
    short = "rigid" if comparison.unregistered else "raw"
    parts.append(_worst_section(table, comparison.rows, feats, pos, rot, short))
    effects = model_effects(model_info, diagnosis)
    parts.append(_diagnosis_section(diagnosis, effects, no_diagnosis, _core_note(model_info, effects)))
    parts.append(_ledger_section(list(ledger)))
    # A table not from `posecorr ingest` has no segments: no section, and no menu entry to nothing.
    if segments:
        parts.append(_segments_section(segments))
    shown = [(sid, label) for sid, label in SECTIONS if segments or sid != "segments"]

    nav = "".join(f'<a href="#{sid}">{_e(label)}</a>' for sid, label in shown)
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><title>{_e(name)}</title>"
            f"<style>{_CSS}</style></head><body><header><h1>{_e(name)}</h1></header><nav>{nav}</nav><main>"
            + "".join(parts) + "</main></body></html>\n")
    out = Path(output_path)
    write_text(out, page)  # atomic: an interrupted report leaves the previous page
    return out

