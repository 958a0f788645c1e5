"""`posecorr apply`: correct the measured poses of a table with an exported model, streaming.

The table is read, corrected and written in chunks (`data.TableReader`), so memory stays
flat for any number of rows. The output holds every input column as read, then the
corrected pose as ``corr_x, corr_y, corr_z, corr_qw, corr_qx, corr_qy, corr_qz``: the raw
``meas_*`` stay beside it. A measurement-only table (no ``ref_*`` columns, e.g. a
demonstration recording) is corrected the same way; metrics (raw and corrected RMSEs,
improvement over raw unless the frames are unregistered, `_Kabsch`) are computed only when
the table has references, and where the table is the one the model was fitted on (its
`training_data_digest`, or its rows in another order: `training_set_digest`), they are marked
in-sample and the fit's held-out figures from the model's metadata go beside them. The output is written
through `safeio.atomic_output`: an interrupted apply leaves the previous file.
"""
from __future__ import annotations

import csv
import io
import os
from typing import Any

import numpy as np

from .. import coverage
from ..data import (CHUNK_ROWS, MEAS_POS, MEAS_QUAT, REF_POS, REF_QUAT, PoseTable, TableError, TableReader,
                    protect_comment)
from ..metrics import METRIC_KEYS, block_name, frames_unregistered, metric_block, named_block, pose_errors
from ..registration import rotation_of_covariance
from ..safeio import atomic_output, check_output
from .checks import COLUMNS, QUATERNION, TIME_INPUT
from .digest import FITTED_DIGESTS, FITTED_SET_DIGESTS, fitted_on
from .onnx_meta import decode_value, stated_metrics, stated_rigid
from .runtime import Corrector, PoseCorrError

CORR_COLUMNS = tuple("corr_" + name.split("_", 1)[1] for name in MEAS_POS + MEAS_QUAT)


# The model computes in float32: nine significant digits carry all of it.
_CORR_FORMAT = ",%.9g,%.9g,%.9g,%.9g,%.9g,%.9g,%.9g\n"


def _input_column(clause: str, has_times: bool) -> str | None:
    """The table column an input check's clause names (`checks`, run.c: "y = 5.000 m is
    outside ...", "the quaternion qw, qx, qy, qz has norm ...", "t is not finite"); None for
    an output check."""
    names = MEAS_POS + MEAS_QUAT
    if "output 'corrected'" in clause:
        return None
    if clause.startswith(QUATERNION):
        return f"{names[3]}..{names[6]}"
    first = clause.split(" ", 1)[0]
    if first == TIME_INPUT:
        return "t" if has_times else None
    return names[COLUMNS.index(first)] if first in COLUMNS else None


def _pose_by_pose(path: str, model: Any, chunk: Any, measured: np.ndarray, times: np.ndarray | None,
                  corrector: Corrector) -> tuple[np.ndarray, list[TableError]]:
    """A chunk the model refused, corrected pose by pose: (the corrected poses, NaN where
    refused; a TableError for each refused pose). The runtime names a pose within its call
    ("pose 0: CLAUSE", posecorr.h), so alone each is its file's row, named in front with the
    table's column of an input the clause names."""
    corrected, refused = np.full_like(measured, np.nan), []
    for i in range(len(measured)):
        try:
            corrected[i] = corrector.correct(measured[i], t=None if times is None else times[i])
        except PoseCorrError as one:
            status, _, clause = str(one).partition(": pose 0: ")
            text = f"{status}: {clause}" if clause else str(one)
            column = _input_column(clause, times is not None)
            refused.append(TableError(path, f"{os.fspath(model)}: {text}", chunk.row_numbers[i], column))
    return corrected, refused


def _refused_row(path: str, model: Any, chunk: Any, measured: np.ndarray, times: np.ndarray | None,
                 corrector: Corrector, error: PoseCorrError) -> TableError:
    """The first table row of a chunk the model refused (`error`, the whole chunk's)."""
    refused = _pose_by_pose(path, model, chunk, measured, times, corrector)[1]
    return refused[0] if refused else TableError(path, f"{os.fspath(model)}: {error}")


