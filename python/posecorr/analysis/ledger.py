"""The ledger: every model fitted on a data set, kept next to the data (DATA.csv.ledger.jsonl).

One JSON object per line, appended by `posecorr fit`, read by `posecorr report`, so a user
sees the error fall step by step as effects are added. Keys: time (UTC ISO 8601), model,
effects (list), method, representation, raw, the held-out block ("cv" or "test") with
rmse_pos, rmse_rot, rmse_total and improvements, and `baseline`: the best rigid fit on the
same poses ({"name": its candidate name, the same figures}; "model" in ledgers written
before). What lets a report rebuild the held-out predictions (`fitting.ledger_fit_entry`):
model_sha256 (the model file's), n (the table's poses), table_digest (`ledger_table_digest`:
the report's history keeps the lines of the table it reads), table_set_digest (the same in any
order of its rows, `ledger_set_digest`), row_ranks (`row_ranks`: the table sorted or reversed
since is put back in the fit's order, whose folds are by row: `fit_order`), plan ("none",
"loo" or a number of folds), seed, station_pose (where `--station-pose` stated one), spec (the
requested `ModelSpec`'s fields), chosen (the
candidate returned), fell_back, rigid (its variant, or null), and where it fell back `asked`:
the model asked for, scored ({"name", "rmse_total", "on": "held-out", "validation" or
"test"}, and "why" where it was not the score that sent it back: its file failed the
export's parity check).

Appends are whole lines (`safeio.append_line`): a line torn by an interrupted append is
moved to DATA.csv.ledger.jsonl.corrupt at the next append; reading skips (and names) any
line that is not a record, so one torn write never blocks `report`. The ledger is read and
appended only as a regular file (`safeio.open_sidecar`): a link or a FIFO in its place is
refused, naming it.
"""
from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np


def ledger_path(data_path: str | Path) -> Path:
    data_path = Path(data_path)
    return data_path.with_name(data_path.name + ".ledger.jsonl")


def append_entry(data_path: str | Path, entry: dict[str, Any]) -> dict[str, Any]:
    """Append one fitted model's record (a time stamp is added) and return it."""
    from ..safeio import append_line

    record = {"time": datetime.now(timezone.utc).isoformat(timespec="seconds"), **entry}
    append_line(ledger_path(data_path), json.dumps(record, default=float))
    return record


def read_ledger(data_path: str | Path) -> list[dict[str, Any]]:
    """All records, oldest first; a missing ledger is empty. A line that is not a record
    (torn by an interrupted write, edited by hand) is skipped with a warning naming it."""
    from ..safeio import open_sidecar, warn

    path = ledger_path(data_path)
    handle = open_sidecar(path)
    if handle is None:
        return []
    with handle:
        text = handle.read().decode("utf-8", errors="replace")
    records = []
    for number, line in enumerate(text.splitlines(), start=1):
        if line.strip():
            try:
                record = json.loads(line)
            except json.JSONDecodeError as exc:
                warn(f"{path}, line {number}: not a ledger record ({exc.msg}); skipped")
                continue
            if isinstance(record, dict):
                records.append(record)
            else:
                warn(f"{path}, line {number}: not a ledger record (not an object); skipped")
    return records


def held_out(record: Mapping[str, Any]) -> tuple[str, Mapping[str, Any]]:
    """("cv" | "test" | "", block) of a record: the held-out figures its model was scored on."""
    for key in ("cv", "test"):
        block = record.get(key)
        if isinstance(block, Mapping):
            return key, block
    return "", {}


def plan_name(record: Mapping[str, Any]) -> str:
    """The held-out plan of a record in the words the report's metrics table says it ("leave one
    out", "5 folds", "test split": `splits`' description), not the key of its block ("cv"); a
    line without a plan (older posecorr) by its block: "cross-validated" or "test split"; "" for
    a line without held-out figures."""
    from ..train.splits import parse_plan

    kind, _ = held_out(record)
    if kind and "plan" in record:
        try:
            return parse_plan(record["plan"]).description
        except (ValueError, TypeError):
            pass  # a plan no posecorr writes: named by its block, as an older line
    return {"cv": "cross-validated", "test": "test split"}.get(kind, "")


