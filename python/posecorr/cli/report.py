"""`posecorr report`."""
from __future__ import annotations

import argparse
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .common import (PAGE, CliError, Verb, backend_option, check_effect_files, diagnosis_options, diagnosis_workers,
                     effect_file_option, effect_names, given, effects_help, emit, model_effect_names, output_option,
                     progress, read_data, station_pose_of, station_pose_option)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", type=Path, help="the paired-pose table (CSV) the model is judged on")
    p.add_argument("--model", type=Path, required=True,
                   help="the exported model (ONNX) to judge (`posecorr fit DATA -o MODEL` writes one: the best "
                        "rigid fit where nothing it tries beats that)")
    output_option(p, help="the HTML page to write")
    p.add_argument("--effects", help=effects_help("the model's effects for the diagnosis (default: from the model "
                                                  "file)"))
    effect_file_option(p)
    station_pose_option(p, "the model's (its metadata station_pose), else the paper's station")
    p.add_argument("--no-diagnosis", action="store_true", help="skip the (slower) diagnosis section")
    backend_option(p)
    diagnosis_options(p)


def run(args: argparse.Namespace) -> None:
    from ..analysis.comparison import compare
    from ..analysis.interpretation import model_effects, takeaway
    from ..analysis.ledger import entry_for_model, ledger_path, of_table, read_ledger
    from ..analysis.page import write_report
    from ..controller.apply import correct_table, refuse_missing_time
    from ..controller.onnx_meta import read_info
    from ..controller.runtime import Corrector
    from ..data import require_rows
    from ..train.pipeline import check_outliers
    from ..ingest.pipeline import segments_path
    from ..safeio import check_sidecar, open_sidecar, warn
    from ..textui import counted

    for sidecar in (ledger_path(args.data), segments_path(args.data)):
        check_sidecar(sidecar)  # a link or a FIFO refused before the work, not after it
    table = read_data(args)   # its --effect-file first: --effects may name that file's effects
    _refuse_diagnosis_options(args)
    asked = effect_names(args.effects) if args.effects is not None else None   # its fault before the work
    require_rows(table, 3, "a report (its baseline is the best rigid fit)", outliers=check_outliers)
    info = read_info(args.model)
    check_effect_files(args.model, info)
    table.station_pose = station_pose_of(args, args.model, info)
    if asked is None and not args.no_diagnosis:
        asked = model_effect_names(args.model, info)   # one its --effect-file defines named now, not after the work
    corrector = Corrector(args.model, backend=args.backend)
    refuse_missing_time(corrector, args.model, table.path, table.time() is not None)
    corrected = correct_table(corrector, args.model, table)
    records = read_ledger(args.data)
    # the model's own line wherever it was fitted: compare says why a table is not the fit's
    comparison = compare(table, corrected, entry_for_model(records, args.model), say=progress(args),
                         model_info=info)
    ledger, elsewhere = of_table(records, table)
    if elsewhere:
        warn(f"{ledger_path(args.data)}: {counted(elsewhere, 'fit')} of another table under this name (other poses: "
             "the file was replaced, or the ledger copied, since) left out of the history")
    diagnosis, no_diagnosis = (None, None) if args.no_diagnosis else _diagnosis(args, table, asked, corrected)
    segments = None
    handle = open_sidecar(segments_path(args.data))
    if handle is not None:
        with handle:
            segments = json.loads(handle.read())
    path = write_report(args.output, table, corrected, info, diagnosis, ledger, segments=segments,
                        comparison=comparison, no_diagnosis=no_diagnosis)
    summary = comparison.to_json()
    # the held parameters the page shows, in fit --json's layout ({} when none; metadata that
    # is not a mapping is the author's, shown by neither)
    fixed = dict(info["fixed"]) if isinstance(info.get("fixed"), Mapping) else {}
    emit(args, {"output": str(path), "bytes": path.stat().st_size, **summary, "fixed": fixed,
                "diagnosis": diagnosis, "no_diagnosis": no_diagnosis},
         lambda: (f"{args.data} against {args.model} -> {path} ({path.stat().st_size // 1024} KiB)\n"
                  f"  before: {comparison.baseline}, {'held out alike' if comparison.held_out else 'in-sample'}, "
                  f"rmse_pos {1e3 * summary['baseline']['rmse_pos']:.4g} mm; "
                  f"after: {summary['after']['scored']}, rmse_pos {1e3 * summary['after']['rmse_pos']:.4g} mm"
                  + (f"\n  note: no diagnosis on the page: {no_diagnosis}" if no_diagnosis else "")
                  + (f"\n  diagnosis: {takeaway(diagnosis, model_effects(info, diagnosis))}" if diagnosis else "")))


def _refuse_diagnosis_options(args: argparse.Namespace) -> None:
    """An option of the diagnosis, given with --no-diagnosis, would be ignored: refused."""
    if not args.no_diagnosis:
        return
    if args.effects is not None:
        raise CliError("--effects names the model's effects for the diagnosis, which --no-diagnosis leaves out")
    if args.workers is not None:
        raise CliError("--workers sets the diagnosis's processes, which --no-diagnosis leaves out")
    if given(args, "folds"):    # the model's own held-out test keeps its fit's folds
        raise CliError("--cv sets the diagnosis's folds, which --no-diagnosis leaves out")


# From this many poses the diagnosis takes about half a minute or more: 300 of the paper's
# Experiment II took 22 s, 600 took 103 s (docs/guides/loop.md), against 3 s for a 50-pose session.
LONG_DIAGNOSIS_POSES = 300


def _diagnosis(args: argparse.Namespace, table: Any, asked: list[str], corrected: Any) -> tuple[Any, str | None]:
    """(the diagnosis, None), or (None, why there is none): the page is still worth having
    without it."""
    from ..analysis.diagnose import diagnose, require_diagnosable

    try:
        require_diagnosable(table, args.folds)
    except ValueError as error:
        return None, getattr(error, "message", str(error))
    say = progress(args)
    workers = diagnosis_workers(args)
    if table.n >= LONG_DIAGNOSIS_POSES:
        say(f"the diagnosis of {table.n} poses refits each candidate on every fold, in {workers} "
            f"{'process' if workers == 1 else 'processes'} (--workers): minutes on a table this size "
            "(--no-diagnosis leaves it out)")
    return diagnose(table, asked, folds=args.folds, seed=args.seed, model_corrected=corrected, progress=say,
                    workers=workers), None


VERB = Verb(
    help="an HTML page: measurements against a model, where it fails, what is missing",
    rank=5,
    needs="train",
    outputs={"output": PAGE},
    models=("model",),
    tables=("data",),
    add_arguments=add_arguments,
    run=run,
)
