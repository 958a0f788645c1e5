"""`posecorr fit`."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from . import options
from .common import (ESTIMATOR, MODEL, Verb, CliError, emit, progress, apply_threads, load_effect_files,
                     effect_names, effects_help, output_option, seed_option, effect_file_option, station_pose_option,
                     threads_option)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from ..train.spec import (DEFAULT_ACTIVATION, DEFAULT_EPOCHS, DEFAULT_HIDDEN, DEFAULT_TRAINER, NUMBERS_PER_WEIGHT,
                              SESSION_EPOCHS, SESSION_HIDDEN)

    p.add_argument("data", type=Path, help="the paired-pose table (CSV) to fit")
    output_option(p, help="the ONNX model to write")
    p.add_argument("--effects", help=effects_help("comma-separated effects of the physics stage, e.g. station,mount "
                                                  "(default: none)"))
    effect_file_option(p)
    station_pose_option(p)
    from ..train.methods import METHODS

    p.add_argument("--method", choices=tuple(METHODS), default="pmc",
                   help="the core after the physics stage: pmc, mlp, auto (a cross-validated choice among "
                        "candidates) or none (the physics stage alone) (default: pmc)")
    from ..rotations import orientations

    p.add_argument("--representation", choices=orientations(),
                   help="orientation representation of the core (position-only tables use position only) "
                        "(default: zhou; --method auto also tries a PMC in every other one on tables of 200 poses "
                        "or more)")
    p.add_argument("--hidden", help="MLP hidden layer sizes: 20-20, 20x20 or 20,20; #N is table 1's N-th "
                                    f"(default: {'-'.join(map(str, DEFAULT_HIDDEN))} where the table holds "
                                    f"{NUMBERS_PER_WEIGHT} numbers for each of its weights, else "
                                    f"{'-'.join(map(str, SESSION_HIDDEN))} trained {SESSION_EPOCHS} epochs)")
    p.add_argument("--network", help="an MLP named as in the paper, ARCHITECTURE/ALGORITHM: 16/2 = table 1's "
                                     "architecture 16 trained by algorithm 2 (overrides --hidden and --trainer)")
    from ..train.activations import ACTIVATIONS

    p.add_argument("--activation", choices=tuple(ACTIVATIONS),
                   help=f"the MLP's activation function (default: {DEFAULT_ACTIVATION})")
    from ..train.trainers import TRAINERS

    p.add_argument("--trainer", choices=tuple(TRAINERS),
                   help=f"the MLP's training algorithm (default: {DEFAULT_TRAINER})")
    p.add_argument("--epochs", type=options.integer(1, 1_000_000), metavar="N",
                   help=f"the MLP's most training epochs (default: {DEFAULT_EPOCHS}; {SESSION_EPOCHS} for the "
                        "network a smaller table gets, see --hidden)")
    p.add_argument("--cv", default="none", help="held-out test: none (fixed 15%% test split), loo, or a number of "
                                                "folds (default: none)")
    seed_option(p)
    p.add_argument("--save", type=Path, metavar="FILE",
                   help="also save the fitted estimator, signed for this account (for `posecorr export`)")
    threads_option(p)
    p.add_argument("--subsample", type=options.integer(4, FIT_ROWS_MAX), metavar="N",
                   help=f"fit on an even random draw of N rows (seeded by --seed); a table of more than "
                        f"{FIT_ROWS_MAX:,} rows needs it")


# Rows a fit takes: its memory and time grow with them (the rigid fits and the physics stage
# are nonlinear least squares over every row). Measured with /usr/bin/time -v at a load of
# 9-10 on 2 cores: 2*10^4 rows of Experiment III 18 s, 10^5 rows 2:52 and 1.1 GB.
FIT_ROWS_MAX = 50_000


def _read(args: argparse.Namespace) -> Any:
    """The table to fit (where its station stood, `--station-pose`), or its draw with
    --subsample; a table of more than FIT_ROWS_MAX rows is refused once that many are read,
    before any fitting, saying how to reduce it."""
    table = _read_rows(args)
    table.station_pose = args.station_pose
    return table


def _read_rows(args: argparse.Namespace) -> Any:
    from ..data import TooManyRows, read_table

    if args.subsample is not None:
        table = read_table(args.data)
        if table.n <= args.subsample:
            from ..safeio import warn

            warn(f"--subsample {args.subsample}: {args.data} has {table.n} rows; every one is fitted")
        return table.draw(args.subsample, args.seed)[0]
    try:
        return read_table(args.data, max_rows=FIT_ROWS_MAX)
    except TooManyRows:
        raise CliError(f"{args.data}: more than {FIT_ROWS_MAX:,} rows, the most a fit takes (its memory and time "
                       "grow with the rows); reduce the table: `posecorr ingest` averages a recording's still "
                       f"segments into one row per stop of the robot, or --subsample {FIT_ROWS_MAX} fits an even "
                       "random draw of the rows") from None


def _parse_cv(text: str | None) -> Any:
    """The held-out plan (`train.splits`): the fixed test split, leave one out, or 2..1000 folds."""
    from ..train.splits import KFold, parse_plan

    try:
        plan = parse_plan(text)
    except ValueError:
        plan = None
    if plan is None or isinstance(plan, KFold) and plan.k > 1000:
        raise CliError(f"--cv takes none, loo or a number of folds in 2..1000, got {text!r}")
    return plan


def run(args: argparse.Namespace) -> None:
    from ..analysis.ledger import ledger_path
    from ..fitting import extrapolation_note
    from ..safeio import check_sidecar
    from ..train.pipeline import fit_table

    apply_threads(args)
    check_sidecar(ledger_path(args.data))  # refused before the work, not after it
    load_effect_files(args, exported=True)
    # The options are checked before the table is read: their faults are theirs, and found at once.
    effects, plan, spec = effect_names(args.effects), _parse_cv(args.cv), _spec(args)
    table = _read(args)
    spec, chosen_network = _sized_network(args, spec, table.n)
    report = fit_table(table, effects, spec, plan, args.seed, progress=progress(args))
    if chosen_network:
        report.notes.insert(0, chosen_network)
    report, exported = _export(args, report, table, effects, spec)
    extrapolates = extrapolation_note(exported)
    if extrapolates:
        report.notes.append(extrapolates)
    effects_json = report.model.physics_.describe() if report.model.physics_ is not None else {}
    emit(args, _payload(args, report, exported, effects_json),
         lambda: _text(args, table, effects, report, exported, effects_json))


# The options of an MLP (`--method mlp`), which the other methods do not take.
NETWORK_OPTIONS = ("hidden", "network", "activation", "trainer", "epochs")


def _spec(args: argparse.Namespace) -> Any:
    """The model the options name; an MLP too large for its trainer is refused here, before the fit."""
    from ..train.methods import get_method
    from ..train.spec import DEFAULT_REPRESENTATION, spec_from_options

    hidden = None if args.hidden is None else options.layer_sizes(args.hidden, "--hidden")
    method = get_method(args.method)
    network = [f"--{name}" for name in NETWORK_OPTIONS if getattr(args, name) is not None]
    if network and not method.network:   # they were ignored without a word
        raise CliError(f"{', '.join(network)} {'sets' if len(network) == 1 else 'set'} the network of --method mlp; "
                       f"--method {args.method} takes none")
    if args.representation is not None and not (method.has_core or method.chooses):
        raise CliError(f"--representation sets the orientation representation of the core after the physics stage; "
                       f"--method {args.method} fits none")
    spec = spec_from_options(args.method, args.representation or DEFAULT_REPRESENTATION, hidden=hidden,
                             network=args.network, activation=args.activation, trainer=args.trainer,
                             epochs=args.epochs)
    if spec.hidden is not None:
        from ..train.spec import DEFAULT_TRAINER

        options.check_network_size(tuple(spec.hidden), spec.trainer or DEFAULT_TRAINER, "--hidden")
    return spec


def _sized_network(args: argparse.Namespace, spec: Any, poses: int) -> tuple[Any, str]:
    """A network named by none of --hidden, --network, --epochs is sized to the table
    (`spec.session_network`); (spec, what was chosen) or (spec, "") where the user chose."""
    from ..train.spec import session_network

    if any(getattr(args, name) is not None for name in ("hidden", "network", "epochs")):
        return spec, ""
    return session_network(spec, poses)


def _export(args: argparse.Namespace, report: Any, table: Any, effects: list, spec: Any) -> tuple[Any, dict]:
    """(the report of what was written, its export record: nodes, size, parity). A model whose
    graph fails the parity check (float32 cannot follow it: a network scaled to a feature
    that barely varies) gives way to the rigid fit, said in a note; any other export failure,
    or the rigid fit's own, is one CliError line."""
    from ..export.onnx_export import ParityError
    from ..export.symbolic import ExportError
    from ..fitting import write_fit
    from ..train.pipeline import floor_instead

    def written(report: Any) -> tuple[Any, dict]:
        return report, write_fit(report, table, args.data, args.output, effects, save=args.save, spec=spec,
                                 seed=args.seed).exported

    try:
        try:
            return written(report)
        except ParityError as exc:
            if report.chosen == report.baseline_name:
                raise
            progress(args)(f"{report.chosen}: {exc}; writing the rigid fit instead")
            return written(floor_instead(report, table, str(exc)))
    except ExportError as exc:
        raise CliError(f"{args.output}: the model could not be exported: {exc}") from None


