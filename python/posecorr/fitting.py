"""The files a fit leaves, as `posecorr fit` writes them and as Python callers can.

`write_fit` exports the fitted model with its training box and the parity check on its
training poses, has the written graph itself score the held-out poses (so the figures
printed and recorded are those of the file, float32, not of the Python estimator), saves
the estimator when asked (`saved`: signed, for `posecorr export`) and appends the ledger
line beside the data; all or nothing (`safeio.staged_outputs`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .metrics import named_block


@dataclass
class FitFiles:
    """What `write_fit` wrote: the export's summary and the ledger record."""

    exported: dict[str, Any]
    ledger_entry: dict[str, Any]


def training_fit(report: Any, table: Any) -> Any:
    """The fitted estimator with the poses it was trained on (for parity and `--save`), its
    held-out poses and the figures its file states."""
    from .controller.digest import data_digest, set_digest
    from .saved import SavedFit

    rows = report.train_index
    times = table.time()
    # the whole table a fit with a test split read, in its order and in any
    split = ((table.measured, table.reference, times if getattr(report.model, "needs_time", False) else None)
             if report.test_index is not None else None)
    return SavedFit(report.model, table.measured[rows], table.reference[rows],
                    None if times is None else times[rows], heldout=heldout_poses(report, table),
                    test_metrics={report.heldout_kind: report.heldout, "raw": report.raw,
                                  # the floor: the best rigid fit, scored alike
                                  "rigid": named_block(report.baseline_name, report.baseline)},
                    table_digest=data_digest(*split) if split else None,
                    table_set_digest=set_digest(*split) if split else None)


def heldout_poses(report: Any, table: Any) -> tuple | None:
    """(measured, reference, t, with_rotation) of the test split, None under cross-validation."""
    rows = report.test_index
    if rows is None:
        return None
    times = table.time()
    return (table.measured[rows], table.reference[rows], None if times is None else times[rows],
            table.has_orientation)


def export_fit(report: Any, table: Any, output: str | Path, write: Any = None) -> dict[str, Any]:
    """Writes report.model to output (`write` as in `export.to_onnx`); report.heldout becomes
    the written graph's figures."""
    exported = report.model.to_onnx(output, write=write, **training_fit(report, table).export_arguments())
    if exported.get("heldout_metrics"):
        report.heldout = exported["heldout_metrics"]["test"]
    return exported


# A model whose largest correction on the poses the runtimes accept (any orientation,
# positions in input_bounds) is this many times its largest on the training poses, and above
# EXTRAPOLATION_MIN_M, extrapolates: a sub-millimetre model that moves a pose by 5 mm is no
# hazard.
EXTRAPOLATION_FACTOR = 10.0
EXTRAPOLATION_MIN_M = 0.01


def extrapolation_note(exported: dict[str, Any]) -> str | None:
    """Words for a model that moves poses unlike its training poses far more than it moves
    those (a core fitted on orientations of one axis, turned about another), which the
    runtimes accept: they refuse positions outside input_bounds, not orientations."""
    largest = exported.get("largest_correction")
    if not largest:
        return None
    training, accepted = largest["training"][0], largest["accepted"][0]
    if accepted <= max(EXTRAPOLATION_FACTOR * training, EXTRAPOLATION_MIN_M):
        return None
    against = (f"{accepted / training:.0f} times its largest correction of the training poses "
               f"({1e3 * training:.3g} mm)" if training > 0 else "where it leaves the training poses as they are")
    return (f"on poses unlike its training poses (any orientation, positions in input_bounds) this model moves "
            f"positions by up to {accepted:.3g} m, {against}: it extrapolates, and the runtimes accept those "
            "orientations; run it near the orientations it was fitted on")


def write_fit(report: Any, table: Any, data_path: str | Path, output: str | Path, effects: list[str],
              save: str | Path | None = None, spec: Any = None, seed: int | None = None) -> FitFiles:
    """The model file, the saved estimator (when `save`) and the ledger line, all or none: the files reach the disk, then the ledger line,
    then the files take their names. `spec` (the requested `ModelSpec`) and `seed` let
    `posecorr report` recompute the held-out predictions (`ledger_fit_entry`)."""
    from .analysis.ledger import append_entry
    from .safeio import staged_outputs
    from .saved import save as save_fit

    with staged_outputs() as stage:
        written: dict[str, bytes] = {}

        def write(path: str | Path, data: bytes) -> None:
            written[str(path)] = bytes(data)
            stage.write_bytes(path, data)

        saved = training_fit(report, table)    # before export_fit states the graph's own test figures
        exported = export_fit(report, table, output, write=write)
        if save is not None:
            save_fit(save, saved, write=stage.write_bytes)
        # the model as seen from the data and its ledger: a fit run from elsewhere wrote its own
        # working directory's path, which the report, run from the data's, showed as another file
        seen = os.path.relpath(os.path.abspath(output), os.path.dirname(os.path.abspath(data_path)))
        entry = ledger_fit_entry(report, table, seen, effects, written.get(str(output), b""), spec, seed)
        stage.before_replacing(lambda: entry.update(append_entry(data_path, entry)))
    return FitFiles(exported, entry)


def ledger_fit_entry(report: Any, table: Any, output: str | Path, effects: list[str], model_bytes: bytes,
                     spec: Any = None, seed: int | None = None) -> dict[str, Any]:
    """The ledger line of a fit: what it scored (raw, the held-out block, the best rigid fit on
    the same poses) and what a report needs to tell the model file apart and to rebuild the
    held-out predictions: the file's SHA-256, the plan, the seed, the table's size and
    digests, its rows' ranks (the table reordered since is put back in this order), the spec
    and the candidate chosen (a rigid variant when the fit fell back)."""
    import dataclasses
    import hashlib

    from .analysis.ledger import ledger_set_digest, ledger_table_digest, row_ranks

    info = report.model.export_info()
    entry: dict[str, Any] = {"model": str(output), "effects": effects, "method": info.get("method"),
                             "representation": info.get("representation"), "raw": report.raw,
                             report.heldout_kind: report.heldout,
                             "baseline": named_block(report.baseline_name, report.baseline),
                             "model_sha256": hashlib.sha256(model_bytes).hexdigest() if model_bytes else None,
                             "n": int(table.n), "table_digest": ledger_table_digest(table),
                             # the same table in another order of rows, and the way back to this one
                             "table_set_digest": ledger_set_digest(table), "row_ranks": row_ranks(table),
                             "plan": str(report.plan), "chosen": report.chosen,
                             "fell_back": bool(report.fell_back), "rigid": report.model.rigid or None}
    if table.station_pose is not None:
        entry["station_pose"] = table.station_pose
    if report.asked is not None:
        entry["asked"] = report.asked
    if seed is not None:
        entry["seed"] = int(seed)
    if spec is not None:
        entry["spec"] = {f.name: getattr(spec, f.name) for f in dataclasses.fields(spec)}
    return entry


__all__ = ["FitFiles", "export_fit", "heldout_poses", "ledger_fit_entry", "training_fit", "write_fit"]
