"""`posecorr diagnose`."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from .common import (EFFECT_FILE, Verb, backend_option, check_effect_files, diagnosis_options, diagnosis_workers,
                     effect_file_option, effect_names, effects_help, emit, model_effect_names, progress, read_data,
                     station_pose_of, station_pose_option)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", type=Path, help="the paired-pose table (CSV) to diagnose")
    p.add_argument("--effects", help=effects_help("comma-separated effects of the model (default: those of --model, "
                                                  "else none)"))
    p.add_argument("--model", type=Path, help="an exported model (ONNX) whose residuals to analyse (default: those "
                                              "of the physics stage of --effects, fitted fold by fold)")
    p.add_argument("--propose", type=Path, metavar="FILE",
                   help="write the proposed form as an effect file that fit --effect-file accepts")
    p.add_argument("--no-forms", dest="forms", action="store_false",
                   help="test the catalogue's effects only, not the generic forms")
    backend_option(p)
    effect_file_option(p)
    station_pose_option(p, "the --model's (its metadata station_pose), else the paper's station")
    diagnosis_options(p)


def run(args: argparse.Namespace) -> None:
    from ..analysis.diagnose import advised_effects, diagnose
    from ..analysis.proposal import effect_file_text
    from ..safeio import write_text

    table = read_data(args, advised=True)   # its advice is a fit with the effects it loads
    effects, corrected, mismatch = _with_model(args, table, effect_names(args.effects))
    result = diagnose(table, effects, folds=args.folds, seed=args.seed, forms=args.forms,
                      model_corrected=corrected, progress=progress(args), workers=diagnosis_workers(args))
    result["notes"] += [mismatch] if mismatch else []
    proposal = result["proposal"]
    if proposal is not None and args.propose is not None:
        words = ["posecorr", "diagnose", str(args.data), "--effects", ",".join(effects) or "''"]
        for path in _effect_files(args):
            words += ["--effect-file", path]
        write_text(args.propose, effect_file_text(proposal, " ".join(words + ["--propose", str(args.propose)]),
                                                  str(args.data), _effect_files(args)))
        proposal["file"] = str(args.propose)
    present = [c["effect"] for c in result["candidates"] if c["present"] and c["kind"] == "effect"]
    # the text's "add: --effects ..." line: the effects to fit next, None where none is present
    result["add_effects"], joined = advised_effects(table, effects, result["model_effects"], present)
    result["notes"] += [joined] if joined else []
    emit(args, result, lambda: _text(args, result["model_effects"], result))


def _effect_files(args: argparse.Namespace) -> list[str]:
    return [str(path) for path in getattr(args, "effect_file", None) or []]


def _with_model(args: argparse.Namespace, table: Any, effects: list[str]) -> tuple[list[str], Any, str | None]:
    """(the effects to refit, the --model's corrections or None, a note where --effects are
    not the model's): the ranking refits the effects; the model's residuals feed the
    residual structure by feature."""
    if args.model is None:
        return effects, None, None
    from ..controller.apply import correct_table
    from ..controller.onnx_meta import read_info
    from ..controller.runtime import Corrector

    info = read_info(args.model)
    check_effect_files(args.model, info)
    table.station_pose = station_pose_of(args, args.model, info)
    held = list(info.get("effects") or [])
    mismatch = None
    if args.effects is None:
        effects = model_effect_names(args.model, info)
    elif sorted(effects) != sorted(held):
        mismatch = (f"--effects {', '.join(effects) or 'none'} are not {args.model}'s "
                    f"({', '.join(held) or 'none'}): the candidates are ranked against a refit of --effects; the "
                    "model's own residuals feed the residual structure by feature")
    # corrected before the diagnosis: a pose the model refuses stops it at once, by its row
    return effects, correct_table(Corrector(args.model, backend=args.backend), args.model, table), mismatch


# A candidate whose held-out error grows this many times is shown as having run away: the
# figures (2.7e+82 m + rad on a real session with no frame registered) say nothing more.
RAN_AWAY = 100.0


def _text(args: argparse.Namespace, effects: list[str], result: dict) -> str:
    from ..analysis.interpretation import alias_text, not_ranked_why
    from ..textui import table as fmt_table

    ran_away = [c for c in result["candidates"] if not c["cv_rmse_after"] < RAN_AWAY * c["cv_rmse_before"]]
    # p to two significant digits, as the lines below and the page write it: a tail of the
    # chi-square multiplies its statistic's rounding by about half the statistic, and another
    # CPU's kernels move the fourth digit of a p of 1e-11.
    rows = [[c["rank"], c["effect"], c["kind"], c["parameters"], "ran away" if c in ran_away else c["score"],
             f"{c['p_value']:.2g}", c["cv_rmse_before"], "ran away" if c in ran_away else c["cv_rmse_after"],
             "yes" if c["present"] else "no"] for c in result["candidates"]]
    lines = [f"{args.data}: model effects {', '.join(effects) or 'none'}; "
             f"{result['folds']}-fold cross-validated rmse_total {result['cv_base']['rmse_total']:.4g} m + rad, "
             f"rmse_pos {1e3 * result['cv_base']['rmse_pos']:.3g} mm"
             + (f" (on {result['rows']['used']} of {result['rows']['given']} rows, drawn evenly)"
                if result["rows"]["used"] < result["rows"]["given"] else ""),
             fmt_table(["rank", "candidate", "kind", "params", "score", "p_value", "cv_rmse_before", "cv_rmse_after",
                        "present"], rows,
                       title="Missing effects and forms (score = mean relative fall of the held-out whitened error; "
                             "cv_rmse: held-out rmse_total, m + rad)"),
             *_test_lines(result["test"]),
             *_feature_lines(result["features"])]
    lines[1:1] = [f"note: {note}" for note in result["notes"]]
    lines += [f"ran away: {c['effect']}'s fits predict the held-out poses {c['cv_rmse_after']:.3g} m + rad off "
              f"(against {c['cv_rmse_before']:.4g} before; --json has the figures): fitted to what "
              f"{', '.join(effects) or 'a model of no effects'} leaves, its terms grow without bound"
              for c in ran_away]
    lines += [alias_text(pair) for pair in result["aliases"]]
    for row in result.get("undetermined", []):
        lines.append(f"not ranked: {row['effect']} {not_ranked_why(row)} ({row['reason']})")
    for row in result["absorbed"]:
        lines.append(f"{row['effect']} takes {row['share']:.0%} of {row['form']}'s gain alone, but {row['why']}")
    for row in result["absent"]:
        lines.append(f"not present: {row['effect']} lowers the held-out whitened error by {row['score']:.1%} "
                     f"(p = {row['p_value']:.2g}), but {row['why']}")
    if result["add_effects"]:
        lines.append(f"add: --effects {','.join(result['add_effects'])}")
    lines += _proposal_lines(args, result)
    return "\n".join(lines)


def _test_lines(test: str) -> list[str]:
    """The test's conditions one to a line: in one line it ran to 900 characters."""
    parts, depth, start = [], 0, 0
    for at, char in enumerate(test):
        depth += {"(": 1, ")": -1}.get(char, 0)
        if depth == 0 and test.startswith("; ", at):
            parts.append(test[start:at])
            start = at + 2
    return ["present where all of these hold:"] + [f"  - {part}" for part in parts + [test[start:]]]


def _feature_lines(features: list[dict]) -> list[str]:
    """The features along which a smooth fit explains some held-out residual; the others in
    one line, so that a session with no structure reads as such."""
    from ..analysis.interpretation import split_features
    from ..textui import table as fmt_table

    title = "Residual structure by feature (smooth fit, cross-validated)"
    some, others = split_features(features)
    none = ", ".join(others)
    if not some:
        return [f"{title}: none (cv R^2 0 along {none})"] if none else []
    return ([fmt_table(["feature", "cv R^2", "of the error in"], [[f["feature"], f["r2"], f.get("error", "")]
                                                                 for f in some], title=title)]
            + ([f"cv R^2 0 along {none}"] if none else []))


def _proposal_lines(args: argparse.Namespace, result: dict) -> list[str]:
    from ..analysis.proposal import gain_words, numbers_text, terms_words
    from ..effects import get_effect

    proposal = result["proposal"]
    if proposal is None:
        lines = [f"no proposal: {result['no_proposal']}"]
        if args.propose is not None:   # a file of an earlier run stays: not this diagnosis's
            lines.append(f"  {args.propose}: not written" + (" (the file there is from before)"
                                                            if Path(args.propose).exists() else ""))
        return lines
    lines = [f"proposal: {', '.join(proposal['forms'])} ({proposal['parameters']} parameters), "
             f"{result['folds']}-fold: {gain_words(proposal)}"]
    for form in proposal["forms"]:
        effect = get_effect(form)
        values = "; ".join(f"{label} = {numbers_text(v, 3)}" for label, v in proposal["terms"][form].items())
        lines.append(f"  {form}: {(effect.__doc__ or '').strip().splitlines()[0]} Fitted "
                     f"({terms_words(proposal, form)}{effect.params[0].unit_after(', ')}): {values}.")
        lines.append(f"  causes of this shape: {proposal['causes'][form]}")
    if proposal["file"]:
        from ..analysis.proposal import fit_command

        lines.append(f"  written to {proposal['file']}; fit it with: "
                     f"{fit_command(str(args.data), _effect_files(args), proposal['file'], proposal)}")
    else:
        lines.append("  (--propose FILE writes it as an effect file)")
    return lines


VERB = Verb(
    help="rank the physical effects and generic forms the model lacks; propose an effect file",
    rank=4,
    needs="train",
    outputs={"propose": EFFECT_FILE},
    models=("model",),
    tables=("data",),
    add_arguments=add_arguments,
    run=run,
)
