"""The paired-pose table (docs/design.md, "Data"): one row per static pose.

Positions in metres in the robot base frame, quaternions (w, x, y, z) scalar first.
A table without `ref_q*` columns is position-only (like Experiment I) and first-class.
Bad input raises `TableError`, whose message names the file, the row, the column and
what was expected; nothing is silently dropped: columns posecorr does not know are kept
and written back. Numbers are plain decimal notation (what Python's float() takes beyond
that, "1_0", "inf", "0x1p3", is an error), text is UTF-8 (a byte order mark is skipped),
quaternions are unit (a zero one is an error). A line that starts with '#' is a comment
(a logger's preamble before the header, a pose left out by hand), as numpy and pandas read
one: it is no pose, the reader says how many it passed over among the poses, and `apply`
copies each to its output where it stood. `TableReader` streams a table in chunks with the
same checks (`posecorr apply` on millions of rows).
"""
from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .textui import closest, counted, first_few

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
# What a refused quaternion's line suggests: a zero one is a tracker's "no pose"; a norm a
# little off is most often a quaternion rounded when written (4 decimals keep it within 0.001).
ZERO_QUATERNION_FIX = "a tracker that lost tracking writes zeros: remove the row"
NORM_FIX = "normalise the quaternions if they were rounded (4 decimals keep the norm within 0.001)"
# A tracker sees a few metres and a robot cell is a few metres wide: a coordinate beyond
# this (metres) is a unit mistake (millimetres) or a corrupt value, not a pose.
MAX_POSITION = 1e3
# A Lighthouse system tracks within about 10 m and a robot cell is smaller: positions whose
# median absolute deviation exceeds this (metres) are another unit, most likely millimetres
# within MAX_POSITION. The median's statistic: one pose far away (a glitch) is no unit.
PLAUSIBLE_SPREAD = 10.0


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
        self.path, self.message, self.row, self.column = path, message, row, column

    def __reduce__(self):
        # Rebuilt from its parts, so that it crosses a process pool intact.
        return type(self), (self.path, self.message, self.row, self.column)


@dataclass
class PoseTable:
    """Measured and reference poses, (N, 3) positions and (N, 4) unit quaternions.

    rows: each pose's row in the file it was read from, the number of its line as an editor
    shows it (blank and comment lines count); None for a table made in memory (`simulate`).
    station_pose: where the session's base station stood, as the user states it
    (`geometry.parse_station_pose`, `--station-pose`); None: the paper's station (eq. 23).
    """

    meas_p: np.ndarray
    meas_q: np.ndarray
    ref_p: np.ndarray
    ref_q: np.ndarray | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    path: str | None = None
    rows: np.ndarray | None = None
    station_pose: str | None = None
    # `require_rows` has said what a fit should know of these rows (`warn_fit_table`)
    warned: bool = field(default=False, repr=False, compare=False)

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
        if self.rows is not None and np.shape(self.rows) != (n,):
            raise ValueError(f"rows has shape {np.shape(self.rows)}, expected ({n},)")

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

    @property
    def source(self) -> str:
        """What a warning about the table names: its file, or 'the table' for one made in
        memory."""
        return self.path if self.path is not None else "the table"

    def file_row(self, i: int) -> int:
        """Pose i's row as an editor shows it: the file's, or for a table made in memory the
        one `write_table` would give it (the header is row 1)."""
        return int(self.rows[i]) if self.rows is not None else int(i) + 2

    def subset(self, index: np.ndarray) -> "PoseTable":
        return PoseTable(self.meas_p[index], self.meas_q[index], self.ref_p[index],
                         None if self.ref_q is None else self.ref_q[index],
                         {k: v[index] for k, v in self.extras.items()}, self.path,
                         None if self.rows is None else self.rows[index], self.station_pose)

    def draw(self, n: int, seed: int = 0) -> tuple["PoseTable", np.ndarray]:
        """An even random draw of n rows in table order (the whole table when it has at most
        n), and their indices."""
        if self.n <= n:
            return self, np.arange(self.n)
        keep = np.sort(np.random.default_rng(seed).choice(self.n, n, replace=False))
        return self.subset(keep), keep

    def with_measured(self, measured: np.ndarray) -> "PoseTable":
        """A copy whose measured poses are replaced by an (N, 7) array (a correction's output)."""
        return PoseTable(np.array(measured[:, :3], dtype=float), np.array(measured[:, 3:7], dtype=float),
                         self.ref_p.copy(), None if self.ref_q is None else self.ref_q.copy(),
                         dict(self.extras), self.path, self.rows, self.station_pose)


# Below this extent (metres, under the tracker's jitter) the poses are one pose seen twice
# over: a fit would model noise and report absurd improvements.
MIN_SPREAD = 1e-4


