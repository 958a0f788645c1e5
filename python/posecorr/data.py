"""The paired-pose table (DESIGN.md, "Data"): one row per static pose.

Positions in metres in the robot base frame, quaternions (w, x, y, z) scalar first.
A table without `ref_q*` columns is position-only (like Experiment I) and first-class.
Bad input raises `TableError`, whose message names the file, the row, the column and
what was expected; nothing is silently dropped: columns posecorr does not know are kept
and written back.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MEAS_POS = ("meas_x", "meas_y", "meas_z")
MEAS_QUAT = ("meas_qw", "meas_qx", "meas_qy", "meas_qz")
REF_POS = ("ref_x", "ref_y", "ref_z")
REF_QUAT = ("ref_qw", "ref_qx", "ref_qy", "ref_qz")
REQUIRED = MEAS_POS + MEAS_QUAT + REF_POS
JOINTS = tuple(f"q{i}" for i in range(1, 7))
# Optional columns with a meaning; numeric ones are parsed and checked like the poses.
NUMERIC_OPTIONAL = ("t", "jitter_mm") + JOINTS
TEXT_OPTIONAL = ("id", "session")
QUAT_NORM_TOLERANCE = 1e-3


class TableError(ValueError):
    """A problem with a pose table, located by file, row and column."""

    def __init__(self, path: str | None, message: str, row: int | None = None,
                 column: str | None = None) -> None:
        where = [str(path) if path else "<table>"]
        if row is not None:
            where.append(f"row {row}")
        if column is not None:
            where.append(f"column {column}")
        super().__init__(f"{', '.join(where)}: {message}")
        self.path, self.row, self.column = path, row, column


@dataclass
class PoseTable:
    """Measured and reference poses, (N, 3) positions and (N, 4) unit quaternions."""

    meas_p: np.ndarray
    meas_q: np.ndarray
    ref_p: np.ndarray
    ref_q: np.ndarray | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    path: str | None = None

    def __post_init__(self) -> None:
        n = len(self.meas_p)
        shapes = {"meas_p": (self.meas_p, 3), "meas_q": (self.meas_q, 4), "ref_p": (self.ref_p, 3)}
        if self.ref_q is not None:
            shapes["ref_q"] = (self.ref_q, 4)
        for name, (a, width) in shapes.items():
            if a.shape != (n, width):
                raise ValueError(f"{name} has shape {a.shape}, expected ({n}, {width})")
        for name, a in self.extras.items():
            if len(a) != n:
                raise ValueError(f"column {name} has {len(a)} rows, expected {n}")

    @property
    def n(self) -> int:
        return len(self.meas_p)

    @property
    def has_orientation(self) -> bool:
        return self.ref_q is not None

    @property
    def measured(self) -> np.ndarray:
        """(N, 7) measured poses x, y, z, qw, qx, qy, qz."""
        return np.concatenate([self.meas_p, self.meas_q], axis=1)

    @property
    def reference(self) -> np.ndarray:
        """(N, 7) reference poses; for a position-only table the orientation is the measured one."""
        q = self.ref_q if self.ref_q is not None else self.meas_q
        return np.concatenate([self.ref_p, q], axis=1)

    def time(self) -> np.ndarray | None:
        return self.extras.get("t")

    def subset(self, index: np.ndarray) -> "PoseTable":
        return PoseTable(self.meas_p[index], self.meas_q[index], self.ref_p[index],
                         None if self.ref_q is None else self.ref_q[index],
                         {k: v[index] for k, v in self.extras.items()}, self.path)

    def with_measured(self, measured: np.ndarray) -> "PoseTable":
        """A copy whose measured poses are replaced by an (N, 7) array (a correction's output)."""
        return PoseTable(np.array(measured[:, :3], dtype=float), np.array(measured[:, 3:7], dtype=float),
                         self.ref_p.copy(), None if self.ref_q is None else self.ref_q.copy(),
                         dict(self.extras), self.path)


def require_rows(table: PoseTable, needed: int, purpose: str) -> None:
    """Raise TableError when the table has fewer rows than `purpose` needs."""
    if table.n < needed:
        raise TableError(table.path, f"{table.n} rows, but {purpose} needs at least {needed}")


def _parse_number(text: str, path: str, row: int, column: str) -> float:
    stripped = text.strip()
    if not stripped:
        raise TableError(path, "empty value, expected a number", row, column)
    try:
        value = float(stripped)
    except ValueError:
        raise TableError(path, f"expected a number, got {stripped!r}", row, column) from None
    if not math.isfinite(value):
        raise TableError(path, f"expected a finite number, got {stripped!r}", row, column)
    return value


def read_table(path: str | Path) -> PoseTable:
    """Read a paired-pose CSV; TableError on anything malformed."""
    path = str(path)
    try:
        handle = open(path, newline="", encoding="utf-8")
    except OSError as exc:
        raise TableError(path, f"cannot open: {exc.strerror}") from None
    with handle:
        reader = csv.reader(handle)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise TableError(path, "empty file, expected a header row") from None
        except csv.Error as exc:
            raise TableError(path, f"not a CSV file: {exc}", 1) from None
        duplicates = sorted({h for h in header if header.count(h) > 1})
        if duplicates:
            raise TableError(path, "duplicate column in header", 1, duplicates[0])
        for name in REQUIRED:
            if name not in header:
                raise TableError(path, "missing column (required: " + ", ".join(REQUIRED) + ")", 1, name)
        present_ref_q = [c for c in REF_QUAT if c in header]
        if present_ref_q and len(present_ref_q) != 4:
            missing = next(c for c in REF_QUAT if c not in header)
            raise TableError(path, "missing column (ref_qw..ref_qz come as a set, or not at all)", 1, missing)
        numeric = list(REQUIRED) + present_ref_q + [c for c in NUMERIC_OPTIONAL if c in header]
        text = [c for c in header if c not in numeric]
        index = {name: header.index(name) for name in header}
        values: dict[str, list[float]] = {c: [] for c in numeric}
        strings: dict[str, list[str]] = {c: [] for c in text}
        row_number = 1
        row_numbers: list[int] = []
        try:
            for row_number, row in enumerate(reader, start=2):
                if not row or all(not cell.strip() for cell in row):
                    continue  # a blank line carries no pose
                if len(row) != len(header):
                    raise TableError(path, f"{len(row)} fields, expected {len(header)} as in the header",
                                     row_number)
                for c in numeric:
                    values[c].append(_parse_number(row[index[c]], path, row_number, c))
                for c in text:
                    strings[c].append(row[index[c]].strip())
                row_numbers.append(row_number)
        except csv.Error as exc:
            raise TableError(path, f"malformed CSV: {exc}", row_number + 1) from None

    arrays = {c: np.asarray(v, dtype=float) for c, v in values.items()}
    extras: dict[str, np.ndarray] = {c: arrays[c] for c in NUMERIC_OPTIONAL if c in arrays}
    extras.update({c: np.asarray(v, dtype=object) for c, v in strings.items()})

    def block(names: tuple[str, ...]) -> np.ndarray:
        return np.stack([arrays[c] for c in names], axis=1)

    table = PoseTable(meas_p=block(MEAS_POS), meas_q=block(MEAS_QUAT), ref_p=block(REF_POS),
                      ref_q=block(REF_QUAT) if present_ref_q else None,
                      extras=extras, path=path)
    _check_quaternions(table, row_numbers)
    return table


def _check_quaternions(table: PoseTable, rows: list[int]) -> None:
    blocks = [("meas_q", table.meas_q, MEAS_QUAT)]
    if table.ref_q is not None:
        blocks.append(("ref_q", table.ref_q, REF_QUAT))
    for _, q, columns in blocks:
        off = np.abs(np.linalg.norm(q, axis=1) - 1.0)
        bad = np.flatnonzero(off > QUAT_NORM_TOLERANCE)
        if bad.size:
            i = int(bad[0])
            raise TableError(table.path, f"quaternion norm {np.linalg.norm(q[i]):.6g} is off 1 by more than "
                             f"{QUAT_NORM_TOLERANCE:g} (expected a unit quaternion w, x, y, z)",
                             rows[i] if i < len(rows) else None, "..".join((columns[0], columns[-1])))


def write_table(table: PoseTable, path: str | Path) -> None:
    """Write the table as CSV, every float with round-trip precision."""
    columns: list[tuple[str, np.ndarray]] = []
    if "id" in table.extras:
        columns.append(("id", table.extras["id"]))
    columns += [(c, table.meas_p[:, i]) for i, c in enumerate(MEAS_POS)]
    columns += [(c, table.meas_q[:, i]) for i, c in enumerate(MEAS_QUAT)]
    columns += [(c, table.ref_p[:, i]) for i, c in enumerate(REF_POS)]
    if table.ref_q is not None:
        columns += [(c, table.ref_q[:, i]) for i, c in enumerate(REF_QUAT)]
    columns += [(c, v) for c, v in table.extras.items() if c != "id"]
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow([c for c, _ in columns])
        for i in range(table.n):
            writer.writerow([repr(float(v[i])) if isinstance(v[i], (float, np.floating)) else v[i]
                             for _, v in columns])
