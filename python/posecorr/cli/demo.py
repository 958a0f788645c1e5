"""`posecorr demo`."""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import FOLDER, Verb, apply_threads, print_json, seed_option, threads_option


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", type=Path, default=Path("out/demo"),
                   help="the folder to fill with the table, model and C build (default: out/demo)")
    seed_option(p)
    threads_option(p)


def run(args: argparse.Namespace) -> None:
    from ..demo import run

    apply_threads(args)
    summary = run(args.output, seed=args.seed, log=(lambda message: None) if args.json else print)
    if args.json:
        print_json(summary)


VERB = Verb(
    help="simulate the paper's Experiment III; fit PMC, an MLP and a physics pipeline; export them as ONNX, run "
         "them in C and print the paper's table 4 beside theirs",
    rank=8,
    needs="train",
    outputs={"output": FOLDER},
    folder_output=True,  # -o is a folder it fills
    add_arguments=add_arguments,
    run=run,
)
