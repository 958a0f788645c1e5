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

    files = [str(path) for path in args.effect_file or []]
    for path in files:
        load_effect_file(path)  # before parsing: --effects may name the file's effects
    effects = parse_effects_arg(args.effects) if args.effects else None
    result = simulate(args.experiment, effects=effects, seed=args.seed, effect_files=files,
                      base="none" if args.only else "default")
    write_table(result.table, args.output)
    effects_used = result.effects_json()
    payload = {"n": result.table.n, "output": str(args.output), "raw": result.raw,
               "noise_floor": result.noise_floor, "effects": effects_used}

    def text() -> str:
        lines = [f"Experiment {args.experiment}, seed {args.seed}: {result.table.n} poses -> {args.output}",
                 table(METRIC_HEADERS, metrics_rows({"raw": result.raw, "noise floor": result.noise_floor}))]
        lines.append("effects: " + "; ".join(f"{name}={_fmt_params(p)}" for name, p in effects_used.items()))
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


# --- fit / diagnose / export (need the train extra) ------------------------------------

def _load_effect_files(args: argparse.Namespace) -> None:
    from .effects import load_effect_file

    for path in getattr(args, "effect_file", None) or []:
        load_effect_file(path)


def _effect_names(text: str | None) -> list[str]:
    """'station,mount' -> checked names (unknown ones fail naming the catalogue)."""
    from .effects import get_effect

    names = [n.strip() for n in (text or "").split(",") if n.strip()]
    for name in names:
        get_effect(name)
    return names


def _parse_cv(text: str | None) -> int | str | None:
    if text is None or text == "none":
        return None
    if text == "loo":
        return "loo"
    try:
        return int(text)
    except ValueError:
        raise CliError(f"--cv takes none, loo or a number of folds, got {text!r}") from None


def _threads_option(parser: argparse.ArgumentParser, scope: str = "") -> None:
    parser.add_argument("--threads", type=int, metavar="N",
                        help=f"threads for torch and BLAS{' ' + scope if scope else ''} (default: the cores other "
                             "processes leave idle, at least 1)")


def _threads(args: argparse.Namespace, workers: int = 1) -> int:
    """Apply --threads (or the default) before anything trains; one call at the top of a verb."""
    from .threads import set_threads

    return set_threads(args.threads, workers)


def _progress(args: argparse.Namespace) -> Callable[[str], None]:
    quiet = args.json
    return (lambda message: None) if quiet else (lambda message: print(f"  {message}", file=sys.stderr, flush=True))


def cmd_fit(args: argparse.Namespace) -> None:
    from .data import read_table
    from .ledger import append_entry
    from .train.pipeline import fit_table
    from .textui import METRIC_HEADERS, metrics_rows, table as fmt_table

    _threads(args)
    _load_effect_files(args)
    table = read_table(args.data)
    effects = _effect_names(args.effects)
    hidden = tuple(int(h) for h in args.hidden.split(",") if h.strip())
    report = fit_table(table, effects, args.method, args.representation, hidden, args.activation, args.trainer,
                       args.epochs, _parse_cv(args.cv), args.seed, progress=_progress(args))
    key = report.heldout_kind
    exported = report.model.to_onnx(args.output, measured=table.measured[report.train_index],
                                    reference=table.reference[report.train_index],
                                    test_metrics={key: report.heldout, "raw": report.raw})
    info = report.model.export_info()
    effects_json = report.model.physics_.describe() if report.model.physics_ is not None else {}
    payload: dict[str, Any] = {"model": str(args.output), "method": info.get("method"),
                               "chosen": report.chosen, "representation": info.get("representation"),
                               "raw": report.raw, key: report.heldout, "effects": effects_json,
                               "parity": exported.get("parity"), "nodes": exported.get("n_nodes")}
    if report.auto_scores:
        payload["auto_cv_rmse_total"] = report.auto_scores
    if args.save is not None:
        import pickle

        # Kept with the estimator so that `posecorr export` can re-run the parity check.
        report.model.training_measured_ = table.measured[report.train_index]
        report.model.training_reference_ = table.reference[report.train_index]
        with open(args.save, "wb") as handle:
            pickle.dump(report.model, handle)
    append_entry(args.data, {"model": str(args.output), "effects": effects, "method": info.get("method"),
                             "representation": info.get("representation"), "raw": report.raw, key: report.heldout})

    def text() -> str:
        label = "test split" if key == "test" else f"cross-validated ({args.cv})"
        lines = [f"{args.data}: {table.n} poses; effects: {', '.join(effects) or 'none'}; "
                 f"core: {report.chosen}" + (f" (auto: {_fmt_scores(report.auto_scores)})" if report.auto_scores else ""),
                 fmt_table(METRIC_HEADERS + ["improvement"],
                           [row + [imp] for row, imp in zip(
                               metrics_rows({"raw": report.raw, label: report.heldout}),
                               [None, report.heldout.get("improvement_total")])])]
        for name, params in effects_json.items():
            lines.append(f"  {name}: " + "; ".join(f"{p} = {_value_pm(v)}" for p, v in params.items()))
        parity = exported.get("parity") or {}
        lines.append(f"-> {args.output} ({exported['n_nodes']} nodes, {exported['file_size']} bytes"
                     + (f", parity {parity.get('max_pos_m', 0):.1e} m / {parity.get('max_rot_rad', 0):.1e} rad)"
                        if parity else ")"))
        return "\n".join(lines)

    _emit(args, payload, text)