def require_rows(table: PoseTable, needed: int, purpose: str,
                 outliers: Callable[[PoseTable], list[str]] | None = None) -> None:
    """Raise TableError when the table cannot support `purpose`: fewer than `needed` rows,
    fewer than `needed` distinct poses, or poses that do not spread over a workspace; then
    `outliers` (the verbs that fit: `posecorr.train.pipeline.check_outliers`, which refuses
    blunders and gives the lines naming suspect rows), then the warnings (`warn_fit_table`)."""
    if table.n < needed:
        raise TableError(table.path, f"{counted(table.n, 'row')}, but {purpose} needs at least {needed}")
    distinct = len(np.unique(table.measured, axis=0))
    if distinct < needed:
        raise TableError(table.path, f"{counted(table.n, 'row')} but only "
                         f"{counted(distinct, 'distinct measured pose')}; {purpose} needs at least {needed}")
    for name, p in (("measured", table.meas_p), ("reference", table.ref_p)):
        spread = float(np.max(np.ptp(p, axis=0)))
        if spread < MIN_SPREAD:
            raise TableError(table.path, f"the {name} positions span only {spread:.3g} m; {purpose} needs "
                             f"poses spread over the workspace (at least {MIN_SPREAD:g} m)")
    _require_one_unit(table)
    warn_fit_table(table, outliers(table) if outliers is not None else [])


# A rigid registration keeps distances, and no effect scales them by more than a few per cent:
# the two frames' spreads this many times apart are two units (millimetres and metres: 1000).
UNITS_APART = 30.0


def _require_one_unit(table: PoseTable) -> None:
    """TableError where the measured and reference positions spread (`typical_spread`, which
    a glitching pose does not move) by `UNITS_APART` times or more apart, the larger a metre
    or more, or both beyond `PLAUSIBLE_SPREAD`: a fit went on after a warning and wrote a
    model off by hundreds of metres (the first), or fitted millimetres against thresholds in
    metres (the second)."""
    spreads = {"measured": typical_spread(table.meas_p), "reference": typical_spread(table.ref_p)}
    if min(spreads.values()) > PLAUSIBLE_SPREAD:   # the units warning's case in both frames
        raise TableError(table.path, f"the measured positions lie a typical {spreads['measured']:.4g} m from their "
                                     f"median and the reference {spreads['reference']:.4g} m, where a tracked cell "
                                     f"spans a few metres (are {MEAS_POS[0]}..{MEAS_POS[-1]} and "
                                     f"{REF_POS[0]}..{REF_POS[-1]} in millimetres? posecorr reads metres)")
    large, small = sorted(spreads, key=spreads.get, reverse=True)
    if spreads[large] >= 1.0 and spreads[large] >= UNITS_APART * spreads[small]:
        columns = REF_POS if large == "reference" else MEAS_POS
        raise TableError(table.path, f"the {large} positions lie a typical {spreads[large]:.4g} m from their median "
                                     f"and the {small} {spreads[small]:.3g} m: a registration keeps distances, so "
                                     f"the two are in units {spreads[large] / spreads[small]:.0f} times apart (are "
                                     f"{columns[0]}..{columns[-1]} in millimetres or centimetres? posecorr reads "
                                     "metres)")


# Plain decimal notation only: Python's float() also takes "1_0", "infinity", "nan" and
# "0x1p3", which no tracker or robot writes and which would turn a typo into a number.
_NUMBER = r"[ \t]*[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?[ \t]*"
_NUMBER_RE = re.compile(_NUMBER)
# A column whose cells use only these characters and that float() reads whole is plain
# decimal notation: what float() takes beyond it needs a letter or an underscore.
_DECIMAL_CHARS_RE = re.compile(r"[0-9eE+\-. \t\n]*")
CHUNK_ROWS = 16384  # rows per chunk: ~25 MB of cells as Python strings


def header_again(cell: str, column: str) -> str:
    """The words after "expected a number, got 'meas_x'" where a cell holds its column's name:
    two logs joined with `cat` carry the second one's header inside the table."""
    return ", its column's name: a header row again (tables joined? keep the first header only)" \
        if cell == column else ""


def _parse_number(text: str, path: str, row: int, column: str) -> float:
    stripped = text.strip()
    if not stripped:
        raise TableError(path, "empty value, expected a number", row, column)
    try:
        value = float(stripped)
    except ValueError:
        raise TableError(path, f"expected a number, got {stripped[:40]!r}{header_again(stripped, column)}",
                         row, column) from None
    if math.isfinite(value) and not _NUMBER_RE.fullmatch(stripped):
        raise TableError(path, f"expected a number in plain decimal notation (like -0.125 or 1.5e-3), "
                         f"got {stripped[:40]!r}", row, column)
    if not math.isfinite(value):
        raise TableError(path, f"expected a finite number, got {stripped[:40]!r}", row, column)
    return value


