"""The files a fit leaves, as `posecorr fit` writes them and as Python callers can.

`write_fit` exports the fitted model with its training box and the parity check on its
training poses, has the written graph itself score the held-out poses (so the figures
printed and recorded are those of the file, float32, not of the Python estimator), saves
the estimator when asked (`saved`: signed, for `posecorr export`) and appends the ledger
line beside the data; all or nothing (`safeio.staged_outputs`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass
class FitFiles:
    """What `write_fit` wrote: the export's summary and the ledger record."""

    exported: dict[str, Any]
    ledger_entry: dict[str, Any]


def training_fit(report: Any, table: Any) -> Any:
    """The fitted estimator with the poses it was trained on (for parity and `--save`)."""
    from .saved import SavedFit

    rows = report.train_index
    times = table.time()
    return SavedFit(report.model, table.measured[rows], table.reference[rows],
                    None if times is None else times[rows])


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
    fit = training_fit(report, table)
    exported = report.model.to_onnx(output, measured=fit.measured, reference=fit.reference, t=fit.t,
                                    heldout=heldout_poses(report, table), write=write,
                                    test_metrics={report.heldout_kind: report.heldout, "raw": report.raw})
    if exported.get("heldout_metrics"):
        report.heldout = exported["heldout_metrics"]["test"]
    return exported


def write_fit(report: Any, table: Any, data_path: str | Path, output: str | Path, effects: list[str],
              save: str | Path | None = None) -> FitFiles:
    """The model file, the saved estimator (when `save`) and the ledger line, all or none: the files reach the disk, then the ledger line,
    then the files take their names."""
    from .analysis.ledger import append_entry
    from .safeio import staged_outputs
    from .saved import save as save_fit

    with staged_outputs() as stage:
        exported = export_fit(report, table, output, write=stage.write_bytes)
        if save is not None:
            save_fit(save, training_fit(report, table), write=stage.write_bytes)
        info = report.model.export_info()
        entry = {"model": str(output), "effects": effects, "method": info.get("method"),
                 "representation": info.get("representation"), "raw": report.raw,
                 report.heldout_kind: report.heldout}
        stage.before_replacing(lambda: entry.update(append_entry(data_path, entry)))
    return FitFiles(exported, entry)


__all__ = ["FitFiles", "export_fit", "heldout_poses", "training_fit", "write_fit"]