def _payload(args: argparse.Namespace, report: Any, exported: dict, effects_json: dict) -> dict[str, Any]:
    """`fit --json`: the model, its held-out scores against the rigid floor, and its physics."""
    info = report.model.export_info()
    payload: dict[str, Any] = {"model": str(args.output), "output": str(args.output), "method": info.get("method"),
                               "chosen": report.chosen, "representation": info.get("representation"),
                               "raw": report.raw, report.heldout_kind: report.heldout, "effects": effects_json,
                               "parity": exported.get("parity"), "nodes": exported.get("n_nodes")}
    from ..metrics import frames_unregistered, improvement, named_block

    payload.update({"baseline": named_block(report.baseline_name, report.baseline), "n_heldout": report.n_heldout,
                    # raw measures the frames' offset where they are unregistered: the floor is the reference
                    "frames_unregistered": frames_unregistered(report.raw, report.baseline),
                    "vs_floor": improvement(report.baseline, report.heldout),
                    "rigid_rmse_total": report.rigid_scores, "rigid_rmse_pos": report.rigid_rmse_pos,
                    "fell_back_to_rigid": report.fell_back, "fixed": report.fixed, "notes": report.notes})
    if report.shrinkage is not None:
        payload["shrinkage"] = report.shrinkage
    if report.model.physics_ is not None:
        payload["spread"] = report.model.physics_.spread_.to_json()
    if report.auto_scores:
        payload["auto_cv_rmse_total"] = report.auto_scores
    return payload