def refused_row_of(path: Any, model: Any, corrector: Corrector, error: PoseCorrError) -> TableError:
    """The row of the table at `path` (and its column) where `corrector` refused a pose it was
    given whole (`error`), found as `apply` finds it, chunk by chunk."""
    with TableReader(path, require_reference=False) as reader:
        for chunk in reader.chunks():
            measured = np.concatenate([chunk.block(MEAS_POS), chunk.block(MEAS_QUAT)], axis=1)
            times = chunk.block(("t",))[:, 0] if corrector.takes_time else None
            try:
                corrector.correct(measured, t=times)
            except PoseCorrError as located:
                return _refused_row(reader.path, model, chunk, measured, times, corrector, located)
    return TableError(os.fspath(path), f"{os.fspath(model)}: {error}")


def correct_table(corrector: Corrector, model: Any, table: PoseTable) -> np.ndarray:
    """The (N, 7) measured poses of a table read whole (`report`, `diagnose --model`)
    corrected in one call; a pose the model refuses is named by its file's row and column, as
    apply names it, not by its place in the call."""
    try:
        return corrector.correct(table.measured, t=table.time())
    except PoseCorrError as error:
        if table.path is None:
            raise
        raise refused_row_of(table.path, model, corrector, error) from None


def _line_writer(width: int, ending: str = "\n"):
    """Cells as read -> one CSV line (no newline): joined directly when no cell needs
    quoting (the common case, many times faster), through the csv module otherwise. `ending`:
    the file's line ending, which the output's newline translation writes for each "\\n"; a
    line break inside a quoted cell, read with that ending, is given back as "\\n"."""
    buffer = io.StringIO()
    # "\n" as the terminator: the csv module quotes a cell holding its terminator's
    # characters, and with "" it would leave a line break inside a cell unquoted.
    writer = csv.writer(buffer, lineterminator="\n")

    def line(cells: list[str]) -> str:
        text = ",".join(cells)
        if text.count(",") == width - 1 and '"' not in text and "\n" not in text and "\r" not in text:
            return protect_comment(text, cells[0])
        buffer.seek(0)
        buffer.truncate()
        writer.writerow([cell.replace(ending, "\n") for cell in cells])
        return protect_comment(buffer.getvalue()[:-1], cells[0])

    return line


def _with_comments(lines: list[str], comments: list[tuple[int, str]]) -> str:
    """A chunk's written lines with its comment lines back where they stood."""
    out, done = [], 0
    for before, text in comments:
        out += lines[done:before] + [text + "\n"]
        done = before
    return "".join(out + lines[done:])


class _RmseSums:
    """Running sums of squared errors, so that RMSEs over chunks equal `pose_metrics` over all."""

    def __init__(self, with_rotation: bool) -> None:
        self.with_rotation = with_rotation
        self.n = 0
        self.sums = dict.fromkeys(METRIC_KEYS, 0.0)

    def add(self, reference: np.ndarray, estimate: np.ndarray) -> None:
        dp, dr = pose_errors(reference, estimate, self.with_rotation)
        self.n += len(dp)
        self.sums["rmse_pos"] += float(np.sum(dp * dp))
        if dr is not None:
            self.sums["rmse_rot"] += float(np.sum(dr * dr))
            dp = dp + dr
        self.sums["rmse_total"] += float(np.sum(dp * dp))

    def metrics(self) -> dict[str, float | None]:
        out: dict[str, float | None] = {k: float(np.sqrt(v / self.n)) for k, v in self.sums.items()}
        if not self.with_rotation:
            out["rmse_rot"] = None
        return out


# The refused rows `apply --keep-going` names (it counts them all).
REFUSED_SHOWN = 10

class _Refused:
    """The poses `apply --keep-going` wrote as nan: all counted, the first REFUSED_SHOWN rows
    and the first message kept (a recording far outside the box keeps memory flat)."""

    def __init__(self) -> None:
        self.count, self.rows, self.first = 0, [], None

    def add(self, errors: list[TableError]) -> None:
        self.count += len(errors)
        self.rows += [e.row for e in errors[:REFUSED_SHOWN - len(self.rows)]]
        self.first = self.first or (errors[0] if errors else None)

    def record(self) -> dict[str, Any]:
        return {"count": self.count, "rows": self.rows, "first": None if self.first is None else str(self.first)}