def entry_for_model(ledger: Sequence[Mapping[str, Any]], model_path: str | Path) -> Mapping[str, Any] | None:
    """The newest record whose model_sha256 is that of the file at `model_path` (the same
    bytes, wherever the file was moved since), or None."""
    import hashlib

    digest = hashlib.sha256(Path(model_path).read_bytes()).hexdigest()
    return next((r for r in reversed(ledger) if r.get("model_sha256") == digest), None)


def _table_arrays(table: Any) -> tuple[Any, Any, Any]:
    """What the ledger's digests read of a table: its poses and times."""
    return table.measured, table.reference, table.time()


def ledger_table_digest(table: Any) -> str:
    """The digest a ledger line keeps of the table its fit read (`digest.data_digest` of its
    poses and times): a file replaced under the same name has another."""
    from ..controller.digest import data_digest

    return data_digest(*_table_arrays(table))


def ledger_set_digest(table: Any) -> str:
    """`table_set_digest`: the same poses and times in any order (`digest.set_digest`): the
    fit's table sorted or reversed in place is still its table."""
    from ..controller.digest import set_digest

    return set_digest(*_table_arrays(table))


def row_ranks(table: Any) -> str:
    """`row_ranks`: each row's place in `digest.row_order`, as base64 of little-endian unsigned
    integers (2 bytes each, 4 from 65,537 rows): 8 characters for every 3 rows (4,336 for
    1,626), half what the numbers take as a JSON list."""
    import base64

    from ..controller.digest import row_order

    ranks = np.empty(table.n, dtype="<u2" if table.n <= 1 << 16 else "<u4")
    ranks[row_order(*_table_arrays(table))] = np.arange(table.n)
    return base64.b64encode(ranks.tobytes()).decode("ascii")


def _decoded_ranks(text: Any, n: int) -> np.ndarray | None:
    """The ranks `row_ranks` wrote for a table of n rows, or None where `text` is not them."""
    import base64
    import binascii

    try:
        raw = base64.b64decode(text, validate=True)
    except (binascii.Error, TypeError, ValueError):
        return None
    width = len(raw) // n if n else 0
    if width not in (2, 4) or len(raw) != width * n:
        return None
    ranks = np.frombuffer(raw, dtype=f"<u{width}").astype(np.intp)
    return ranks if np.array_equal(np.sort(ranks), np.arange(n)) else None


def fit_order(record: Mapping[str, Any], table: Any) -> np.ndarray | None:
    """`table`'s rows in the order of the fit whose ledger line is `record`, where `table` holds
    that fit's poses in another order: `table.subset(order)` is the table the fit read
    (checked against the line's `table_digest`). None where the line has no `row_ranks` (an
    older posecorr) or they do not give that table. Identical rows are interchangeable: either
    will do."""
    from ..controller.digest import row_order

    ranks = _decoded_ranks(record.get("row_ranks"), table.n)
    if ranks is None:
        return None
    order = np.asarray(row_order(*_table_arrays(table)), dtype=np.intp)[ranks]
    return order if ledger_table_digest(table.subset(order)) == record.get("table_digest") else None


def of_table(ledger: Sequence[Mapping[str, Any]], table: Any) -> tuple[list[Mapping[str, Any]], int]:
    """The records of fits on `table`, in any order of its rows (by `table_digest` or
    `table_set_digest`; a record older than the digest, by its number of poses), and how many
    are of another table under the same name: a session simulated over another, a ledger
    copied beside another table."""
    ordered, unordered = ledger_table_digest(table), ledger_set_digest(table)

    def mine(record: Mapping[str, Any]) -> bool:
        if "table_digest" not in record:
            return record.get("n") == table.n
        return record["table_digest"] == ordered or record.get("table_set_digest") == unordered

    kept = [r for r in ledger if mine(r)]
    return kept, len(ledger) - len(kept)