# What a tracker's log writes where tracking was lost, read as nan by `apply --keep-going`.
LOST_CELLS = ("", "nan")


def _parse_column(cells: list[str], path: str, rows: list[int], column: str, lost_as_nan: bool = False) -> np.ndarray:
    """One column of a chunk as float64, checked as a whole; cell by cell only to name the
    first bad one. `lost_as_nan`: a cell of LOST_CELLS is nan, for the model to refuse."""
    if _DECIMAL_CHARS_RE.fullmatch("\n".join(cells)):
        try:
            values = np.array(list(map(float, cells)), dtype=np.float64)
        except ValueError:
            pass
        else:
            if np.all(np.isfinite(values)):
                return values
    return np.array([math.nan if lost_as_nan and c.strip().lower() in LOST_CELLS else _parse_number(c, path, r, column)
                     for c, r in zip(cells, rows)], dtype=np.float64)


@dataclass
class Chunk:
    """Consecutive data rows of a table: the cells as read and the numeric columns parsed."""

    rows: list[list[str]]
    row_numbers: list[int]
    values: dict[str, np.ndarray]
    # (how many of `rows` come before it, its text): the comment lines among these rows
    comments: list[tuple[int, str]] = field(default_factory=list)

    def block(self, names: tuple[str, ...]) -> np.ndarray:
        return np.stack([self.values[c] for c in names], axis=1)


COMMENT = "#"


@dataclass
class _Cursor:
    """Where `csv_records` is in a file: the lines read, the line the record being read
    starts on, that line's text if it is a comment, and how the first line ends (a table
    written back, `posecorr apply`'s, keeps the input's line endings)."""

    line: int = 0
    start: int = 1
    comment: str | None = None
    ending: str = "\n"


def _decoded_lines(handle, path: str, cursor: _Cursor):
    """The file's lines as text; a byte that is not UTF-8 fails naming its line. A record's
    first line that starts with COMMENT is kept in `cursor` and reaches the csv module as a
    blank line: a quote in a comment opens no cell (a line inside a quoted cell is read as is)."""
    for raw in handle:
        cursor.line += 1
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise TableError(path, f"not UTF-8 text (byte 0x{raw[exc.start]:02x} at character {exc.start + 1}); "
                             "save the table as UTF-8 CSV", cursor.line) from None
        if cursor.line == 1:
            cursor.ending = "\r\n" if line.endswith("\r\n") else "\n"
            if line.startswith("\ufeff"):
                line = line[1:]  # a byte order mark is an encoding detail, not part of the first name
        if cursor.line == cursor.start and line.startswith(COMMENT):
            cursor.comment, line = line.rstrip("\r\n"), "\n"
        yield line


def csv_records(handle, path: str, cursor: _Cursor | None = None):
    """A CSV file's records as (the line it starts on, its cells, its text if it is a comment
    line, else None). `handle` is opened in binary: the lines are decoded here. `cursor`: where
    the reading is, for a caller that asks (a new one if None)."""
    cursor = cursor or _Cursor()
    reader = csv.reader(_decoded_lines(handle, path, cursor))
    while True:
        cursor.start, cursor.comment = cursor.line + 1, None
        try:
            cells = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            if "new-line character seen in unquoted field" in str(exc):   # the csv module's words
                raise TableError(path, "a carriage return (\\r) inside the line, not at its end: its line endings "
                                 "are mixed (text added after a Windows line ending?); save the table with "
                                 "one kind of line ending", cursor.line) from None
            raise TableError(path, f"malformed CSV: {exc}", cursor.line) from None
        yield cursor.start, cells, cursor.comment


def header_record(records) -> tuple[int | None, list[str] | None, list[tuple[int, str]]]:
    """Read `csv_records` up to the header, the first record neither blank nor a comment: (its
    row, its cells, the comment lines before it as (row, text)); (None, None, those comment
    lines) where the file has no header."""
    preamble: list[tuple[int, str]] = []
    for row, cells, comment in records:
        if comment is not None:
            preamble.append((row, comment))
        elif "".join(cells).strip():
            return row, cells, preamble
    return None, None, preamble


def protect_comment(line: str, first: str) -> str:
    """A CSV line (no newline) whose first cell `first`, written bare, would read back as a
    comment: that cell quoted."""
    if not line.startswith(COMMENT):
        return line
    return '"' + first.replace('"', '""') + '"' + line[len(first):]


# The comment lines a warning names by row; the rest it counts.
COMMENTS_SHOWN = 5


