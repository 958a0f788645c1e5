"""The `posecorr` command line: one entry point, one verb per job, `--json` everywhere.

Verbs import what they need when they run, so the controller-side verbs (`apply`,
`info`, `bench`) work on an install with numpy only. Every anticipated failure (bad table,
bad model file, bad option, bad output path, a missing optional package) ends with a
one-line message naming the file and exit code 2, never a traceback; SIGTERM and Ctrl-C
end a verb cleanly (exit 143 / 130), and every file is written atomically (`safeio`).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable

from . import __version__
from .jsonable import json_default

EXIT_USAGE = 2


class CliError(Exception):
    """A user-facing error: printed as one line, exit code 2."""


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, indent=2, default=json_default))


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
    if (args.experiment is None) == (not args.session):
        raise CliError("give either --experiment N or --session")
    if args.session:
        if args.recording is not None:
            raise CliError("--recording drives the robot through an experiment's targets: give --experiment N")
        result = _simulate_session(args)
    else:
        result = simulate(args.experiment, effects=effects, seed=args.seed, effect_files=files,
                          base="none" if args.only else "default")
    sim_table, raw, floor = result.table, result.raw, result.noise_floor
    recording = None
    if args.recording is not None:
        from .recording import simulate_recording, table_metrics, write_recording

        recording = simulate_recording(result, n_targets=args.targets, seed=args.seed)
        write_recording(recording, args.recording)
        sim_table = recording.table
        raw, floor = table_metrics(result, sim_table.n)
    write_table(sim_table, args.output)
    effects_used = result.effects_json()
    payload = {"n": sim_table.n, "output": str(args.output), "raw": raw,
               "noise_floor": floor, "effects": effects_used}
    if recording is not None:
        payload["recording"] = {"path": str(args.recording), "joint_samples": len(recording.joints.t),
                                "tracker_samples": len(recording.tracker.t), "clock_offset_s": recording.offset,
                                "duration_s": float(recording.joints.t[-1] - recording.joints.t[0])}

    if result.spec is not None:
        payload["session"] = dict(vars(result.spec))

    def text() -> str:
        what = f"Experiment {args.experiment}" if result.spec is None else _session_words(result.spec)
        lines = [f"{what}, seed {args.seed}: {sim_table.n} poses -> {args.output}",
                 table(METRIC_HEADERS, metrics_rows({"raw": raw, "noise floor": floor}))]
        lines.append("effects: " + "; ".join(f"{name}={_fmt_params(p)}" for name, p in effects_used.items()))
        if recording is not None:
            r = payload["recording"]
            lines.append(f"recording -> {args.recording}: {r['duration_s']:.0f} s, {r['joint_samples']} joint states, "
                         f"{r['tracker_samples']} tracker poses, clock offset {recording.offset:+.3f} s")
        return "\n".join(lines)

    _emit(args, payload, text)


# --- ingest ----------------------------------------------------------------------------

def cmd_ingest(args: argparse.Namespace) -> None:
    from .data import write_table
    from .ingest import IngestOptions, ingest, write_segments
    from .ingest.csvlog import CsvColumns
    from .ingest.pipeline import parse_transform
    from .ingest.segments import StillOptions

    names = lambda text: tuple(n.strip() for n in text.split(",") if n.strip())  # noqa: E731
    options = IngestOptions(
        robot=args.robot, base_link=args.base_link, tip_link=args.tip_link,
        tool=parse_transform(args.tool, "tool"), registration=parse_transform(args.registration, "registration"),
        joints_topic=args.joints, tracker_topic=args.tracker, tracker_frame=args.tracker_frame, stamps=args.stamps,
        joint_names=names(args.joint_names) if args.joint_names else None,
        csv=CsvColumns(args.time_col, names(args.joint_cols), names(args.pose_cols)),
        still=StillOptions(args.still_speed, args.min_still, args.settle, args.gate_mm, args.max_jitter_mm,
                           args.min_samples),
        offset=args.offset, max_offset=args.max_offset, session=args.session)
    result = ingest(args.recording, options)
    write_table(result.table, args.output)
    sidecar = write_segments(result, args.output)
    summary = result.summary()
    payload = {"output": str(args.output), "segments_file": str(sidecar), **summary}

    def text() -> str:
        a = result.alignment
        how = (f"estimated, speed correlation {a.correlation:.3f}" if a.source == "estimated" else "given")
        rates = f"{summary['joint_samples']} joint states"
        if summary["joint_rate_hz"]:
            rates += f" ({summary['joint_rate_hz']:.0f} Hz)"
        rates += f", {summary['tracker_samples']} tracker poses"
        if summary["tracker_rate_hz"]:
            rates += f" ({summary['tracker_rate_hz']:.0f} Hz)"
        lines = [f"{', '.join(map(str, args.recording))}: {rates}",
                 f"clock offset tracker - robot: {a.offset:+.4f} s ({how})",
                 f"{len(result.segments)} still segments: {result.table.n} rows -> {args.output}, "
                 f"{len(result.rejected)} rejected"]
        lines += [f"  rejected segment {s.index} (t {s.start - result.t0:.1f}..{s.end - result.t0:.1f} s): {s.reason}"
                  for s in result.rejected]
        jitter = result.table.extras["jitter_mm"]
        lines.append(f"jitter {jitter.min():.3f}..{jitter.max():.3f} mm; segments -> {sidecar}")
        return "\n".join(lines)

    _emit(args, payload, text)


def _simulate_session(args: argparse.Namespace) -> Any:
    from .simulate import ROBOTS, SPREADS, simulate_session

    if args.effects or args.effect_file or args.only:
        raise CliError("--session draws its own effects (frame, lever arm, noise); --effects, --effect-file "
                       "and --only go with --experiment")
    if args.spread is not None and args.spread not in SPREADS:
        raise CliError(f"--spread takes {', '.join(SPREADS)}, got {args.spread!r}")
    if args.robot is not None and args.robot not in ROBOTS:
        raise CliError(f"--robot takes {', '.join(ROBOTS)}, got {args.robot!r}")
    pin = {"n": args.poses, "spread": args.spread, "unremovable": None if args.unremovable is None
           else args.unremovable / 1000.0, "position_only": True if args.position_only else None,
           "robot": args.robot}
    return simulate_session(args.seed, **{k: v for k, v in pin.items() if v is not None})


def _session_words(spec: Any) -> str:
    parts = [f"realistic session: orientation spread {spec.spread}", f"carried by a {spec.robot}" if spec.robot else "",
             "planar" if spec.planar and not spec.robot else "",
             "position-only reference" if spec.position_only else "",
             f"unremovable error {1000 * spec.unremovable:.0f} mm" if spec.unremovable else "",
             f"tracker frame {spec.offset:.1f} m away, lever arm {1000 * spec.lever:.0f} mm"]
    return "; ".join(p for p in parts if p)


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
    from .analysis.ledger import append_entry
    from .data import read_table
    from .train.pipeline import fit_table
    from .textui import METRIC_HEADERS, metrics_rows, table as fmt_table

    _threads(args)
    _load_effect_files(args)
    table = read_table(args.data)
    effects = _effect_names(args.effects)
    trainer = args.trainer
    if args.network is not None:
        from .train.mlp import parse_network

        hidden, trainer = parse_network(args.network)
    else:
        hidden = tuple(int(h) for h in args.hidden.split(",") if h.strip())
    report = fit_table(table, effects, args.method, args.representation, hidden, args.activation, trainer,
                       args.epochs, _parse_cv(args.cv), args.seed, progress=_progress(args))
    key = report.heldout_kind
    from .export.symbolic import ExportError

    try:
        times = table.time()
        rows = report.test_index
        heldout = None if rows is None else (table.measured[rows], table.reference[rows],
                                             None if times is None else times[rows], table.has_orientation)
        exported = report.model.to_onnx(args.output, measured=table.measured[report.train_index],
                                        reference=table.reference[report.train_index],
                                        t=None if times is None else times[report.train_index],
                                        heldout=heldout, test_metrics={key: report.heldout, "raw": report.raw})
    except ExportError as exc:
        raise CliError(f"{args.output}: the model could not be exported: {exc}") from None
    if exported.get("heldout_metrics"):
        # The test split's figures are those of the file written (float32 graph), not of the
        # Python estimator it came from.
        report.heldout = exported["heldout_metrics"]["test"]
    info = report.model.export_info()
    effects_json = report.model.physics_.describe() if report.model.physics_ is not None else {}
    payload: dict[str, Any] = {"model": str(args.output), "method": info.get("method"),
                               "chosen": report.chosen, "representation": info.get("representation"),
                               "raw": report.raw, key: report.heldout, "effects": effects_json,
                               "parity": exported.get("parity"), "nodes": exported.get("n_nodes")}
    payload.update({"baseline": {"model": report.baseline_name, **report.baseline}, "n_heldout": report.n_heldout,
                    "rigid_rmse_total": report.rigid_scores,
                    "fell_back_to_rigid": report.fell_back, "fixed": report.fixed, "notes": report.notes})
    if report.shrinkage is not None:
        payload["shrinkage"] = report.shrinkage
    if report.model.physics_ is not None:
        payload["spread"] = report.model.physics_.spread_.to_json()
    if report.auto_scores:
        payload["auto_cv_rmse_total"] = report.auto_scores
    if args.save is not None:
        import pickle

        # Kept with the estimator so that `posecorr export` can re-run the parity check.
        report.model.training_measured_ = table.measured[report.train_index]
        report.model.training_reference_ = table.reference[report.train_index]
        if table.time() is not None:
            report.model.training_t_ = table.time()[report.train_index]
        from .safeio import write_bytes

        write_bytes(args.save, pickle.dumps(report.model))
    append_entry(args.data, {"model": str(args.output), "effects": effects, "method": info.get("method"),
                             "representation": info.get("representation"), "raw": report.raw, key: report.heldout})

    def text() -> str:
        label = f"test split ({report.n_heldout})" if key == "test" else f"{report.chosen}, cv {report.cv}"
        lines = [f"{args.data}: {table.n} poses; effects: {', '.join(effects) or 'none'}; "
                 f"model: {report.chosen}" + (f" (auto: {_fmt_scores(report.auto_scores)})" if report.auto_scores else ""),
                 fmt_table(METRIC_HEADERS + ["improvement"],
                           [row + [imp] for row, imp in zip(
                               metrics_rows({"raw": report.raw, label: report.heldout,
                                             f"{report.baseline_name} (floor), same poses": report.baseline}),
                               [None, report.heldout.get("improvement_total"),
                                report.baseline.get("improvement_total")])])]
        lines.append(f"  floor: {report.baseline_name}, the best of the rigid fits on the same poses ("
                     + ", ".join(f"{name} {value:.4g}" for name, value in report.rigid_scores.items())
                     + " rmse_total)")
        if report.shrinkage is not None:
            lines.append(f"  prior strength {report.shrinkage['prior_strength']:g}: "
                         f"{report.shrinkage['effective_params']:.1f} effective parameters")
        for name, params in effects_json.items():
            lines.append(f"  {name}: " + "; ".join(f"{p} = {_value_pm(v)}" for p, v in params.items()))
        for name, reason in report.fixed.items():
            lines.append(f"  fixed {name}: {reason}")
        lines += [f"  note: {note}" for note in report.notes]
        parity = exported.get("parity") or {}
        lines.append(f"-> {args.output} ({exported['n_nodes']} nodes, {exported['file_size']} bytes"
                     + (f", parity {parity.get('max_pos_m', 0):.1e} m / {parity.get('max_rot_rad', 0):.1e} rad)"
                        if parity else ")"))
        return "\n".join(lines)

    _emit(args, payload, text)


def _fmt_scores(scores: dict[str, float]) -> str:
    return ", ".join(f"{name} {value:.3g}" for name, value in sorted(scores.items(), key=lambda kv: kv[1]))


def _value_pm(pair: list) -> str:
    """'0.07 ± 0.007', or '0.0006 (not determined)' where the fit has no standard error."""
    value, error = pair
    if isinstance(value, list):
        return "[" + ", ".join(_one_pm(v, e) for v, e in zip(value, error)) + "]"
    return _one_pm(value, error)


def _one_pm(value: float, error: float | None) -> str:
    return f"{value:.4g} ± {error:.1g}" if error is not None else f"{value:.4g} (not determined)"


def cmd_diagnose(args: argparse.Namespace) -> None:
    from .analysis.diagnose import diagnose
    from .data import read_table
    from .textui import table as fmt_table

    _threads(args)
    _load_effect_files(args)
    table = read_table(args.data)
    effects = _effect_names(args.effects)
    model_predict = None
    if args.model is not None:
        from .controller.onnx_meta import read_info
        from .controller.runtime import Corrector

        if args.effects is None:
            effects = list(read_info(args.model).get("effects") or [])
        corrector = Corrector(args.model, backend=args.backend)
        times = table.time()
        model_predict = lambda measured: corrector.correct(measured, t=times)  # noqa: E731
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
        for row in result.get("undetermined", []):
            lines.append(f"not ranked: {row['effect']} cannot be determined by this data ({row['reason']})")
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
    from .analysis.ledger import read_ledger
    from .analysis.page import write_report
    from .controller.onnx_meta import read_info
    from .controller.runtime import Corrector
    from .data import read_table

    _threads(args)
    _load_effect_files(args)
    table = read_table(args.data)
    info = read_info(args.model)
    corrected = Corrector(args.model, backend=args.backend).correct(table.measured, t=table.time())
    diagnosis = None
    if not args.no_diagnosis:
        from .analysis.diagnose import diagnose

        effects = _effect_names(args.effects) if args.effects is not None else list(info.get("effects") or [])
        diagnosis = diagnose(table, effects, folds=args.folds, seed=args.seed,
                             model_predict=lambda measured: corrected, progress=_progress(args))
    from .ingest.pipeline import segments_path

    sidecar = segments_path(args.data)
    segments = json.loads(sidecar.read_text(encoding="utf-8")) if sidecar.exists() else None
    path = write_report(args.output, table, corrected, info, diagnosis, read_ledger(args.data), segments=segments)
    _emit(args, {"report": str(path), "bytes": path.stat().st_size, "diagnosis": diagnosis},
          lambda: f"{args.data} against {args.model} -> {path} ({path.stat().st_size // 1024} KiB)")


# --- info / apply / bench (controller side: numpy only) ---------------------------------

def cmd_info(args: argparse.Namespace) -> None:
    from .controller.onnx_meta import read_info

    info = read_info(args.model)
    # Metadata is whatever the file's author wrote: escape what a terminal would obey.
    _emit(args, info, lambda: "\n".join(f"{_printable(str(k)):>22}: {_printable(_one_line(v))}"
                                         for k, v in info.items()))


def _one_line(value: Any) -> str:
    return json.dumps(value, default=json_default) if isinstance(value, (dict, list)) else str(value)


def _printable(text: str) -> str:
    """Control and other non-printable characters as escapes (\\x1b, \\n, \\u202e)."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def cmd_apply(args: argparse.Namespace) -> None:
    from .controller.apply import apply_file

    payload = apply_file(args.model, args.input, args.output, backend=args.backend)

    def text() -> str:
        from .textui import METRIC_HEADERS, metrics_rows, table as fmt_table

        head = (f"{payload['n']} poses corrected with {args.model} ({args.backend}) -> {args.output} "
                f"(columns corr_x..corr_qz beside the raw meas_*)")
        if payload["raw"] is None:
            return head + "\nno ref_* columns: no metrics"
        return head + "\n" + fmt_table(METRIC_HEADERS, metrics_rows({"raw": payload["raw"],
                                                                     "corrected": payload["corrected"]}))

    _emit(args, payload, text)


