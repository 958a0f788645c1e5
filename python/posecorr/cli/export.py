"""`posecorr export`."""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import MODEL, Verb, emit, output_option


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("estimator", type=Path, help="a fitted estimator saved by `posecorr fit --save`")
    output_option(p, help="the ONNX model to write")
    p.add_argument("--no-parity", action="store_true", help="skip the onnxruntime parity check")


def run(args: argparse.Namespace) -> None:
    from ..saved import load

    fit = load(args.estimator)
    exported = fit.estimator.to_onnx(args.output, parity="skip" if args.no_parity else "raise",
                                     **fit.export_arguments())
    # The JSON of fit's export, in fit --json's words: the file written, its nodes, and the
    # held-out figures it states (its cross-validation's or its test split's).
    payload = {"output": str(args.output), "nodes": exported["n_nodes"], "op_counts": exported["op_counts"],
               "file_size": exported["file_size"], "parity": exported["parity"],
               "test_metrics": exported["metadata"].get("test_metrics")}
    emit(args, payload,
         lambda: f"{args.estimator} -> {args.output} ({exported['n_nodes']} nodes, {exported['file_size']} bytes)")


VERB = Verb(
    help="export an estimator saved by `fit --save` (signed by this account) to ONNX",
    rank=7,
    needs="train",
    outputs={"output": MODEL},
    add_arguments=add_arguments,
    run=run,
)
