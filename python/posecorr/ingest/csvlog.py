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
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data import (CHUNK_ROWS, MEAS_POS, REF_POS, REQUIRED, TableError, csv_records, header_record, header_again,
                    implausible_span, quaternion_faults, rows_words, separator_hint, warn_comments)
from ..textui import counted
from .progress import progress_bar
from .streams import IngestError, JointStream, PoseStream, median_period


@dataclass(frozen=True)
class CsvColumns:
    time: str = "t"
    joints: tuple[str, ...] = ("q1", "q2", "q3", "q4", "q5", "q6")
    pose: tuple[str, ...] = ("x", "y", "z", "qw", "qx", "qy", "qz")


# The streams' names in messages.
STREAMS = {"joints": "joint", "pose": "tracker"}
# s: robot drivers publish joint states at 125-500 Hz and trackers report at tens to a thousand
# Hz; both streams a median step this long apart are milliseconds read as seconds (up to
# 2 kHz), or a log too sparse for the still segments' --min-samples.
SLOWEST_PERIOD_S = 0.5


def _open(path: Path):
    try:
        return open(path, "rb")
    except OSError as exc:
        raise IngestError(f"{path}: cannot open: {exc.strerror}") from None


def _read_block(path: Path, columns: CsvColumns) -> tuple[list[str], dict[str, np.ndarray | None], list[str]]:
    """(the header, {'joints': (t, values) or None, 'pose': ...}, notes on what was left out) of
    one file. Read in chunks of CHUNK_ROWS records, each parsed to numbers before the next is
    read: a long log's cells as Python strings would take ten times the file's size."""
    comment_rows: list[int] = []
    bare_rows: list[np.ndarray] = []        # rows with a time and no sample of either stream
    with _open(path) as handle, progress_bar(os.fstat(handle.fileno()).st_size, "B", path) as done:
        try:
            records = csv_records(handle, str(path))
            header_row, header, _ = header_record(records)
            if header_row is None or header is None:
                raise IngestError(f"{path}: empty file, expected a header row")
            header = [h.strip() for h in header]
            _refuse_paired_table(path, header_row, header, columns)
            if columns.time not in header:
                raise IngestError(f"{path}: row {header_row}: no time column {columns.time!r} "
                                  f"(header: {', '.join(header)}){separator_hint(header, columns.time)}")
            wanted = _wanted_columns(path, header_row, header, columns)
            parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {key: [] for key in wanted}
            for numbered in _sample_chunks(records, comment_rows):
                samples, bare = _parse_chunk(path, header, numbered, wanted)
                for key, (values, file_rows) in samples.items():
                    parts[key].append((values, file_rows))
                bare_rows.append(bare)
                done(handle.tell())
        except TableError as exc:
            raise IngestError(str(exc)) from None
    if comment_rows:
        warn_comments(str(path), comment_rows)
    out: dict[str, np.ndarray | None] = {key: None for key in ("joints", "pose")}
    for key, names in wanted.items():
        values = np.concatenate([v for v, _ in parts[key]]) if parts[key] else np.zeros((0, len(names)))
        file_rows = np.concatenate([r for _, r in parts[key]]) if parts[key] else np.zeros(0, np.int64)
        _check_stream(path, key, names, values, file_rows)
        out[key] = values
    bare = np.concatenate(bare_rows) if bare_rows else np.zeros(0, np.int64)
    # A bag's samples that carry nothing usable are counted in a note (streams.keep_usable); so are a log's.
    notes = [f"{path}: {rows_words(bare.tolist(), bare.size, 'has', 'have')} a time but no joint or tracker "
             f"values: {counted(bare.size, 'row')} left out"] if bare.size else []
    return header, out, notes


def _refuse_paired_table(path: Path, header_row: int, header: list[str], columns: CsvColumns) -> None:
    """IngestError on a table that is paired already (what ingest writes and `posecorr fit`
    reads) given as a recording: read as one, it was refused for a recording's column it lacks,
    which did not say that it needs no ingest."""
    if set(REQUIRED) <= set(header) and not set(columns.pose) <= set(header):
        raise IngestError(f"{path}: row {header_row}: columns {MEAS_POS[0]}..{REF_POS[-1]}: this file is already a "
                          "paired pose table, not a recording; give it to `posecorr fit` directly")


def _wanted_columns(path: Path, header_row: int, header: list[str],
                    columns: CsvColumns) -> dict[str, tuple[str, ...]]:
    """{stream: (time, its columns...)} for each stream whose columns the header has, all of them."""
    wanted = {}
    for key, names in (("joints", columns.joints), ("pose", columns.pose)):
        present = [n for n in names if n in header]
        if not present:
            continue
        if len(present) != len(names):
            missing = next(n for n in names if n not in header)
            raise IngestError(f"{path}: row {header_row}, column {missing}: missing (expected {', '.join(names)})")
        wanted[key] = (columns.time,) + tuple(names)
    return wanted


def _sample_chunks(records, comment_rows: list[int]):
    """Lists of (file row, cells) of the records that carry a sample, CHUNK_ROWS at most each:
    blank and comment lines carry none (the comments' rows go to `comment_rows`)."""
    numbered: list[tuple[int, list[str]]] = []
    for number, cells, comment in records:
        if comment is not None:
            comment_rows.append(number)
        elif "".join(cells).strip():
            numbered.append((number, cells))
            if len(numbered) == CHUNK_ROWS:
                yield numbered
                numbered = []
    if numbered:
        yield numbered