# The rows of a table `apply` keeps to tell whether the model was fitted on it: a session's
# table, not a recording's (a table longer than this is not the one a fit saw whole).
FITTED_ON_MAX_ROWS = 100_000


class _FittedOn:
    """Whether a table's poses are the ones the model was fitted on: the digest of its
    measured and reference arrays (as a fit reads them) against `training_data_digest`, or,
    for a fit with a test split, against `fitted_table_digest`, the whole table it split; in
    any order of the rows, against their `training_set_digest` and `fitted_table_set_digest`."""

    def __init__(self, metadata: dict[str, str]):
        self.digests = {key: decode_value(metadata.get(key, "null"))
                        for key in (*FITTED_DIGESTS.values(), *FITTED_SET_DIGESTS.values())}
        self.metrics = decode_value(metadata.get("test_metrics", "null"))
        self.blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] | None = (
            [] if any(self.digests.values()) else None)
        self.rows = 0

    def add(self, measured: np.ndarray, reference: np.ndarray, t: np.ndarray | None) -> None:
        if self.blocks is None:
            return
        self.rows += len(measured)
        if self.rows > FITTED_ON_MAX_ROWS:   # a recording, not a session: memory stays flat
            self.blocks = None
        else:   # each chunk's arrays are its own (concatenated from its cells), kept as they are
            self.blocks.append((measured, reference, t))

    def verdict(self) -> str | bool | None:
        """"training": fitted on these poses; "table": these are the table the fit split (its
        training rows and the test split it held out); either with "-reordered" where they are
        those poses in another order; False: neither; None: not known (no digest in the model,
        or too many rows to keep)."""
        if not self.blocks:
            return None
        measured = np.concatenate([m for m, _, _ in self.blocks])
        reference = np.concatenate([r for _, r, _ in self.blocks])
        t = None if self.blocks[0][2] is None else np.concatenate([t for _, _, t in self.blocks])
        return fitted_on(measured, reference, self.digests, t) or False

    def held_out(self) -> dict[str, Any] | None:
        """The fit's held-out figures (its cross-validation's or its test split's), as the
        model states them."""
        stated = stated_metrics({"test_metrics": self.metrics})
        if stated is None:
            return None
        kind, figures, _ = stated
        rigid = stated_rigid({"test_metrics": self.metrics})
        return {"source": kind, **{k: figures.get(k) for k in ("rmse_pos", "rmse_rot", "rmse_total")},
                "rigid": None if rigid is None else named_block(block_name(rigid), {k: rigid.get(k) for k in METRIC_KEYS})}


class _Kabsch:
    """Whether the table's frames are unregistered, which makes raw measure their offset, not
    the tracker (`metrics.RULE`): raw rmse_pos against a Kabsch fit of the measured positions
    onto the reference's, the rigid fit the controller side can do with numpy alone. A fit
    with a lever arm does better, never worse: raw above the rule's factor times the Kabsch
    fit's is above it for the best rigid fit too, so the verdict is never wrongly
    "unregistered". Its figure needs only sums of the positions (about the first pose, so
    that metres of offset cost no digits of the millimetres), so memory stays flat for any
    length."""

    def __init__(self) -> None:
        self.n = 0
        self.origin: tuple[np.ndarray, np.ndarray] | None = None
        self.sums = {"m": np.zeros(3), "r": np.zeros(3), "rm": np.zeros((3, 3)), "mm": 0.0, "rr": 0.0}

    def add(self, measured_p: np.ndarray, reference_p: np.ndarray) -> None:
        if not len(measured_p):
            return
        if self.origin is None:
            self.origin = measured_p[0].copy(), reference_p[0].copy()
        m, r = measured_p - self.origin[0], reference_p - self.origin[1]
        self.n += len(m)
        for key, value in (("m", m.sum(axis=0)), ("r", r.sum(axis=0)), ("rm", r.T @ m),
                           ("mm", float(np.sum(m * m))), ("rr", float(np.sum(r * r)))):
            self.sums[key] = self.sums[key] + value

    def rmse_pos(self) -> float | None:
        """The Kabsch fit's in-sample rmse_pos (None below 3 poses): mean |R m + t - r|^2 is
        var(m) + var(r) - 2 trace(R^T cov) at the best R."""
        if self.n < 3:
            return None
        sums, n = self.sums, self.n
        mean_m, mean_r = sums["m"] / n, sums["r"] / n
        _, aligned = rotation_of_covariance(sums["rm"] / n - np.outer(mean_r, mean_m))
        mse = sums["mm"] / n - mean_m @ mean_m + sums["rr"] / n - mean_r @ mean_r - 2.0 * aligned
        return float(np.sqrt(max(mse, 0.0)))