def rows_words(rows: list[int], count: int, one: str, many: str) -> str:
    """'row 7 starts' or 'rows 7, 9, 12, 15, 18 and 3 more start': the first rows of `count`
    a warning names, with its verb for one (`one`) or for many (`many`)."""
    return f"row {rows[0]} {one}" if count == 1 else f"rows {first_few(rows, COMMENTS_SHOWN, count)} {many}"


def warn_comments(path: str, rows: list[int], count: int | None = None) -> None:
    """One warning line for the `count` comment lines after a header, the first of them at
    `rows`: 'rows 7, 9, 12, 15, 18 and 3 more start with '#'': a line left out by hand is said
    to be left out."""
    from .safeio import warn

    count = len(rows) if count is None else count
    which = rows_words(rows, count, "starts", "start")
    warn(f"{path}: {which} with {COMMENT!r}: read as comments, not data")


KNOWN_COLUMNS = REQUIRED + REF_QUAT + NUMERIC_OPTIONAL + TEXT_OPTIONAL


def _warn_misspelled(path: str, header: list[str]) -> None:
    """One warning line for each unknown column whose name is close to a known one the table
    lacks (`jiter_mm`): it is kept as an unknown column, so its meaning would be lost unsaid."""
    from .safeio import warn

    missing = [c for c in KNOWN_COLUMNS if c not in header]
    angles = _angle_columns(header, "ref_") if REF_QUAT[0] not in header else []
    if angles:
        warn(f"{path}: columns {', '.join(map(repr, angles))} look like angles (Euler or a rotation vector), and "
             f"posecorr reads the reference orientation as unit quaternions {REF_QUAT[0]}..{REF_QUAT[-1]}: without "
             f"them the table is read position-only; {ANGLES_FIX}")
    for name in header:
        if name in KNOWN_COLUMNS or not name or name in angles:
            continue
        close = closest(name.lower(), missing, cutoff=0.8)
        if close:
            warn(f"{path}: column {name!r} is not one posecorr knows and is kept as is; did you mean {close}?")


def separator_hint(header: list[str], name: str) -> str:
    """"; the header is one column holding ';': posecorr reads commas" where the header is one
    column whose name holds `name` between another separator's; "" otherwise."""
    # a spreadsheet's export in a comma-decimal locale: one column whose name holds them all
    other = next((sep for sep in ";\t|" if len(header) == 1 and name in header[0].split(sep)), None)
    return f"; the header is one column holding {other!r}: posecorr reads commas" if other else ""


# A name with its unit after it: 'meas_x [m]', 'ref_x (mm)'.
_UNIT_SUFFIX = re.compile(r"(.+?)\s*[\[(][^\])]*[\])]\s*")
# An orientation as angles, which posecorr does not read: Euler angles (roll, pitch, yaw;
# KUKA's A, B, C), or a rotation vector (Universal Robots' rx, ry, rz), after meas_ or ref_.
_ANGLE_NAME = re.compile(r"(roll|pitch|yaw|rpy|euler|rot|r[xyz]|[abc]\b|angle).*")
# How angle columns become the quaternions posecorr reads.
ANGLES_FIX = ("convert them (scipy: Rotation.from_euler(sequence, angles, degrees=True), or from_rotvec, then "
              ".as_quat(scalar_first=True))")
HEADER_SHOWN = 12


def _angle_columns(names: Sequence[str], side: str) -> list[str]:
    """The columns among `names` of the `side` ('meas_' or 'ref_') that look like angles."""
    return [h for h in names if h.lower().startswith(side) and _ANGLE_NAME.fullmatch(h.lower()[len(side):])]


def _stand_in(name: str, header: list[str]) -> str:
    """What the header holds in place of the missing column `name`: the name with a unit after
    it ('; the header has 'meas_x [m]': ...'), Euler angles in place of a quaternion, a
    mistyping of it (refy, meas_X, ref_x_m: '; the header has 'refy': is it ref_y?'), else
    the header's first names."""
    for h in header:
        bare = _UNIT_SUFFIX.fullmatch(h)
        if bare and bare.group(1) == name:
            return (f"; the header has {h!r}: name the column {name}, without a unit (posecorr reads positions in "
                    "metres)")
    side = name.split("_")[0] + "_"
    angles = _angle_columns(header, side) if name in MEAS_QUAT + REF_QUAT else []
    if angles:
        return (f"; the header has {', '.join(map(repr, angles))}: posecorr reads orientations as unit quaternions "
                f"{side}qw..{side}qz, not angles: {ANGLES_FIX}")
    unknown = {h.lower(): h for h in header if h not in KNOWN_COLUMNS}
    close = closest(name, list(unknown), cutoff=0.8)
    if close:
        return f"; the header has {unknown[close]!r}: is it {name}?"
    return f"; the header has {first_few([repr(h) for h in header], HEADER_SHOWN)}"