def _fmt_scores(scores: dict[str, float]) -> str:
    return ", ".join(f"{name} {value:.3g}" for name, value in sorted(scores.items(), key=lambda kv: kv[1]))


def _value_pm(pair: list) -> str:
    value, error = pair
    if isinstance(value, list):
        return "[" + ", ".join(f"{v:.4g} ± {e:.1g}" for v, e in zip(value, error)) + "]"
    return f"{value:.4g} ± {error:.1g}"


def cmd_diagnose(args: argparse.Namespace) -> None:
    from .data import read_table
    from .diagnose import diagnose
    from .textui import table as fmt_table

    _threads(args)
    _load_effect_files(args)
    table = read_table(args.data)
    effects = _effect_names(args.effects)
    model_predict = None
    if args.model is not None:
        from .onnx_meta import read_info
        from .runtime import Corrector

        if args.effects is None:
            effects = list(read_info(args.model).get("effects") or [])
        corrector = Corrector(args.model, backend=args.backend)
        model_predict = corrector.correct
    result = diagnose(table, effects, folds=args.folds, seed=args.seed, model_predict=model_predict,
                      progress=_progress(args))

    def text() -> str:
        rows = [[c["rank"], c["effect"], c["score"], c["p_value"], c["cv_rmse_before"], c["cv_rmse_after"],
                 "yes" if c["present"] else "no"] for c in result["candidates"]]
        lines = [f"{args.data}: model effects {', '.join(effects) or 'none'}; "
                 f"cross-validated rmse_total {result['cv_base']['rmse_total']:.4g}",
                 fmt_table(["rank", "effect", "score", "p_value", "cv_rmse_before", "cv_rmse_after", "present"], rows,
                           title="Missing effects (score = mean relative fall of the held-out whitened error)"),
                 f"present = {result['test']}",
                 fmt_table(["feature", "cv R^2"], [[f["feature"], f["r2"]] for f in result["features"]],
                           title="Residual structure by feature (smooth fit, cross-validated)")]
        if result["aliases"]:
            lines.append("cannot be told apart by this data: " + "; ".join(" ~ ".join(p) for p in result["aliases"]))
        present = [c["effect"] for c in result["candidates"] if c["present"]]
        if present:
            lines.append(f"add: --effects {','.join(effects + present)}")
        return "\n".join(lines)

    _emit(args, result, text)


def cmd_sweep(args: argparse.Namespace) -> None:
    from .train.protocol import PRESET_TABLES, build_grid, run_sweep

    threads = _threads(args, workers=args.workers)
    if (args.experiment is None) == (args.data is None):
        raise CliError("give either --experiment N or a DATA.csv")
    if args.data is not None:
        from .data import read_table

        table = read_table(args.data)
        default_store = args.data.with_name(args.data.name + ".sweep.jsonl")
    else:
        from .simulate import simulate

        table = simulate(args.experiment, seed=args.seed).table
        default_store = Path(f"sweep-exp{args.experiment}-seed{args.seed}.jsonl")
    split = lambda text: None if text is None else [x.strip() for x in text.split(",") if x.strip()]  # noqa: E731
    options = {"epochs": args.epochs} if args.epochs is not None else None
    representations = split(args.representations)
    if not table.has_orientation:
        representations = ["pos"]
    configs = build_grid(args.preset, representations=representations, activations=split(args.activations),
                         trainers=split(args.trainers), architectures=split(args.architectures),
                         networks=split(args.networks), include_pmc=not args.no_pmc, include_mlp=not args.no_mlp,
                         options=options)
    result = run_sweep(table, configs, repeats=args.repeats, store=args.store or default_store,
                       workers=args.workers, ray_address=args.ray, seed=args.seed, progress=not args.json,
                       threads=threads)
    _emit(args, result.to_json(), lambda: result.format(comparisons=args.comparisons, all_configs=args.all_configs,
                                                        table=PRESET_TABLES.get(args.preset)))


def cmd_export(args: argparse.Namespace) -> None:
    import pickle

    with open(args.estimator, "rb") as handle:
        estimator = pickle.load(handle)
    if not hasattr(estimator, "forward"):
        raise CliError(f"{args.estimator}: not a posecorr estimator (no forward method)")
    exported = estimator.to_onnx(args.output, parity="skip" if args.no_parity else "raise")
    _emit(args, {k: v for k, v in exported.items() if k != "metadata"},
          lambda: f"{args.estimator} -> {args.output} ({exported['n_nodes']} nodes, {exported['file_size']} bytes)")