def _parse_chunk(path: Path, header: list[str], numbered: list[tuple[int, list[str]]],
                 wanted: dict[str, tuple[str, ...]]) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """({stream: (its rows' numbers (time first), their file rows)}, the file rows that carry no
    sample of any stream) of one chunk; the rows that carry no sample of a stream are left out of it."""
    for number, row in numbered:
        if len(row) != len(header):
            raise IngestError(f"{path}: row {number}: {len(row)} fields, expected {len(header)} as in the header")
    file_rows = np.array([number for number, _ in numbered], dtype=np.int64)
    out = {}
    carried = np.zeros(len(numbered), dtype=bool)
    for key, names in wanted.items():
        index = [header.index(n) for n in names]
        block = np.array([[row[i] for i in index] for _, row in numbered], dtype=object)
        filled = block[:, 1:] != ""
        partial = np.flatnonzero(filled.any(axis=1) & ~filled.all(axis=1))
        if partial.size:
            r = int(partial[0])
            col = names[1 + int(np.flatnonzero(~filled[r])[0])]
            raise IngestError(f"{path}: row {file_rows[r]}, column {col}: empty, expected a number like the rest "
                              f"of the row's {key} columns")
        rows_with = np.flatnonzero(filled.all(axis=1))
        carried[rows_with] = True
        out[key] = (_numbers(path, block[rows_with], file_rows[rows_with], names), file_rows[rows_with])
    return out, file_rows[~carried]


def _check_stream(path: Path, key: str, names: tuple[str, ...], values: np.ndarray, file_rows: np.ndarray) -> None:
    """A stream's whole-file rules: unit quaternions, times that increase (rates, speeds and
    the clock alignment divide by time steps: each must be > 0) and span no more than a session
    (nanoseconds of a minute span 1900 years; the clock alignment's grid of them does not fit
    in memory)."""
    bad, what = quaternion_faults(values[:, 4:8]) if key == "pose" else (np.zeros(0), "")
    if bad.size:
        raise IngestError(f"{path}: row {file_rows[bad[0]]}, column {names[4]}..{names[7]}: {what} "
                          "(expected a unit quaternion w, x, y, z)")
    stalled = np.flatnonzero(np.diff(values[:, 0]) <= 0)
    if stalled.size:
        r = int(stalled[0]) + 1
        raise IngestError(f"{path}: row {file_rows[r]}, column {names[0]}: time {float(values[r, 0])!r} is not "
                          f"after the previous {key} row's {float(values[r - 1, 0])!r} (times must increase)")
    span = implausible_span(values[:, 0])
    if span:
        raise IngestError(f"{path}: rows {file_rows[0]}..{file_rows[-1]}, column {names[0]}: the {STREAMS[key]} stream "
                          f"{span}: nanoseconds or milliseconds? posecorr reads seconds; convert the column "
                          "to seconds")


def _warn_sparse(names: str, time: str, joints: JointStream, pose: PoseStream) -> None:
    """One warning line where both streams' samples come a median SLOWEST_PERIOD_S or more apart:
    milliseconds read as seconds leave the robot still (speeds a thousand times too low) and
    every still segment short of tracker samples, which would be the only words for it."""
    periods = [median_period(t) for t in (joints.t, pose.t)]
    if min(periods) < SLOWEST_PERIOD_S:
        return
    from ..safeio import warn

    joint, tracker = periods
    warn(f"{names}: column {time}: the joint samples are a median {joint:.3g} s apart ({1 / joint:.3g} Hz), the "
         f"tracker samples {tracker:.3g} s ({1 / tracker:.3g} Hz), where a robot cell records tens to thousands of "
         "samples a second: milliseconds? posecorr reads seconds")


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
                    text = cell.strip()
                    raise IngestError(f"{path}: row {rows[i]}, column {names[j]}: expected a number, "
                                      f"got {text!r}{header_again(text, names[j])}") from None
        raise
    bad = np.argwhere(~np.isfinite(values))
    if bad.size:
        i, j = bad[0]
        raise IngestError(f"{path}: row {rows[i]}, column {names[j]}: expected a finite number")
    return values


def read_csv_log(paths: list[str | Path], columns: CsvColumns = CsvColumns()) -> tuple[JointStream, PoseStream]:
    """The joint and tracker streams of one or two CSV logs (layout in the module docstring)."""
    joints = pose = None
    found: dict[str, None] = {}         # the files' header columns, in order
    notes: list[str] = []
    for path in map(Path, paths):
        header, block, left_out = _read_block(path, columns)
        notes += left_out
        found.update(dict.fromkeys(header))
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
        raise IngestError(_no_samples(names, "joint", columns.time, columns.joints, list(found),
                                      "the joint-angle columns with --joint-cols, comma-separated in kinematic order"))
    if pose is None:
        raise IngestError(_no_samples(names, "tracker", columns.time, columns.pose, list(found),
                                      "the tracker's position and quaternion columns with --pose-cols, "
                                      f"comma-separated in the order {', '.join(CsvColumns.pose)}"))
    _warn_sparse(names, columns.time, joints, pose)
    joints.notes += notes
    return joints, pose


def _no_samples(names: str, stream: str, time: str, wanted: tuple[str, ...], found: list[str], option: str) -> str:
    """Why the files give a stream no sample: no row fills its columns, or (a log that names them
    otherwise) the header has none of them: then the columns found, and the option that maps them."""
    if wanted[0] in found:
        return f"{names}: no {stream} samples (columns {time}, {', '.join(wanted)})"
    return (f"{names}: no {stream} columns {', '.join(wanted)} in the header (found {', '.join(found)}); "
            f"name {option}")


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
