"""`posecorr apply`."""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import TABLE, Verb, allow_arguments, allow_options, backend_option, emit, output_option


# where a model's stated held-out figures come from (its test_metrics' key)
HELD_OUT_SOURCES = {"cv": "the fit's cross-validation", "test": "the fit's test split"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path, help="the exported model (ONNX)")
    p.add_argument("input", type=Path, help="the table (CSV) whose meas_* poses to correct; ref_* columns optional")
    output_option(p, help="the CSV to write: the input's columns, then corr_x..corr_qz")
    backend_option(p)
    allow_options(p)
    p.add_argument("--keep-going", action="store_true",
                   help="write a pose the model refuses (outside its box, or where tracking was lost: a zero "
                        "measured quaternion, a measured cell empty or nan) as nan and go on, counting them, instead "
                        "of stopping at the first (default: stop); any other cell that is no number is the table's "
                        "fault and stops it all the same")


def run(args: argparse.Namespace) -> None:
    from ..controller.apply import apply_file

    payload = apply_file(args.model, args.input, args.output, backend=args.backend, keep_going=args.keep_going,
                         **allow_arguments(args))

    def text() -> str:
        from ..metrics import block_name
        from ..textui import METRIC_HEADERS, counted, metrics_rows, table as fmt_table

        refused = payload["refused"]
        done = (f"{payload['n'] - refused['count']} of {counted(payload['n'], 'pose')}" if refused["count"]
                else counted(payload["n"], "pose"))
        head = (f"{done} corrected with {args.model} ({args.backend}) -> {args.output} "
                f"(columns corr_x..corr_qz beside the raw meas_*)")
        if refused["count"]:
            head += (f"\n{counted(refused['count'], 'pose')} refused by the model, written as nan "
                     f"({_rows_words(refused)}); the metrics are over the others; the first: {refused['first']}")
        head += _turned_words(args.model.name, payload["beyond_training_orientations"])
        if payload["raw"] is None:
            return head + "\nno ref_* columns: no metrics"
        in_sample, held, fitted = payload["in_sample"], payload["held_out"], payload["fitted_on"]
        label = {"training": "corrected (in-sample)", "table": "corrected (the fit's table)",
                 "training-reordered": "corrected (in-sample)",
                 "table-reordered": "corrected (the fit's table)"}.get(fitted, "corrected")
        blocks = {"raw": payload["raw"], label: payload["corrected"]}
        if held is not None:
            blocks[f"held out ({HELD_OUT_SOURCES[held['source']]})"] = held
            if held["rigid"] is not None:   # the floor the fit measured itself against
                blocks[f"the best rigid fit ({block_name(held['rigid'])}), held out alike"] = held["rigid"]
        fitted_words = {
            "training": "was fitted on these poses (its training_data_digest): corrected is in-sample",
            "table": ("was fitted on this table's training rows, its test split held out (its fitted_table_digest): "
                      "corrected is mostly in-sample"),
            "training-reordered": ("was fitted on these poses, in another order (its training_set_digest): corrected "
                                   "is in-sample"),
            "table-reordered": ("was fitted on this table's training rows, its test split held out, the table in "
                                "another order (its fitted_table_set_digest): corrected is mostly in-sample")}
        note = (f"\nnote: {args.model.name} {fitted_words[fitted]}"
                + ("; held out is the fit's, as the model states it" if held else "")) if in_sample else ""
        if payload["unregistered"]:
            from ..metrics import UNREGISTERED_FACTOR, UNREGISTERED_MIN_M

            blocks["Kabsch fit of the positions, same poses (in-sample)"] = {"rmse_pos": payload["kabsch_rmse_pos"]}
            note += ("\nnote: the frames are unregistered (raw rmse_pos above "
                     f"{UNREGISTERED_FACTOR:g}x a Kabsch fit's and {UNREGISTERED_MIN_M * 1e3:g} mm): raw measures "
                     "their offset, not the tracker, and no improvement over it is given; `posecorr report` sets "
                     "the corrected poses against the best rigid fit")
        return head + "\n" + fmt_table(METRIC_HEADERS, metrics_rows(blocks)) + note

    emit(args, payload, text)


def _rows_words(counted_rows: dict) -> str:
    """'row 6', 'rows 2, 3 and 8 more' of a {"count", "rows": the first few} record."""
    from ..textui import first_few

    count, rows = counted_rows["count"], counted_rows["rows"]
    return f"{'row' if count == 1 else 'rows'} {first_few(rows, len(rows), count)}"


def _turned_words(model: str, beyond: dict | None) -> str:
    """The note on poses turned away from every orientation the model was fitted on, or ""."""
    if not beyond or not beyond["count"]:
        return ""
    import math

    from ..textui import counted

    one = beyond["count"] == 1
    return (f"\nnote: {counted(beyond['count'], 'pose')} ({_rows_words(beyond)}) "
            f"{'lies' if one else 'lie up to'} {math.degrees(beyond['largest_rad']):.3g} deg beyond "
            f"the orientations {model} was fitted on (within {math.degrees(beyond['within_rad']):.3g} deg of their "
            f"mean; counted from {math.degrees(beyond['margin_rad']):.3g} deg beyond): its core reads the "
            "orientation and there it extrapolates (corrected all the same; a fit on poses that turn as "
            f"{'this one does' if one else 'these do'} would know)")


VERB = Verb(
    help="correct the measured poses of a table with a model",
    rank=10,
    outputs={"output": TABLE},
    models=("model",),
    tables=("input",),
    add_arguments=add_arguments,
    run=run,
)
