"""`posecorr demo`."""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import Verb, print_json, apply_threads, seed_option, threads_option


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", type=Path, default=Path("out/demo"))
    seed_option(p)
    threads_option(p)


def run(args: argparse.Namespace) -> None:
    from ..demo import run

    apply_threads(args)
    summary = run(args.output, seed=args.seed, log=(lambda message: None) if args.json else print)
    if args.json:
        print_json(summary)


VERB = Verb(
    help="the main job on the embedded default: simulate Exp III, fit, export, run in C",
    rank=8,
    needs="train",
    outputs=("output",),
    folder_output=True,  # -o is a folder it fills
    add_arguments=add_arguments,
    run=run,
)