def cmd_report(args: argparse.Namespace) -> None:
    from .data import read_table
    from .ledger import read_ledger
    from .onnx_meta import read_info
    from .report import write_report
    from .runtime import Corrector

    _threads(args)
    _load_effect_files(args)
    table = read_table(args.data)
    info = read_info(args.model)
    corrected = Corrector(args.model, backend=args.backend).correct(table.measured)
    diagnosis = None
    if not args.no_diagnosis:
        from .diagnose import diagnose

        effects = _effect_names(args.effects) if args.effects is not None else list(info.get("effects") or [])
        diagnosis = diagnose(table, effects, folds=args.folds, seed=args.seed,
                             model_predict=lambda measured: corrected, progress=_progress(args))
    path = write_report(args.output, table, corrected, info, diagnosis, read_ledger(args.data))
    _emit(args, {"report": str(path), "bytes": path.stat().st_size, "diagnosis": diagnosis},
          lambda: f"{args.data} against {args.model} -> {path} ({path.stat().st_size // 1024} KiB)")


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


def cmd_demo(args: argparse.Namespace) -> None:
    from .demo import run

    _threads(args)
    summary = run(args.output, seed=args.seed, log=(lambda message: None) if args.json else print)
    if args.json:
        _print_json(summary)


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

    p = verb("fit", cmd_fit, "fit a correction (physics effects, then PMC/MLP) and export it as ONNX")
    p.add_argument("data", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--effects", help="comma-separated effects of the physics stage, e.g. station,mount")
    p.add_argument("--effect-file", action="append", type=Path, help="a Python file with user effects")
    p.add_argument("--method", choices=("none", "pmc", "mlp", "auto"), default="pmc")
    p.add_argument("--representation", choices=("eaa", "quat", "R", "zhou"), default="zhou",
                   help="orientation representation of the core (position-only tables use position only)")
    p.add_argument("--hidden", default="20,20,20,20", help="MLP hidden layer sizes")
    p.add_argument("--activation", default="tansig",
                   choices=("tansig", "logsig", "radbas", "purelin", "satlin", "softmax", "hardlim", "compet"))
    p.add_argument("--trainer", default="br", help="lm, br, rp, adam, lbfgs, gd, gdm, gda, gdx")
    p.add_argument("--epochs", type=int, default=1000)
    p.add_argument("--cv", default="none", help="none (fixed 15%% test split), loo, or a number of folds")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save", type=Path, help="also pickle the fitted estimator (for `posecorr export`)")
    _threads_option(p)

    p = verb("diagnose", cmd_diagnose, "rank the physical effects the model lacks; show where the residual lives")
    p.add_argument("data", type=Path)
    p.add_argument("--effects", help="the model's effects (default: those of --model, else none)")
    p.add_argument("--model", type=Path, help="an exported model whose residuals to analyse")
    p.add_argument("--backend", choices=("c", "onnxruntime"), default="c")
    p.add_argument("--effect-file", action="append", type=Path, help="a Python file with user effects")
    p.add_argument("--folds", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    _threads_option(p)

    p = verb("report", cmd_report, "an HTML page: measurements against a model, where it fails, what is missing")
    p.add_argument("data", type=Path)
    p.add_argument("--model", type=Path, required=True)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--effects", help="the model's effects for the diagnosis (default: from the model file)")
    p.add_argument("--effect-file", action="append", type=Path, help="a Python file with user effects")
    p.add_argument("--no-diagnosis", action="store_true", help="skip the (slower) diagnosis section")
    p.add_argument("--backend", choices=("c", "onnxruntime"), default="c")
    p.add_argument("--folds", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    _threads_option(p)

    p = verb("sweep", cmd_sweep, "the paper's protocol: repeats x configurations, tables 2-4, Friedman, tier list")
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
    p.add_argument("--no-pmc", action="store_true")
    p.add_argument("--no-mlp", action="store_true")
    p.add_argument("--epochs", type=int, help="epoch cap of every MLP")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--store", type=Path, help="results store (JSON lines); an interrupted sweep resumes from it")
    p.add_argument("--workers", type=int, default=2)
    _threads_option(p, "per worker process")
    p.add_argument("--ray", help="address of a Ray cluster to run on")
    p.add_argument("--comparisons", action="store_true", help="also print table A1 (pairwise comparisons)")
    p.add_argument("--all-configs", action="store_true",
                   help="also list every configuration, not only the best network per representation and activation")
    p.add_argument("--seed", type=int, default=0)

    p = verb("export", cmd_export, "export a pickled fitted estimator to ONNX")
    p.add_argument("estimator", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--no-parity", action="store_true", help="skip the onnxruntime parity check")

    p = verb("demo", cmd_demo, "the main job on the embedded default: simulate Exp III, fit, export, run in C")
    p.add_argument("-o", "--output", type=Path, default=Path("out/demo"))
    p.add_argument("--seed", type=int, default=0)
    _threads_option(p)

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