def _text(args: argparse.Namespace, table: Any, effects: list, report: Any, exported: dict,
          effects_json: dict) -> str:
    """The human summary: scores against the rigid floor, the physics found, notes, the file written."""
    from ..metrics import frames_unregistered, improvement
    from ..textui import METRIC_HEADERS, metrics_rows, table as fmt_table
    from ..train.splits import HeldOut

    key = report.heldout_kind
    label = f"test split ({report.n_heldout})" if key is HeldOut.TEST else f"{report.chosen}, cv {report.plan}"
    # Raw in a frame metres away measures that offset: the floor is then what a model must beat.
    unregistered = frames_unregistered(report.raw, report.baseline)
    if unregistered:
        header, raw_label = "improvement vs floor", "raw (frames unregistered)"
        ratios = [None, improvement(report.baseline, report.heldout)["improvement_total"], 1.0]
    else:
        header, raw_label = "improvement", "raw"
        ratios = [None, report.heldout.get("improvement_total"), report.baseline.get("improvement_total")]
    if key is HeldOut.TEST:    # raw is scored on the test split too, not on the table's every pose
        raw_label += ", test split"
    # auto's scores on all poses chose the final model; the table's held-out row scores auto itself
    auto = f"auto's inner cross-validation on all poses, rmse_total: {_fmt_scores(report.auto_scores)}"
    # a fallback writes another model than the one asked for: said where the model is named
    why = (report.asked or {}).get("why") or "it did worse held out"
    model = report.chosen + (f", not the one asked for: {why} (see the note)" if report.fell_back else "")
    if report.auto_scores:
        model += f"; {auto}" if report.fell_back else f" ({auto})"
    # a rigid model written for the effects asked holds the registration's: "asked", not "none"
    held = sorted(effects_json) if effects_json else sorted(effects)
    asked = "effects" if held == sorted(effects) else "effects asked"
    lines = [f"{args.data}: {table.n} poses; {asked}: {', '.join(effects) or 'none'}; model: {model}",
             fmt_table(METRIC_HEADERS + [header],
                       [row + [ratio] for row, ratio in zip(
                           metrics_rows({raw_label: report.raw, label: report.heldout,
                                         f"{report.baseline_name} (floor), same poses": report.baseline}),
                           ratios)])]
    pos = report.rigid_rmse_pos     # under cross-validation only
    scores = ", ".join(f"{name} {value:.4g}" + (f" / {1e3 * pos[name]:.4g}" if pos else "")
                       for name, value in report.rigid_scores.items())
    lines.append(f"  floor: {report.baseline_name}, the best of the rigid fits on the same poses "
                 f"({'rmse_total / rmse_pos [mm]' if pos else 'rmse_total'}: {scores})")
    if report.shrinkage is not None:
        # the trace of the physics stage's hat matrix: a core's weights are not in it
        core = " (the core's weights apart)" if report.model.core_ is not None else ""
        lines.append(f"  prior strength {report.shrinkage['prior_strength']:g}: "
                     f"{report.shrinkage['effective_params']:.1f} effective parameters in the physics stage{core}")
    if effects_json and report.chosen.startswith("rigid-"):   # effects asked or not, the rigid fit has these
        lines.append(f"  {report.chosen}'s registration and lever, as the station and mount effects hold them:")
    for name, params in effects_json.items():
        units = _units(name)
        lines.append(f"  {name}: " + "; ".join(f"{p} = {_value_pm(v)}{units.get(p, '')}" for p, v in params.items()))
    for name, reason in report.fixed.items():
        lines.append(f"  fixed {name}: {reason}")
    lines += [f"  note: {note}" for note in report.notes]
    lines.append(f"-> {args.output} ({exported['n_nodes']} nodes, {exported['file_size']} bytes"
                 + _parity_words(exported.get("parity") or {}) + ")")
    return "\n".join(lines)


