"""Plain-text tables and number formatting for the CLI (no dependency beyond the stdlib)."""
from __future__ import annotations

import math
from typing import Any, Sequence


def fmt(value: Any, digits: int = 4) -> str:
    """A metric for a table cell: None as '-', floats with `digits` significant digits."""
    if value is None:
        return "-"
    if isinstance(value, float):
        if math.isinf(value) or math.isnan(value):
            return str(value)
        if value != 0 and (abs(value) < 1e-3 or abs(value) >= 1e5):
            return f"{value:.{digits - 1}e}"
        return f"{value:.{digits}g}" if abs(value) >= 1 else f"{value:.{digits}f}"
    return str(value)


def percent(value: float) -> str:
    """A percentage in plain digits, two significant ones: '6.8', '320', '10,000' (a note's
    '3.2e+02 % worse' reads as a formula, not a number)."""
    if value == 0 or not math.isfinite(value):
        return f"{value:g}"
    rounded = float(f"{value:.2g}")
    decimals = max(0, 1 - math.floor(math.log10(abs(rounded))))
    return f"{rounded:,.{decimals}f}"


def closest(name: str, known: Sequence[str], cutoff: float = 0.6) -> str | None:
    """The known name closest to a mistyped one (difflib's ratio at least `cutoff`), or None."""
    import difflib

    close = difflib.get_close_matches(name, list(known), n=1, cutoff=cutoff)
    return close[0] if close else None


def did_you_mean(name: str, known: Sequence[str]) -> str:
    """' (did you mean mount?)', or '' when no known name is close: what a refused name adds."""
    close = closest(name, known)
    return f" (did you mean {close}?)" if close else ""


def first_few(items: Sequence[Any], shown: int, total: int | None = None) -> str:
    """'7, 9, 12 and 3 more': the first `shown` of `items`, and how many of `total` (default:
    all of them) are left unnamed, as a line naming many rows says them."""
    total = len(items) if total is None else total
    head = ", ".join(map(str, list(items)[:shown]))
    return head + (f" and {total - shown} more" if total > shown else "")


def counted(n: int, noun: str) -> str:
    """'1 row', '2 rows': a count with its noun in the number it takes."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]], title: str | None = None) -> str:
    """A left-aligned first column, right-aligned others, a rule under the header."""
    cells = [[fmt(c) for c in row] for row in rows]
    widths = [max(len(str(h)), *(len(r[i]) for r in cells)) if cells else len(str(h))
              for i, h in enumerate(headers)]

    def line(values: Sequence[str]) -> str:
        return "  ".join(v.ljust(w) if i == 0 else v.rjust(w) for i, (v, w) in enumerate(zip(values, widths)))

    out = [title] if title else []
    out += [line([str(h) for h in headers]), "  ".join("-" * w for w in widths)]
    out += [line(r) for r in cells]
    return "\n".join(out)


def metrics_rows(blocks: dict[str, dict[str, Any]]) -> list[list[Any]]:
    """Rows `name, rmse_pos [mm], rmse_rot [mrad], rmse_total` for named metric blocks."""
    rows = []
    for name, m in blocks.items():
        pos, rot = m.get("rmse_pos"), m.get("rmse_rot")
        rows.append([name, None if pos is None else pos * 1e3, None if rot is None else rot * 1e3,
                     m.get("rmse_total")])
    return rows


# rmse_total keeps the metrics' own units (w_pos = 1/m, w_rot = 1): its unit said beside it
METRIC_HEADERS = ["", "rmse_pos [mm]", "rmse_rot [mrad]", "rmse_total [m + rad]"]
