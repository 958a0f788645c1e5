"""`posecorr diagnose`."""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import (backend_option, diagnosis_options, effect_file_option, effect_names, emit, progress,
                     read_data)

HELP = "rank the physical effects the model lacks; show where the residual lives"
NEEDS = "train"
OUTPUTS = ()  # arguments naming files the verb writes


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", type=Path)
    p.add_argument("--effects", help="the model's effects (default: those of --model, else none)")
    p.add_argument("--model", type=Path, help="an exported model whose residuals to analyse")
    backend_option(p)
    effect_file_option(p)
    diagnosis_options(p)


def run(args: argparse.Namespace) -> None:
    from ..analysis.diagnose import diagnose
    from ..textui import table as fmt_table

    table = read_data(args)
    effects = effect_names(args.effects)
    model_predict = None
    if args.model is not None:
        from ..controller.onnx_meta import read_info
        from ..controller.runtime import Corrector

        if args.effects is None:
            effects = list(read_info(args.model).get("effects") or [])
        corrector = Corrector(args.model, backend=args.backend)
        times = table.time()
        model_predict = lambda measured: corrector.correct(measured, t=times)  # noqa: E731
    result = diagnose(table, effects, folds=args.folds, seed=args.seed, model_predict=model_predict,
                      progress=progress(args))

    def text() -> str:
        rows = [[c["rank"], c["effect"], c["score"], c["p_value"], c["cv_rmse_before"], c["cv_rmse_after"],
                 "yes" if c["present"] else "no"] for c in result["candidates"]]
        lines = [f"{args.data}: model effects {', '.join(effects) or 'none'}; "
                 f"cross-validated rmse_total {result['cv_base']['rmse_total']:.4g}"
                 + (f" (on {result['rows']['used']} of {result['rows']['given']} rows, drawn evenly)"
                    if result["rows"]["used"] < result["rows"]["given"] else ""),
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

    emit(args, result, text)
