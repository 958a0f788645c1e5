"""Plain CSV logs: a time column, joint-angle columns and tracker-pose columns.

Layout (docs/guides/ingest.md): a header row, then one row per sample of either stream.
`t` is seconds (any origin; the two streams' clocks may differ by an offset, which ingest
estimates), `q1..q6` are joint angles in rad, `x, y, z` the tracker position in metres and
`qw, qx, qy, qz` its unit quaternion. A row carries a joint sample, a tracker sample or both;
the cells of the stream it does not carry are empty. The streams may also come in two files
(one with `t` and the joint columns, one with `t` and the pose columns). Column names are
options (`--time-col`, `--joint-cols`, `--pose-cols`).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data import TableError, csv_records, header_record, quaternion_faults, warn_comments
from .streams import IngestError, JointStream, PoseStream


@dataclass(frozen=True)
class CsvColumns:
    time: str = "t"
    joints: tuple[str, ...] = ("q1", "q2", "q3", "q4", "q5", "q6")
    pose: tuple[str, ...] = ("x", "y", "z", "qw", "qx", "qy", "qz")


def _records(path: Path) -> tuple[int, list[str], list[tuple[int, list[str]]]]:
    """(the header's row, its cells, (file row, cells) of each row that carries a sample):
    blank and comment lines carry none; those among the samples are named in a warning."""
    try:
        handle = open(path, "rb")
    except OSError as exc:
        raise IngestError(f"{path}: cannot open: {exc.strerror}") from None
    numbered: list[tuple[int, list[str]]] = []
    comment_rows: list[int] = []
    with handle:
        try:
            records = csv_records(handle, str(path))
            header_row, header, _ = header_record(records)
            for number, cells, comment in records:
                if comment is not None:
                    comment_rows.append(number)
                elif "".join(cells).strip():
                    numbered.append((number, cells))
        except TableError as exc:
            raise IngestError(str(exc)) from None
    if header_row is None or header is None:
        raise IngestError(f"{path}: empty file, expected a header row")
    if comment_rows:
        warn_comments(str(path), comment_rows)
    return header_row, header, numbered


def _read_block(path: Path, columns: CsvColumns) -> dict[str, np.ndarray | None]:
    """{'joints': (t, values) or None, 'pose': ...} of one file."""
    header_row, header, numbered = _records(path)
    header = [h.strip() for h in header]
    if columns.time not in header:
        raise IngestError(f"{path}: row {header_row}: no time column {columns.time!r} (header: {', '.join(header)})")
    file_rows = np.array([number for number, _ in numbered], dtype=np.int64)
    rows = [r for _, r in numbered]
    for number, row in numbered:
        if len(row) != len(header):
            raise IngestError(f"{path}: row {number}: {len(row)} fields, expected {len(header)} as in the header")
    cells = np.array(rows, dtype=object).reshape(len(rows), len(header))
    out: dict[str, np.ndarray | None] = {}
    for key, names in (("joints", columns.joints), ("pose", columns.pose)):
        present = [n for n in names if n in header]
        if not present:
            out[key] = None
            continue
        if len(present) != len(names):
            missing = next(n for n in names if n not in header)
            raise IngestError(f"{path}: row {header_row}, column {missing}: missing (expected {', '.join(names)})")
        index = [header.index(n) for n in (columns.time,) + tuple(names)]
        block = cells[:, index]
        filled = block[:, 1:] != ""
        partial = np.flatnonzero(filled.any(axis=1) & ~filled.all(axis=1))
        if partial.size:
            r = int(partial[0])
            col = names[int(np.flatnonzero(~filled[r])[0])]
            raise IngestError(f"{path}: row {file_rows[r]}, column {col}: empty, expected a number like the rest "
                              f"of the row's {key} columns")
        rows_with = np.flatnonzero(filled.all(axis=1))
        out[key] = _numbers(path, block[rows_with], file_rows[rows_with], (columns.time,) + tuple(names))
        bad, what = quaternion_faults(out[key][:, 4:8]) if key == "pose" else (np.zeros(0), "")
        if bad.size:
            raise IngestError(f"{path}: row {file_rows[rows_with[bad[0]]]}, column {names[3]}..{names[6]}: {what} "
                              "(expected a unit quaternion w, x, y, z)")
        # Rates, speeds and the clock alignment divide by time steps: each must be > 0.
        stalled = np.flatnonzero(np.diff(out[key][:, 0]) <= 0)
        if stalled.size:
            r = int(stalled[0]) + 1
            raise IngestError(f"{path}: row {file_rows[rows_with[r]]}, column {columns.time}: time "
                              f"{float(out[key][r, 0])!r} is not after the previous {key} row's "
                              f"{float(out[key][r - 1, 0])!r} (times must increase)")
    return out


def _numbers(path: Path, block: np.ndarray, rows: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """The block's cells as float64; `rows`: each line's file row, for the message of a bad cell."""
    try:
        values = block.astype(float)
    except ValueError:
        for i, row in enumerate(block):
            for j, cell in enumerate(row):
                try:
                    float(cell)
                except ValueError:
                    raise IngestError(f"{path}: row {rows[i]}, column {names[j]}: expected a number, "
                                      f"got {cell.strip()!r}") from None
        raise
    bad = np.argwhere(~np.isfinite(values))
    if bad.size:
        i, j = bad[0]
        raise IngestError(f"{path}: row {rows[i]}, column {names[j]}: expected a finite number")
    return values


def read_csv_log(paths: list[str | Path], columns: CsvColumns = CsvColumns()) -> tuple[JointStream, PoseStream]:
    """The joint and tracker streams of one or two CSV logs (layout in the module docstring)."""
    joints = pose = None
    for path in map(Path, paths):
        block = _read_block(path, columns)
        for key, value in block.items():
            if value is None or len(value) == 0:
                continue
            if key == "joints":
                if joints is not None:
                    raise IngestError(f"{path}: a second file with joint columns; give one")
                joints = JointStream(value[:, 0], value[:, 1:], columns.joints, source=str(path), positional=True)
            else:
                if pose is not None:
                    raise IngestError(f"{path}: a second file with pose columns; give one")
                pose = PoseStream(value[:, 0], value[:, 1:4], value[:, 4:8], source=str(path))
    names = ", ".join(map(str, paths))
    if joints is None:
        raise IngestError(f"{names}: no joint samples (columns {columns.time}, {', '.join(columns.joints)})")
    if pose is None:
        raise IngestError(f"{names}: no tracker samples (columns {columns.time}, {', '.join(columns.pose)})")
    return joints, pose


def write_csv_log(path: Path, joints: JointStream, tracker: PoseStream, columns: CsvColumns = CsvColumns()) -> None:
    """One file, both streams merged by time, empty cells where a row does not carry a stream."""
    nj, npose = joints.q.shape[1], 7
    rows = [(t, np.concatenate([q, np.full(npose, np.nan)])) for t, q in zip(joints.t, joints.q)]
    rows += [(t, np.concatenate([np.full(nj, np.nan), p, q])) for t, p, q in zip(tracker.t, tracker.p, tracker.q)]
    rows.sort(key=lambda r: r[0])
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow((columns.time,) + columns.joints[:nj] + columns.pose)
        for t, values in rows:
            writer.writerow([repr(float(t))] + ["" if np.isnan(v) else repr(float(v)) for v in values])