class TableReader:
    """A paired-pose CSV read in chunks, every cell checked (see the module doc).

    ``require_reference=False`` also accepts a measurement-only table (no ``ref_*``
    columns; `posecorr apply`). ``measured_checked=False`` passes a measured pose that
    tracking lost on to the model, which refuses that pose alone (`apply --keep-going`): a
    quaternion that is zero or not unit, a measured cell that is empty or nan (what a
    tracker's log writes there), read as nan. ``zero_fix`` is what the refusal of a zero
    measured quaternion suggests. Use as a context manager; `chunks()` yields `Chunk`s.
    """

    def __init__(self, path: str | Path, require_reference: bool = True,
                 measured_checked: bool = True, zero_fix: str = ZERO_QUATERNION_FIX) -> None:
        self.path = str(path)
        self.measured_checked = measured_checked
        self.zero_fix = zero_fix
        if Path(self.path).is_dir():
            raise TableError(self.path, "is a folder, expected a CSV file")
        try:
            self._handle = open(self.path, "rb")
        except OSError as exc:
            raise TableError(self.path, f"cannot open: {exc.strerror}") from None
        self._cursor = _Cursor()
        self._records = csv_records(self._handle, self.path, self._cursor)
        # the comment lines before the header (row, text: `_read_header`); how many among the
        # poses and the rows of the first COMMENTS_SHOWN; the text of those after the last pose
        # (`chunks`)
        self.preamble: list[tuple[int, str]] = []
        self.comment_count = 0
        self.comment_rows: list[int] = []
        # rows whose every cell is empty (a spreadsheet's deleted row): how many, the first few
        self.empty_count = 0
        self.empty_rows: list[int] = []
        self.trailing: list[str] = []
        try:
            self.header = self._read_header(require_reference)
        except BaseException:
            self._handle.close()
            raise

    def _read_header(self, require_reference: bool) -> list[str]:
        path = self.path
        self.header_row, cells, self.preamble = header_record(self._records)
        if cells is None:
            raise TableError(path, "empty file, expected a header row" if not self.preamble else
                             "only comment lines, expected a header row naming the columns")
        header = [h.strip() for h in cells]
        # numpy's savetxt writes its header as a comment: name the line, not the first pose's cells
        named, text = self.preamble[-1] if self.preamble else (0, "")
        if MEAS_POS[0] not in header and MEAS_POS[0] in (c.strip() for c in text.lstrip(COMMENT).split(",")):
            raise TableError(path, f"the line naming the columns starts with {COMMENT!r}, which makes it a comment: "
                             f"remove the {COMMENT!r} to make it the header", named)
        # Linear in the number of columns: a header of a million names is refused or read
        # in a second, not in hours.
        self.index = {}
        for i, name in enumerate(header):
            if self.index.setdefault(name, i) != i:
                raise TableError(path, "duplicate column in header", self.header_row, name)
        ref_present = [c for c in REF_POS if c in self.index]
        required = REQUIRED if require_reference or ref_present else MEAS_POS + MEAS_QUAT
        for name in required:
            if name not in self.index:
                hint = separator_hint(header, name) or _stand_in(name, header)
                raise TableError(path, "missing column (required: " + ", ".join(required) + ")" + hint,
                                 self.header_row, name)
        present_ref_q = [c for c in REF_QUAT if c in self.index]
        if present_ref_q and len(present_ref_q) != 4:
            missing = next(c for c in REF_QUAT if c not in self.index)
            raise TableError(path, "missing column (ref_qw..ref_qz come as a set, or not at all)"
                             + _stand_in(missing, header), self.header_row, missing)
        if present_ref_q and not ref_present:
            raise TableError(path, "missing column (ref_qw..ref_qz need ref_x, ref_y, ref_z)", self.header_row,
                             "ref_x")
        self.has_reference = bool(ref_present)
        self.has_ref_orientation = bool(present_ref_q)
        self.numeric = list(required) + present_ref_q + [c for c in NUMERIC_OPTIONAL if c in self.index]
        numeric = set(self.numeric)
        self.text = [c for c in header if c not in numeric]
        _warn_misspelled(path, header)
        return header

    @property
    def line_ending(self) -> str:
        """"\\r\\n" where the file's first line ends so, else "\\n"."""
        return self._cursor.ending

    def __enter__(self) -> "TableReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._handle.close()

    def chunks(self, size: int = CHUNK_ROWS):
        """Chunks of up to `size` data rows; comment lines and lines without a value (blank, or
        every cell empty) go into the chunk's `comments` (those after the last pose into
        `trailing`), and once the table is read a warning names the comment lines among the
        poses and another the rows of empty cells. A chunk also
        ends at `size` comment lines, even with no rows: a file of millions of comment lines
        between two poses is held `size` lines at a time, not whole."""
        width = len(self.header)
        rows: list[list[str]] = []
        numbers: list[int] = []
        comments: list[tuple[int, str]] = []
        for record, row, comment in self._records:
            # A line without a value (blank, or every cell empty) carries no pose; like a
            # comment it stays in its place among the poses (apply writes it back, so the
            # output's lines stay the input's), and a row of empty cells is named: it may be
            # a pose that was lost.
            empty = comment is None and not "".join(row).strip()
            if comment is not None or empty:
                comments.append((len(rows), ",".join(row) if empty else comment))
                if comment is not None:
                    self.comment_count += 1
                    self.comment_rows += [record] if len(self.comment_rows) < COMMENTS_SHOWN else []
                elif row:
                    self.empty_count += 1
                    self.empty_rows += [record] if len(self.empty_rows) < COMMENTS_SHOWN else []
                if len(comments) == size:
                    yield self._parse(rows, numbers, comments)
                    rows, numbers, comments = [], [], []
                continue
            if len(row) != width:
                raise TableError(self.path, f"{len(row)} fields, expected {width} as in the header", record)
            rows.append(row)
            numbers.append(record)
            if len(rows) == size:
                yield self._parse(rows, numbers, comments)
                rows, numbers, comments = [], [], []
        if rows:
            yield self._parse(rows, numbers, comments)
            comments = []
        self.trailing = [text for _, text in comments]
        if self.comment_count:
            warn_comments(self.path, self.comment_rows, self.comment_count)
        if self.empty_count:
            from .safeio import warn

            warn(f"{self.path}: {rows_words(self.empty_rows, self.empty_count, 'has', 'have')} every cell empty: "
                 "no pose read there")

    def _parse(self, rows: list[list[str]], numbers: list[int], comments: list[tuple[int, str]]) -> Chunk:
        values = {c: _parse_column([row[self.index[c]] for row in rows], self.path, numbers, c,
                                   lost_as_nan=not self.measured_checked and c in MEAS_POS + MEAS_QUAT)
                  for c in self.numeric}
        chunk = Chunk(rows, numbers, values, comments)
        for c in MEAS_POS + (REF_POS if self.has_reference else ()):
            far = np.flatnonzero(np.abs(values[c]) > MAX_POSITION)
            if far.size:
                i = int(far[0])
                raise TableError(self.path, f"{values[c][i]:.6g} m is more than {MAX_POSITION:g} m from the origin "
                                 "(positions are in metres)", numbers[i], c)
        if self.measured_checked:
            _check_quaternions(self.path, chunk.block(MEAS_QUAT), MEAS_QUAT, numbers, self.zero_fix)
        if self.has_ref_orientation:
            _check_quaternions(self.path, chunk.block(REF_QUAT), REF_QUAT, numbers)
        return chunk