def refuse_missing_time(corrector: Corrector, model: str | os.PathLike[str], path: Any, has_time: bool,
                        header_row: int | None = None) -> None:
    """TableError where `model` takes each pose's time and the table at `path` has none:
    corrected as at t = 0 (`Corrector.correct`'s default), its time-dependent effects would
    be left out without a word. The error names the header's row (read again if not given)."""
    if corrector.takes_time and not has_time:
        if header_row is None and path is not None:
            with TableReader(path, require_reference=False) as reader:
                header_row = reader.header_row
        raise TableError(path, f"{os.path.basename(os.fspath(model))} takes each pose's time (it models a "
                         "time-dependent effect such as drift), and the table has no such column (seconds since "
                         "the session's start)", header_row, "t")


def _check_header(reader: TableReader, corrector: Corrector, model: str | os.PathLike[str]) -> None:
    """TableError where the table lacks the time the model takes, or already holds a column
    apply writes."""
    refuse_missing_time(corrector, model, reader.path, "t" in reader.header, reader.header_row)
    clash = [c for c in CORR_COLUMNS if c in reader.header]
    if clash:
        raise TableError(reader.path, "column already present: apply writes the corrected pose to "
                         + ", ".join(CORR_COLUMNS) + " (use the raw table as input)", reader.header_row, clash[0])


# A zero measured quaternion refused without --keep-going: the way on (a tracker's "no pose").
KEEP_GOING_FIX = "a tracker that lost tracking writes zeros: --keep-going writes such a pose as nan and goes on"
# A pose the model refuses without --keep-going (outside its box): the way on.
REFUSED_FIX = "--keep-going writes each pose the model refuses as nan and goes on"


def apply_file(model: str | os.PathLike[str], table: str | os.PathLike[str], output: str | os.PathLike[str],
               backend: str = "c", chunk_rows: int = CHUNK_ROWS, allow_unbounded: bool = False,
               allow_unsigned: bool = False, keep_going: bool = False) -> dict[str, Any]:
    """Correct `table` with `model` into `output`; returns {"n", "output", "backend", "reference",
    "raw", "corrected", "in_sample", "fitted_on", "held_out", "unregistered", "kabsch_rmse_pos",
    "refused", "beyond_training_orientations"} (raw / corrected None without reference columns).
    allow_unbounded, allow_unsigned: as `Corrector`'s. A pose the model refuses stops the work
    (TableError naming its row), or with `keep_going` is written as nan and counted in
    "refused" ({"count", "rows": the first REFUSED_SHOWN, "first": its message}); the metrics
    are then over the poses corrected. "fitted_on": `_FittedOn.verdict`;
    "held_out" there: the fit's figures as the model states them, "rigid" the floor's.
    "beyond_training_orientations": `coverage.Beyond.record`, the poses turned away from all
    the model was fitted on (they are corrected all the same)."""
    check_output(output, [model, table])
    corrector = Corrector(model, backend=backend, allow_unbounded=allow_unbounded,
                          allow_unsigned=allow_unsigned)
    n = 0
    with TableReader(table, require_reference=False, measured_checked=not keep_going,
                     zero_fix=KEEP_GOING_FIX) as reader:
        _check_header(reader, corrector, model)
        refused = _Refused()
        scores = _Scores(reader, corrector.metadata) if reader.has_reference else None
        turned = coverage.Beyond(corrector.metadata, REFUSED_SHOWN)
        # "\n" written is the input's line ending on disk: a Windows table stays one
        with atomic_output(output, newline=reader.line_ending) as handle:
            line = _line_writer(len(reader.header), reader.line_ending)
            handle.write("".join(text + "\n" for _, text in reader.preamble) + line(reader.header) + ","
                         + ",".join(CORR_COLUMNS) + "\n")
            for chunk in reader.chunks(chunk_rows):
                measured = np.concatenate([chunk.block(MEAS_POS), chunk.block(MEAS_QUAT)], axis=1)
                # A model with a time input gets the table's t (s since the session's start).
                times = chunk.block(("t",))[:, 0] if corrector.takes_time else None
                try:
                    corrected = corrector.correct(measured, t=times)
                except PoseCorrError as error:
                    if not keep_going:
                        stop = _refused_row(reader.path, model, chunk, measured, times, corrector, error)
                        raise TableError(stop.path, f"{stop.message}; {REFUSED_FIX}", stop.row, stop.column) from None
                    corrected, errors = _pose_by_pose(reader.path, model, chunk, measured, times, corrector)
                    refused.add(errors)
                kept = np.all(np.isfinite(corrected), axis=1)   # the refused poses out of the count and sums
                turned.add(measured[:, 3:7], chunk.row_numbers, kept)
                handle.write(_with_comments([line(row) + (_CORR_FORMAT % tuple(values))
                                             for row, values in zip(chunk.rows, corrected.tolist())], chunk.comments))
                if scores is not None:
                    scores.add(chunk, measured, corrected, kept, times)
                n += len(chunk.rows)
            handle.write("".join(text + "\n" for text in reader.trailing))
            if n == 0:  # inside the block: the previous output stays
                raise TableError(reader.path, "no data rows after the header")
            if refused.count == n:   # a table of nan is no correction: the previous output stays
                raise TableError(reader.path, f"the model refused every pose; the first: {refused.first}")
    return {"n": n, "output": str(output), "backend": backend, **(_no_scores() if scores is None else scores.record()),
            "refused": refused.record(), "beyond_training_orientations": turned.record()}


