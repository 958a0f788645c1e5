"""Text tables in the layout of the paper's tables 2-4, table 5 (tiers) and table A1.

Columns: Method | Position RMSE [m] min avg max imp | Rotation RMSE [rad] min avg max imp |
Total RMSE min avg max imp, a "raw data" row first, then one section per representation
("EAA representation", ...). imp = raw RMSE / min RMSE (the paper's improvement ratio).
Method labels: "PMC" or "<activation> <architecture no.>/<algorithm no.>" with table 1's
numbering (e.g. "tansig 16/2" = 20-20-20-20, Bayesian regularisation); an architecture
outside table 1 is spelled out in parentheses and a trainer outside it by name
("tansig (8-8)/adam"), so a bare number is always table 1's (``spec.network_label``).
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

SECTION_TITLES = {"pos": "Position only", "eaa": "EAA representation", "quat": "Quaternion representation",
                  "R": "R representation", "zhou": "Zhou representation"}
SHORT_REP = {"pos": "pos", "eaa": "EAA", "quat": "Quaternion", "R": "R", "zhou": "Zhou"}
BLOCKS = (("pos", "Position RMSE [m]"), ("rot", "Rotation RMSE [rad]"), ("total", "Total RMSE"))


def _num(v: Any, digits: int = 4) -> str:
    if v is None:
        return "—"
    return f"{v:.{digits}f}"


def format_results(raw: Mapping[str, Any], summaries: Sequence[Mapping[str, Any]], title: str = "") -> str:
    """Rows of ``SweepResult.summary()``: {"representation", "label", "rmse_pos": {min, avg, max},
    ..., "improvement_pos": float, ...}; ``raw`` the test-set raw metrics."""
    width = 22
    head1 = f"{'Method':<{width}}" + "".join(f"{name:^36}" for _, name in BLOCKS)
    head2 = f"{'':<{width}}" + "".join(f"{'min':>9}{'avg':>9}{'max':>9}{'imp':>9}" for _ in BLOCKS)
    lines = [title] if title else []
    lines += [head1, head2, "-" * len(head2)]
    raw_cells = "".join(f"{_num(raw.get('rmse_' + key)):>9}{'—':>9}{'—':>9}{'—':>9}" for key, _ in BLOCKS)
    lines.append(f"{'raw data':<{width}}" + raw_cells)
    section = None
    for row in summaries:
        rep = row["representation"]
        if rep != section:
            section = rep
            lines.append(SECTION_TITLES.get(rep, rep))
        cells = ""
        for key, _ in BLOCKS:
            s = row.get("rmse_" + key)
            if s is None:
                cells += f"{'—':>9}" * 4
            else:
                cells += f"{_num(s['min']):>9}{_num(s['avg']):>9}{_num(s['max']):>9}"
                cells += f"{_num(row.get('improvement_' + key), 2):>9}"
        lines.append(f"{row['label']:<{width}}" + cells)
    return "\n".join(lines)


def format_tiers(tiers: Sequence[Sequence[str]], overlaps: Sequence[tuple[str, str]] = ()) -> str:
    """Table 5: one line per tier."""
    lines = ["Tier  Methods"]
    for i, names in enumerate(tiers, 1):
        lines.append(f"{i:<5} " + "  ".join(names))
    if overlaps:
        lines.append("not separated across adjacent tiers: " + ", ".join(f"{a} ~ {b}" for a, b in overlaps))
    return "\n".join(lines)


def format_comparisons(names: Sequence[str], comparisons: Sequence[Any]) -> str:
    """Table A1: Method 1, Method 2, CI lower, mean rank difference, CI upper, p-value."""
    lines = [f"{'Method 1':<28}{'Method 2':<28}{'CI lower':>10}{'diff':>10}{'CI upper':>10}{'p-value':>10}"]
    for c in comparisons:
        p = "<0.001" if c.p_value < 0.001 else f"{c.p_value:.3f}"
        lines.append(f"{names[c.i]:<28}{names[c.j]:<28}{c.lower:>10.3f}{c.diff:>10.3f}{c.upper:>10.3f}{p:>10}")
    return "\n".join(lines)
