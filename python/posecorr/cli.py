"""The `posecorr` command line: one entry point, one verb per job, `--json` everywhere.

Verbs import what they need when they run, so the controller-side verbs (`apply`,
`info`, `bench`) work on an install with numpy only. Every anticipated failure (bad table,
bad model file, bad option) ends with a one-line message and exit code 2, never a
traceback.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable

from . import __version__

EXIT_USAGE = 2


class CliError(Exception):
    """A user-facing error: printed as one line, exit code 2."""


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, indent=2, default=_json_default))


def _json_default(value: Any) -> Any:
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _emit(args: argparse.Namespace, payload: dict[str, Any], text: Callable[[], str]) -> None:
    if args.json:
        _print_json(payload)
    else:
        print(text())


# --- simulate --------------------------------------------------------------------------

def cmd_simulate(args: argparse.Namespace) -> None:
    from .data import write_table
    from .effects import load_effect_file, parse_effects_arg
    from .simulate import simulate
    from .textui import METRIC_HEADERS, metrics_rows, table

    for path in args.effect_file or []:
        load_effect_file(path)
    effects = parse_effects_arg(args.effects) if args.effects else None
    result = simulate(args.experiment, effects=effects, seed=args.seed,
                      base="none" if args.only else "default")
    write_table(result.table, args.output)
    payload = {"n": result.table.n, "output": str(args.output), "raw": result.raw,
               "noise_floor": result.noise_floor, "effects": result.effects}

    def text() -> str:
        lines = [f"Experiment {args.experiment}, seed {args.seed}: {result.table.n} poses -> {args.output}",
                 table(METRIC_HEADERS, metrics_rows({"raw": result.raw, "noise floor": result.noise_floor}))]
        lines.append("effects: " + "; ".join(f"{name}={_fmt_params(p)}" for name, p in result.effects.items()))
        return "\n".join(lines)

    _emit(args, payload, text)


def _fmt_params(params: dict[str, Any]) -> str:
    parts = []
    for key, value in params.items():
        if isinstance(value, (list, tuple)):
            parts.append(f"{key}=[{', '.join(f'{v:.4g}' for v in value)}]")
        else:
            parts.append(f"{key}={value:.4g}" if isinstance(value, float) else f"{key}={value}")
    return ", ".join(parts)


# --- info / apply / bench (controller side: numpy only) ---------------------------------

def cmd_info(args: argparse.Namespace) -> None:
    from .onnx_meta import read_info

    info = read_info(args.model)
    _emit(args, info, lambda: "\n".join(f"{k:>22}: {_one_line(v)}" for k, v in info.items()))


def _one_line(value: Any) -> str:
    return json.dumps(value, default=_json_default) if isinstance(value, (dict, list)) else str(value)


def cmd_apply(args: argparse.Namespace) -> None:
    from .data import read_table, write_table
    from .runtime import Corrector

    table = read_table(args.input)
    corrector = Corrector(args.model, backend=args.backend)
    corrected = corrector.correct(table.measured)
    write_table(table.with_measured(corrected), args.output)
    payload: dict[str, Any] = {"n": table.n, "output": str(args.output), "backend": args.backend}
    # The reference columns are passed through, so the table can be scored at once.
    from .metrics import metric_block, pose_metrics

    raw = pose_metrics(table.reference, table.measured, table.has_orientation)
    corr = pose_metrics(table.reference, corrected, table.has_orientation)
    payload.update({"raw": raw, "corrected": metric_block(raw, corr)})

    def text() -> str:
        from .textui import METRIC_HEADERS, metrics_rows, table as fmt_table

        return (f"{table.n} poses corrected with {args.model} ({args.backend}) -> {args.output}\n"
                + fmt_table(METRIC_HEADERS, metrics_rows({"raw": raw, "corrected": corr})))

    _emit(args, payload, text)


def cmd_bench(args: argparse.Namespace) -> None:
    from .latency import bench_model

    result = bench_model(args.model, n_single=args.n, batch=args.batch)

    def text() -> str:
        from .textui import table

        keys = list(result["single_pose_median_us"])
        rows = [[k, result["single_pose_median_us"][k], result["single_pose_p99_us"][k],
                 result["batch_ns_per_pose"][k]] for k in keys]
        return table(["backend", "single median [us]", "single p99 [us]", "batch [ns/pose]"], rows,
                     title=f"{args.model} on {result.get('machine', '?')}")

    _emit(args, result, text)


# --- parser -----------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="posecorr", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"posecorr {__version__}")
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB")

    def verb(name: str, func: Callable[[argparse.Namespace], None], help: str) -> argparse.ArgumentParser:
        p = verbs.add_parser(name, help=help, description=help)
        p.add_argument("--json", action="store_true", help="machine-readable output on stdout")
        p.set_defaults(func=func)
        return p

    p = verb("simulate", cmd_simulate, "simulate a paired-pose table of paper experiment I, II or III")
    p.add_argument("--experiment", type=int, choices=(1, 2, 3), required=True)
    p.add_argument("--effects", help="NAME=V1,V2,...;NAME... override or add effects (values in parameter order)")
    p.add_argument("--only", action="store_true", help="use only the --effects given (plus noise), not the default mix")
    p.add_argument("--effect-file", action="append", type=Path, help="a Python file with user effects")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--output", type=Path, required=True)

    p = verb("info", cmd_info, "print a model file's metadata")
    p.add_argument("model", type=Path)

    p = verb("apply", cmd_apply, "correct the measured poses of a table with a model")
    p.add_argument("model", type=Path)
    p.add_argument("input", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--backend", choices=("c", "onnxruntime"), default="c")

    p = verb("bench", cmd_bench, "single-pose latency and batch throughput, C runtime against the alternatives")
    p.add_argument("model", type=Path)
    p.add_argument("--n", type=int, default=100_000, help="single-pose calls per backend")
    p.add_argument("--batch", type=int, default=10_000, help="poses per batch call")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from .data import TableError

    try:
        args.func(args)
    except (CliError, TableError, FileNotFoundError, ValueError) as exc:
        message = str(exc) or type(exc).__name__
        print(f"posecorr {args.verb}: error: {message}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"posecorr {args.verb}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