class TooManyRows(TableError):
    """A table longer than the caller's `max_rows`, refused after reading that many."""


def read_table(path: str | Path, max_rows: int | None = None) -> PoseTable:
    """Read a paired-pose CSV; TableError on anything malformed, TooManyRows past
    `max_rows` data rows (read no further). Only the parsed columns are kept of each chunk,
    not its cells as text, and each pose's file row (`PoseTable.rows`)."""
    values: list[dict[str, np.ndarray]] = []
    cells: list[dict[str, list[str]]] = []
    numbers: list[np.ndarray] = []
    rows = 0
    with TableReader(path) as reader:
        numeric, text = reader.numeric, reader.text
        has_ref_q, index = reader.has_ref_orientation, reader.index
        for chunk in reader.chunks():
            rows += len(chunk.rows)
            if max_rows is not None and rows > max_rows:
                raise TooManyRows(str(path), f"more than {max_rows:,} data rows")
            values.append(chunk.values)
            numbers.append(np.asarray(chunk.row_numbers, dtype=np.int64))
            cells.append({c: [row[index[c]].strip() for row in chunk.rows] for c in text})
    path = str(path)
    if rows == 0:
        raise TableError(path, "no data rows after the header")
    arrays = {c: np.concatenate([v[c] for v in values]) for c in numeric}
    extras: dict[str, np.ndarray] = {c: arrays[c] for c in NUMERIC_OPTIONAL if c in arrays}
    for c in text:
        extras[c] = np.asarray([cell for part in cells for cell in part[c]], dtype=object)

    def block(names: tuple[str, ...]) -> np.ndarray:
        return np.stack([arrays[c] for c in names], axis=1)

    meas_p, ref_p = block(MEAS_POS), block(REF_POS)
    for name, columns, positions in (("measured", MEAS_POS, meas_p), ("reference", REF_POS, ref_p)):
        spread = implausible_spread(positions)
        if spread is not None:
            from .safeio import warn

            warn(f"{path}: the {name} positions lie a typical {spread:.4g} m from their median; posecorr reads "
                 f"metres, and a tracked cell spans a few: are {columns[0]}..{columns[-1]} in millimetres?")
    return PoseTable(meas_p=meas_p, meas_q=block(MEAS_QUAT), ref_p=ref_p,
                     ref_q=block(REF_QUAT) if has_ref_q else None, extras=extras, path=path,
                     rows=np.concatenate(numbers))


