"""The ledger: every model fitted on a data set, kept next to the data (DATA.csv.ledger.jsonl).

One JSON object per line, appended by `posecorr fit`, read by `posecorr report`, so a user
sees the error fall step by step as effects are added. Keys: time (UTC ISO 8601), model,
effects (list), method, representation, raw, and the held-out block ("cv" or "test") with
rmse_pos, rmse_rot, rmse_total and improvements.
"""
from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Any


def ledger_path(data_path: str | Path) -> Path:
    data_path = Path(data_path)
    return data_path.with_name(data_path.name + ".ledger.jsonl")


def append_entry(data_path: str | Path, entry: dict[str, Any]) -> dict[str, Any]:
    """Append one fitted model's record (a time stamp is added) and return it."""
    record = {"time": datetime.now(timezone.utc).isoformat(timespec="seconds"), **entry}
    with open(ledger_path(data_path), "a", encoding="utf-8") as handle:
        handle.write(json.dumps(record, default=float) + "\n")
    return record


def read_ledger(data_path: str | Path) -> list[dict[str, Any]]:
    """All records, oldest first; a missing ledger is empty. A corrupt line raises ValueError naming it."""
    path = ledger_path(data_path)
    if not path.exists():
        return []
    records = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if line.strip():
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError as exc:
                raise ValueError(f"{path}, line {number}: not a ledger record ({exc.msg})") from None
    return records