def _parity_words(parity: dict[str, Any]) -> str:
    """', parity 1.2e-04 m / 3.0e-07 rad', with the position tolerance where float32's steps
    at the data's coordinates widened it to a tenth of a millimetre or more (coordinates
    of 16 m or more: a tracker frame far from its origin), which a user of a millimetre
    tracker must know the check allowed."""
    from posecorr.export.parity import ULPS_POS

    if not parity:
        return ""
    tol = parity.get("tol_pos_m", 0.0)
    widened = (f" (tolerance {tol:.1e} m: {ULPS_POS} float32 steps at the largest coordinate)"
               if tol >= 1e-4 else "")
    return f", parity {parity.get('max_pos_m', 0):.1e} m{widened} / {parity.get('max_rot_rad', 0):.1e} rad"


def _fmt_scores(scores: dict[str, float]) -> str:
    return ", ".join(f"{name} {value:.3g}" for name, value in sorted(scores.items(), key=lambda kv: kv[1]))


def _units(effect: str) -> dict[str, str]:
    """{param name: ' UNIT'} of a registered effect, as its `Param`s declare them."""
    from ..effects import EFFECTS

    found = EFFECTS.get(effect)
    return {param.name: param.unit_after() for param in found.params} if found is not None else {}


def _value_pm(pair: list) -> str:
    """'0.07 ± 0.007', or '0.0006 (not determined)' where the fit has no standard error."""
    value, error = pair
    if isinstance(value, list):
        return "[" + ", ".join(_one_pm(v, e) for v, e in zip(value, error)) + "]"
    return _one_pm(value, error)


def _one_pm(value: float, error: float | None) -> str:
    return f"{value:.4g} ± {error:.1g}" if error is not None else f"{value:.4g} (not determined)"


VERB = Verb(
    help="fit a correction (physics effects, then PMC/MLP) and export it as ONNX",
    rank=3,
    needs="train",
    outputs={"output": MODEL, "save": ESTIMATOR},
    tables=("data",),
    add_arguments=add_arguments,
    run=run,
)