def warn_fit_table(table: PoseTable, more: Sequence[str] = ()) -> None:
    """What a verb that fits should say of a table it accepts, once: repeated rows, a time
    column that is not seconds since the session's start, several sessions, and the lines
    `more`. Said after the table's refusals, so that a refused table ends in its one line."""
    if table.warned:
        return
    table.warned = True
    _warn_repeats(table)
    _warn_times(table)
    _warn_sessions(table)
    if more:
        from .safeio import warn

        for line in more:
            warn(line)


def _warn_sessions(table: PoseTable) -> None:
    """One warning line for a table whose `session` column names several sessions: every
    model has one tracker frame and one mount, so two sessions registered apart are fitted as
    one (two simulated sessions of 10 poses joined scored 1.2 m leave-one-out, each alone 0.6-0.7 mm)."""
    sessions = table.extras.get("session")
    if sessions is None:
        return
    names = list(dict.fromkeys(str(s) for s in sessions if str(s).strip()))
    if len(names) > 1:
        from .safeio import warn

        warn(f"{table.source}: column session names {len(names)} sessions ({first_few(names, COMMENTS_SHOWN)}); posecorr models one tracker frame "
             "and one mount for all rows: where the sessions' frames differ, fit each session's rows alone")


def _warn_repeats(table: PoseTable) -> None:
    """One warning line for rows that repeat an earlier row's measured and reference pose: held
    out, a repeat keeps its twin in training, and every held-out error comes out better than
    the tracker is (a table of six poses each written twice scored 0.70 mm leave-one-out, the
    six alone 1.08 mm)."""
    poses = np.concatenate([table.measured, table.reference], axis=1)
    _, first = np.unique(poses, axis=0, return_index=True)
    repeats = np.setdiff1d(np.arange(table.n), first)
    if repeats.size:
        from .safeio import warn

        verb = "repeats" if repeats.size == 1 else "repeat"
        warn(f"{table.source}: {counted(int(repeats.size), 'row')} ({first_few([table.file_row(i) for i in repeats], COMMENTS_SHOWN)}) "
             f"{verb} an earlier row's measured and "
             "reference pose: a repeat held out keeps its twin in training, so held-out errors come out optimistic")
    _warn_frozen(table, set(repeats.tolist()))


def _warn_frozen(table: PoseTable, repeats: set[int]) -> None:
    """One warning line for rows whose measured pose is, to the last bit, an earlier row's
    while their reference differs: a tracker that lost tracking holds its last pose (a
    pose repeated so, three rows of a real session, scored 410 mm leave-one-out, the
    session 5.7 mm); an average of real samples never repeats exactly."""
    _, first, which = np.unique(table.measured, axis=0, return_index=True, return_inverse=True)
    frozen = [i for i in range(table.n) if first[which[i]] != i and i not in repeats]
    if frozen:
        from .safeio import warn

        pairs = [f"{table.file_row(i)} as {table.file_row(int(first[which[i]]))}" for i in frozen]
        warn(f"{table.source}: {counted(len(frozen), 'row')} report{'s' if len(frozen) == 1 else ''} exactly an "
             f"earlier row's measured pose where the reference moved (rows {first_few(pairs, COMMENTS_SHOWN)}): a "
             "tracker that lost tracking holds its last pose; kept, fix or remove the row(s)")


# A calibration session lasts minutes to hours; a time column that spans more is in another
# unit (milliseconds of a 35-minute session span 24 days).
PLAUSIBLE_SESSION_S = 2 * 86_400.0


def _warn_times(table: PoseTable) -> None:
    """Warning lines for a time column that cannot be seconds since the session's start: times
    before it (drift grows from t = 0; before it, it runs backwards), or a span of days."""
    t = table.time()
    if t is None:
        return
    from .safeio import warn

    if float(t.min()) < 0.0:
        warn(f"{table.source}: column t starts at {float(t.min()):.6g} s; t is seconds since the session's start, "
             "where drift is 0, so no time is negative")
    words = implausible_span(t)
    if words:
        warn(f"{table.source}: column t {words}: milliseconds? posecorr reads seconds")