def cmd_bench(args: argparse.Namespace) -> None:
    from .controller.runtime import Corrector
    from .latency import bench_model

    # Load it in every back end first: a file the runtimes refuse fails here, in one line.
    Corrector(args.model).close()
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        pass
    else:
        Corrector(args.model, backend="onnxruntime").close()
    result = bench_model(args.model, n_single=args.n, batch=args.batch)

    def text() -> str:
        from .textui import table

        keys = list(result["single_pose_median_us"])
        rows = [[k, result["single_pose_median_us"][k], result["single_pose_p99_us"][k],
                 result["batch_ns_per_pose"][k]] for k in keys]
        return table(["backend", "single median [us]", "single p99 [us]", "batch [ns/pose]"], rows,
                     title=f"{args.model} on {result.get('machine', '?')}")

    _emit(args, result, text)


def cmd_ros2(args: argparse.Namespace) -> None:
    from .ros2.node import run_node

    final = run_node(args.model, input_topic=args.input, output_topic=args.output,
                     frame=args.frame, reliable=args.reliable, t0=args.t0,
                     diag_period=args.diagnostics_period,
                     log=(lambda m: print(m, file=sys.stderr, flush=True)))
    if args.json:
        _print_json(final)
    else:
        print(f"stopped: {final['poses_in']} poses in, {final['poses_out']} out, "
              f"{final['refused']} refused; per model generation {final['poses_per_generation']}; "
              f"added latency p50 {final['latency_p50_us']} us, p99 {final['latency_p99_us']} us")


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

    p = verb("simulate", cmd_simulate, "simulate a paired-pose table of paper experiment I, II or III, "
                                       "or a realistic robot-cell session")
    p.add_argument("--experiment", type=int, choices=(1, 2, 3))
    p.add_argument("--session", action="store_true",
                   help="a realistic session: 6-40 poses, the tracker's own frame, a lever arm (drawn from --seed)")
    p.add_argument("--poses", type=int, help="with --session: number of poses (6 or more)")
    p.add_argument("--spread", help="with --session: orientation spread none, yaw or full")
    p.add_argument("--position-only", action="store_true", help="with --session: no reference orientation")
    p.add_argument("--unremovable", type=float, help="with --session: RMS (mm) of an error no model removes")
    p.add_argument("--robot", help="with --session: a robot (ur5e, or the KUKA-sized ur10e) carries the tracker on "
                                   "its flange through 30-60 poses of every orientation")
    p.add_argument("--effects", help="NAME=V1,V2,...;NAME... override or add effects (values in parameter order)")
    p.add_argument("--only", action="store_true", help="use only the --effects given (plus noise), not the default mix")
    p.add_argument("--effect-file", action="append", type=Path, help="a Python file with user effects")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--recording", type=Path, metavar="OUT.(bag|mcap|csv)",
                   help="also write the recording behind the table: ROS 1 .bag, .mcap, .csv, or a name without "
                        "suffix for a ROS 2 bag directory; -o then holds the recorded poses only")
    p.add_argument("--targets", type=int, default=40,
                   help="poses visited by --recording, first of the measurement order (default 40: 7 minutes)")

    p = verb("ingest", cmd_ingest, "a recording (ROS 1/2 bag, MCAP, CSV log) -> the paired-pose table")
    p.add_argument("recording", type=Path, nargs="+",
                   help="a ROS 1 .bag, a ROS 2 bag directory (or its .db3/.mcap), an .mcap file, or one or two CSV logs")
    p.add_argument("-o", "--output", type=Path, required=True, help="the table; its segment list goes beside it "
                   "(OUT.segments.json)")
    p.add_argument("--robot", default="ur5e", help="ur3, ur5, ur10, ur3e, ur5e, ur10e, ur16e, or a .urdf file")
    p.add_argument("--base-link", help="URDF: the base link (default: the root)")
    p.add_argument("--tip-link", help="URDF: the flange link (default: tool0, else the only end link)")
    p.add_argument("--tool", default="paper",
                   help="end_T_tracker: paper (eq. 22: 42 mm along the flange z), none, or x,y,z[,qw,qx,qy,qz]")
    p.add_argument("--registration", default="paper",
                   help="base_T_(tracker frame): paper (eq. 23), none (poses already in the base frame), "
                        "or x,y,z,qw,qx,qy,qz")
    p.add_argument("--joints", help="joint-state topic (default: the only sensor_msgs/JointState one, "
                   "else /joint_states or /ur/joint_states)")
    p.add_argument("--tracker", help="tracker topic: PoseStamped, PoseWithCovarianceStamped, Odometry, "
                   "TransformStamped or TF (default: the only one)")
    p.add_argument("--tracker-frame", help="TF: the tracker's child frame (default: the only one)")
    p.add_argument("--joint-names", help="the robot's joints in the message, comma-separated, in kinematic order "
                   "(default: the model's names, else the message order)")
    p.add_argument("--stamps", choices=("header", "receive"), default="header",
                   help="header stamps (unset ones fall back to the receive time) or the recorder's receive times")
    p.add_argument("--time-col", default="t", help="CSV: time column (s)")
    p.add_argument("--joint-cols", default="q1,q2,q3,q4,q5,q6", help="CSV: joint-angle columns (rad)")
    p.add_argument("--pose-cols", default="x,y,z,qw,qx,qy,qz", help="CSV: tracker pose columns (m, quaternion)")
    p.add_argument("--still-speed", type=float, default=0.01, help="rad/s: still = every joint slower (default 0.01)")
    p.add_argument("--min-still", type=float, default=2.0, help="s: shortest still segment (default 2)")
    p.add_argument("--settle", type=float, default=0.5, help="s dropped at both ends of a segment (default 0.5)")
    p.add_argument("--gate-mm", type=float, default=1.0,
                   help="mm: RMS gate on tracker samples over 0.1 s about the segment median (default 1)")
    p.add_argument("--max-jitter-mm", type=float, default=0.5,
                   help="mm: reject a segment whose kept samples scatter more (RMS, default 0.5)")
    p.add_argument("--min-samples", type=int, default=100, help="reject a segment with fewer kept samples (default 100)")
    p.add_argument("--offset", type=float, help="s, tracker clock - robot clock (default: estimated)")
    p.add_argument("--max-offset", type=float, default=5.0, help="s: the offset search range (default 5)")
    p.add_argument("--session", help="the table's session column (default: the recording's name)")

    p = verb("fit", cmd_fit, "fit a correction (physics effects, then PMC/MLP) and export it as ONNX")
    p.add_argument("data", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--effects", help="comma-separated effects of the physics stage, e.g. station,mount")
    p.add_argument("--effect-file", action="append", type=Path, help="a Python file with user effects")
    from .train.methods import METHODS

    p.add_argument("--method", choices=(*METHODS, "auto"), default="pmc")
    from .rotations import REPRESENTATIONS

    p.add_argument("--representation", choices=tuple(REPRESENTATIONS), default="zhou",
                   help="orientation representation of the core (position-only tables use position only)")
    p.add_argument("--hidden", default="20,20,20,20", help="MLP hidden layer sizes")
    p.add_argument("--network", help="an MLP named as in the paper, ARCHITECTURE/ALGORITHM: 16/2 = table 1's "
                                     "architecture 16 trained by algorithm 2 (overrides --hidden and --trainer)")
    from .train.activations import ACTIVATIONS

    p.add_argument("--activation", default="tansig", choices=tuple(ACTIVATIONS))
    from .train.trainers import TRAINERS

    p.add_argument("--trainer", default="br", choices=tuple(TRAINERS), help="the MLP's training algorithm")
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

    p = verb("ros2", cmd_ros2, "a ROS 2 node: correct a PoseStamped topic live, swap models while it runs")
    p.add_argument("model", type=Path)
    p.add_argument("--input", default="/tracker/pose", help="PoseStamped topic of the raw tracker pose")
    p.add_argument("--output", default="/tracker/pose_corrected", help="topic of the corrected pose")
    p.add_argument("--frame", default="base_link", help="frame id of the corrected pose (the robot's)")
    p.add_argument("--reliable", action="store_true", help="reliable QoS (default: sensor data, best effort)")
    p.add_argument("--t0", type=float, help="models with time: t = stamp - T0 (default: the first pose's stamp)")
    p.add_argument("--diagnostics-period", type=float, default=1.0, help="seconds between /diagnostics messages")

    p = verb("bench", cmd_bench, "single-pose latency and batch throughput, C runtime against the alternatives")
    p.add_argument("model", type=Path)
    p.add_argument("--n", type=int, default=100_000, help="single-pose calls per backend")
    p.add_argument("--batch", type=int, default=10_000, help="poses per batch call")
    return parser


# Arguments that name files a verb writes; every other Path argument is an input. Outputs
# are checked before the verb runs (not a folder, in a writable folder, not an input), so
# `fit d.csv -o d.csv` fails before any work and without touching the data.
OUTPUT_ARGS = ("output", "save", "store")
# Verbs whose -o is a folder they fill.
FOLDER_OUTPUT_VERBS = frozenset({"demo"})
# The optional dependencies, by module, and how to get them.
TRAIN_MODULES = ("torch", "scipy", "sklearn", "onnx", "onnxruntime", "matplotlib", "tqdm", "threadpoolctl")
EXTRAS = {**dict.fromkeys(TRAIN_MODULES, "pip install 'posecorr[train]'"), "ray": "pip install ray",
          **dict.fromkeys(("rclpy", "geometry_msgs", "diagnostic_msgs", "rcl_interfaces"),
                          "pip install 'posecorr[ros2]'")}
# Verbs that need the ros2 extra.
ROS2_VERBS = {"ros2": ("rclpy", "geometry_msgs", "diagnostic_msgs")}
# Verbs that need the train extra whatever their options: checked before any work starts.
TRAIN_VERBS = frozenset({"fit", "sweep", "diagnose", "report", "export", "demo"})
EXIT_INTERNAL = 1
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143


def _paths(args: argparse.Namespace) -> tuple[list[Path], list[Path]]:
    """(inputs, outputs) named by the parsed arguments."""
    inputs: list[Path] = []
    outputs: list[Path] = []
    for name, value in vars(args).items():
        values = value if isinstance(value, list) else [value]
        for item in values:
            if isinstance(item, Path):
                (outputs if name in OUTPUT_ARGS else inputs).append(item)
    return inputs, outputs


def _check_extras(verb: str) -> None:
    import importlib.util

    needed = TRAIN_MODULES if verb in TRAIN_VERBS else ROS2_VERBS.get(verb, ())
    for module in needed:
        if importlib.util.find_spec(module) is None:
            raise ModuleNotFoundError(f"No module named {module!r}", name=module)


def _check_paths(args: argparse.Namespace) -> None:
    from .safeio import check_output

    if args.verb in FOLDER_OUTPUT_VERBS:
        return
    inputs, outputs = _paths(args)
    for i, out in enumerate(outputs):
        # Each output must also differ from the others (`fit -o m.onnx --save m.onnx`).
        check_output(out, inputs + outputs[:i])


def _error_line(exc: BaseException, args: argparse.Namespace) -> str:
    """One line: the message, its first line only, escaped, prefixed with the input it
    concerns when it does not name a file itself."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        message = f"{exc.filename}: {exc.strerror}"
    else:
        message = str(exc) or type(exc).__name__
    lines = [line for line in message.splitlines() if line.strip()] or [type(exc).__name__]
    message = _printable(lines[0].strip()) + (" ..." if len(lines) > 1 else "")
    inputs, outputs = _paths(args)
    if inputs and not any(str(p) in message for p in inputs + outputs):
        message = f"{inputs[0]}: {message}"
    return message


def _anticipated(exc: BaseException) -> bool:
    """Failures that bad input, a bad file or a bad path cause: reported in one line.
    posecorr's own exceptions (table, model, export, parity, options) count, as do the
    ValueErrors and OSErrors of the numeric and file layers below it."""
    import pickle

    # pickle's errors: `export` of a file that is not a pickled estimator (or an empty one).
    if isinstance(exc, (ValueError, OSError, CliError, pickle.UnpicklingError, EOFError)):
        return True
    return any(cls.__module__.split(".")[0] == "posecorr" for cls in type(exc).__mro__)


def main(argv: list[str] | None = None) -> int:
    import os

    from .safeio import Terminated, sigterm_as_interrupt

    args = build_parser().parse_args(argv)
    prefix = f"posecorr {args.verb}: "
    try:
        with sigterm_as_interrupt():
            _check_extras(args.verb)
            _check_paths(args)
            args.func(args)
            sys.stdout.flush()
    except BrokenPipeError:
        # The reader went away (`posecorr info m.onnx | head`): stop quietly.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_INTERNAL
    except Terminated:
        print(prefix + "terminated; nothing half-written was left behind", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print(prefix + "interrupted; nothing half-written was left behind", file=sys.stderr)
        return EXIT_INTERRUPTED
    except ModuleNotFoundError as exc:
        name = (exc.name or "").split(".")[0]
        hint = EXTRAS.get(name)
        what = f"this needs the {name} package, which is not installed" if name else str(exc)
        print(prefix + "error: " + what + (f": {hint}" if hint else ""), file=sys.stderr)
        return EXIT_USAGE
    except Exception as exc:
        if _anticipated(exc) and not os.environ.get("POSECORR_DEBUG"):
            print(prefix + "error: " + _error_line(exc, args), file=sys.stderr)
            return EXIT_USAGE
        if os.environ.get("POSECORR_DEBUG"):
            raise
        print(prefix + f"internal error: {type(exc).__name__}: {_error_line(exc, args)} "
              "(a bug: set POSECORR_DEBUG=1 for the traceback and please report it)", file=sys.stderr)
        return EXIT_INTERNAL
    return 0


if __name__ == "__main__":
    sys.exit(main())
