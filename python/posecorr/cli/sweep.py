"""`posecorr sweep`."""
from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

from . import options
from ..safeio import exclusive
from .common import CliError, STORE, Verb, apply_threads, emit, seed_option, threads_option


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", type=Path, nargs="?", help="a paired-pose table (or use --experiment)")
    p.add_argument("--experiment", type=int, choices=(1, 2, 3), help="sweep a simulated experiment")
    p.add_argument("--preset", choices=("reduced", "paper-exp1", "paper-exp2", "paper-exp3"), default="reduced",
                   help="the grid; explicit axes below override it (default: reduced, minutes on 2 cores)")
    p.add_argument("--representations", help="e.g. R,zhou")
    p.add_argument("--activations", help="e.g. tansig,logsig")
    p.add_argument("--trainers", help="e.g. lm,br")
    p.add_argument("--architectures", help="layer sizes, e.g. 10,5-5,20-20-20-20 (#16 = table 1's number 16)")
    p.add_argument("--networks", help="the paper's ARCHITECTURE/ALGORITHM labels, e.g. 16/2,14/2,(8-8)/adam; "
                                      "replace --architectures x --trainers")
    p.add_argument("--no-pmc", action="store_true", help="leave PMC out of the grid")
    p.add_argument("--no-mlp", action="store_true", help="leave the MLPs out of the grid")
    p.add_argument("--epochs", type=options.integer(1, 1_000_000), help="epoch cap of every MLP")
    p.add_argument("--repeats", type=options.integer(1, 10_000), default=30,
                   help="runs of each model, each on a fresh random 70/15 split (default: 30)")
    p.add_argument("--store", type=Path, help="results store (JSON lines), always written; an interrupted sweep resumes from it "
                        "(default: DATA.sweep.jsonl beside the data, or sweep-expN-seedS.jsonl in the working "
                        "folder for --experiment N)")
    p.add_argument("--workers", type=options.WORKERS, default=None,
                   help="local worker processes (default 2, or 1 on a one-core machine; at most the cores)")
    threads_option(p, "per worker process")
    p.add_argument("--ray", metavar="ADDRESS",
                   help="run on a Ray cluster instead: its head's HOST:PORT, 'auto' (the cluster this machine "
                        "belongs to) or ray://HOST:PORT (Ray Client)")
    p.add_argument("--comparisons", action="store_true", help="also print table A1 (pairwise comparisons)")
    p.add_argument("--all-configs", action="store_true",
                   help="also list every configuration, not only the best network per representation and activation")
    seed_option(p)


def run(args: argparse.Namespace) -> None:
    from ..train.protocol import PRESET_TABLES, build_grid, run_sweep

    if args.no_pmc and args.no_mlp:
        raise CliError("--no-pmc with --no-mlp leaves nothing to sweep")
    for arch in (args.architectures or "").split(","):
        if arch.strip() and not arch.strip().startswith("#"):
            options.layer_sizes(arch, "--architectures")
    # Said when the work starts, so that a command refused below still ends in one line.
    requested = args.workers
    capped = requested is not None and requested > options.cores()
    args.workers = min(requested or 2, options.cores())
    threads = apply_threads(args, workers=args.workers)
    if (args.experiment is None) == (args.data is None):
        raise CliError("give either --experiment N or a DATA.csv")
    if args.data is not None:
        from ..data import read_table

        table = read_table(args.data)
        default_store = args.data.with_name(args.data.name + ".sweep.jsonl")
    else:
        from ..simulate import simulate

        table = simulate(args.experiment, seed=args.seed).table
        default_store = Path(f"sweep-exp{args.experiment}-seed{args.seed}.jsonl")
    split = lambda text: None if text is None else [x.strip() for x in text.split(",") if x.strip()]  # noqa: E731
    grid_options = {"epochs": args.epochs} if args.epochs is not None else None
    representations = split(args.representations)
    if not table.has_orientation:
        representations = ["pos"]
    configs = build_grid(args.preset, representations=representations, activations=split(args.activations),
                         trainers=split(args.trainers), architectures=split(args.architectures),
                         networks=split(args.networks), include_pmc=not args.no_pmc, include_mlp=not args.no_mlp,
                         options=grid_options)
    store = args.store or default_store
    _check_store(store)
    if capped:
        print(f"sweep: --workers {requested} capped at the {options.cores()} cores of this machine", file=sys.stderr)
    # stdout carries the verb's result alone: what a Ray cluster prints while it works (a node
    # lost, a run retried) goes to stderr with the progress bar.
    with exclusive(store), contextlib.redirect_stdout(sys.stderr):
        result = run_sweep(table, configs, repeats=args.repeats, store=store,
                           workers=args.workers, ray_address=args.ray, seed=args.seed, progress=not args.json,
                           threads=threads)
    emit(args, result.to_json(), lambda: result.format(comparisons=args.comparisons, all_configs=args.all_configs,
                                                        table=PRESET_TABLES.get(args.preset)))


def _check_store(path: Path) -> None:
    """An existing store must read as one (its first line a run's record): anything else
    (a model, a table given by mistake) is refused before a byte is appended to it."""
    import json

    from ..safeio import open_sidecar

    handle = open_sidecar(path)  # a link or a FIFO is refused, never followed or waited on
    if handle is None:
        return
    with handle:
        first = handle.readline(1 << 16)
    if not first:
        return
    try:
        row = json.loads(first)
    except ValueError:
        row = None
    if not (isinstance(row, dict) and "key" in row and "repeat" in row):
        raise CliError(f"{path}: exists and is not a sweep store (its first line is not a run's record); "
                       "refusing to append to it (choose another --store)")


VERB = Verb(
    help="the paper's protocol: repeats x configurations, tables 2-4, Friedman, tier list",
    rank=6,
    needs="train",
    outputs={"store": STORE},
    tables=("data",),
    add_arguments=add_arguments,
    run=run,
)