def implausible_span(t: np.ndarray) -> str | None:
    """'spans 2.1e+06 s (24.3 days), and a session lasts minutes to hours' where the times t
    span more than PLAUSIBLE_SESSION_S (another unit than seconds); None otherwise."""
    span = float(np.ptp(t)) if len(t) else 0.0
    if span <= PLAUSIBLE_SESSION_S:
        return None
    return f"spans {span:.6g} s ({span / 86_400:.3g} days), and a session lasts minutes to hours"


def typical_spread(positions: np.ndarray) -> float:
    """The typical distance (m) of positions (N, 3) from their median: the largest axis' median
    absolute deviation, which one far pose does not move."""
    return float(np.max(np.median(np.abs(positions - np.median(positions, axis=0)), axis=0)))


def implausible_spread(positions: np.ndarray) -> float | None:
    """`typical_spread` when it is beyond PLAUSIBLE_SPREAD (another unit); None otherwise."""
    spread = typical_spread(positions)
    return spread if spread > PLAUSIBLE_SPREAD else None


def quaternion_faults(q: np.ndarray) -> tuple[np.ndarray, str]:
    """(the indices of the rows of q (N, 4) that are no unit quaternion, what is wrong with the
    first: 'a zero quaternion' or 'quaternion norm 1.05 is off 1 by more than 0.001'). NaN rows
    are not counted: the readers say where a value is not finite."""
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUAT_NORM_TOLERANCE)
    if not bad.size:
        return bad, ""
    first = norm[bad[0]]
    return bad, ("a zero quaternion" if first == 0 else
                 f"quaternion norm {first:.6g} is off 1 by more than {QUAT_NORM_TOLERANCE:g}")


def _check_quaternions(path: str | None, q: np.ndarray, columns: tuple[str, ...], rows: list[int],
                       zero_fix: str = ZERO_QUATERNION_FIX) -> None:
    bad, what = quaternion_faults(q)
    if bad.size:
        fix = zero_fix if not np.any(q[bad[0]]) else NORM_FIX
        raise TableError(path, f"{what} (expected a unit quaternion w, x, y, z); {fix}", rows[int(bad[0])],
                         "..".join((columns[0], columns[-1])))


def _check_writable(table: PoseTable, path: str) -> None:
    """What `read_table` would refuse is not written: finite positions within MAX_POSITION
    of the origin, unit quaternions (rows as in the file: the header is row 1)."""
    rows = list(range(2, table.n + 2))
    blocks = [(MEAS_POS, table.meas_p), (REF_POS, table.ref_p)]
    for columns, values in blocks:
        bad = np.argwhere(~(np.abs(values) <= MAX_POSITION))
        if bad.size:
            i, k = (int(x) for x in bad[0])
            raise TableError(path, f"refusing to write {values[i, k]:.6g} m (positions are finite metres within "
                             f"{MAX_POSITION:g} m of the origin)", rows[i], columns[k])
    _check_quaternions(path, np.nan_to_num(table.meas_q, nan=0.0), MEAS_QUAT, rows)
    if table.ref_q is not None:
        _check_quaternions(path, np.nan_to_num(table.ref_q, nan=0.0), REF_QUAT, rows)


def write_table(table: PoseTable, path: str | Path, comment: str | None = None) -> None:
    """Write the table as CSV, every float with round-trip precision, after `comment` (one
    line, written after '#', which `read_table` skips); a table `read_table` would refuse (a
    NaN, a pose 1e6 m away, a zero quaternion) is refused instead."""
    _check_writable(table, str(path))
    columns: list[tuple[str, np.ndarray]] = []
    if "id" in table.extras:
        columns.append(("id", table.extras["id"]))
    columns += [(c, table.meas_p[:, i]) for i, c in enumerate(MEAS_POS)]
    columns += [(c, table.meas_q[:, i]) for i, c in enumerate(MEAS_QUAT)]
    columns += [(c, table.ref_p[:, i]) for i, c in enumerate(REF_POS)]
    if table.ref_q is not None:
        columns += [(c, table.ref_q[:, i]) for i, c in enumerate(REF_QUAT)]
    columns += [(c, v) for c, v in table.extras.items() if c != "id"]
    from .safeio import atomic_output

    buffer = io.StringIO()
    writer = csv.writer(buffer)   # the csv module's "\r\n", as RFC 4180 has it

    def line(cells: list[Any]) -> str:
        buffer.seek(0)
        buffer.truncate()
        writer.writerow(cells)
        return protect_comment(buffer.getvalue(), str(cells[0]))

    with atomic_output(path) as handle:
        if comment is not None:
            handle.write(f"{COMMENT} {' '.join(comment.split())}\r\n")
        handle.write(line([c for c, _ in columns]))
        for i in range(table.n):
            handle.write(line([repr(float(v[i])) if isinstance(v[i], (float, np.floating)) else v[i]
                               for _, v in columns]))