def _no_scores() -> dict[str, Any]:
    """apply_file's figures of a table without reference columns."""
    return {"reference": False, "columns_added": list(CORR_COLUMNS), "raw": None, "corrected": None,
            "in_sample": None, "fitted_on": None, "held_out": None, "unregistered": None, "kabsch_rmse_pos": None}


class _Scores:
    """apply_file's figures of a table with reference columns, summed chunk by chunk."""

    def __init__(self, reader: TableReader, metadata: dict[str, str]) -> None:
        self.with_rotation = reader.has_ref_orientation
        self.raw, self.corrected = _RmseSums(self.with_rotation), _RmseSums(self.with_rotation)
        self.fitted_on, self.kabsch = _FittedOn(metadata), _Kabsch()

    def add(self, chunk: Any, measured: np.ndarray, corrected: np.ndarray, kept: np.ndarray,
            times: np.ndarray | None) -> None:
        """A chunk's poses; `kept`: those the model corrected (the refused are out of the sums)."""
        q = chunk.block(REF_QUAT) if self.with_rotation else measured[:, 3:7]
        reference = np.concatenate([chunk.block(REF_POS), q], axis=1)
        self.raw.add(reference[kept], measured[kept])
        self.corrected.add(reference[kept], corrected[kept])
        self.kabsch.add(measured[kept, :3], reference[kept, :3])
        self.fitted_on.add(measured, reference, times)

    def record(self) -> dict[str, Any]:
        """{"reference", "columns_added", "raw", "corrected", "in_sample", "fitted_on", "held_out",
        "unregistered" (`metrics.RULE` by `_Kabsch`: True, False, or None where not known),
        "kabsch_rmse_pos" (the Kabsch fit's, m)}. The corrected block's improvements are
        against raw, and None where the frames are unregistered: a ratio to the frames' offset
        says nothing of the model."""
        raw = self.raw.metrics()
        corrected = metric_block(raw, self.corrected.metrics())
        fitted = self.fitted_on.verdict()
        floor = self.kabsch.rmse_pos()
        unregistered = None if floor is None else frames_unregistered(raw, {"rmse_pos": floor})
        if unregistered:
            corrected = {k: (None if k.startswith("improvement_") else v) for k, v in corrected.items()}
        return {"reference": True, "columns_added": list(CORR_COLUMNS), "raw": raw, "corrected": corrected,
                "in_sample": None if fitted is None else bool(fitted), "fitted_on": fitted or None,
                "held_out": self.fitted_on.held_out() if fitted else None, "unregistered": unregistered,
                "kabsch_rmse_pos": floor}
