"""`posecorr compile`: a model's one-pose function as a C file (controller/to_c.py)."""
from __future__ import annotations

import argparse
import re
from pathlib import Path

from .common import CliError, SOURCE, Verb, allow_arguments, allow_options, emit, output_option


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path, help="the .onnx file: a model libposecorr runs whose one-pose plan has a C form (every "
                                           "shipped model; a step with no C form, a softmax layer's say, is refused, "
                                           "naming the step)")
    output_option(p, help="the C file to write")
    p.add_argument("--name", help="prefix of the function, NAME_run (default: the output file's stem)")
    allow_options(p)


def function_prefix(args: argparse.Namespace) -> str:
    """NAME of NAME_run: --name, else the output's stem with _ for what C does not take."""
    name = args.name if args.name is not None else re.sub(r"\W", "_", args.output.stem)
    # C reserves the names that begin with an underscore at file scope (and NAME_run's own)
    if not re.fullmatch(r"[A-Za-z]\w{0,62}", name):
        given = f"--name {name!r}" if args.name is not None else f"the output's name gives {name!r}; --name"
        raise CliError(f"{given}: a C identifier is expected (letters, digits, _; a letter first: C reserves "
                       "names that begin with _ or a digit)")
    return name


def run(args: argparse.Namespace) -> None:
    from ..controller.onnx_meta import read_info
    from ..controller.to_c import Unsupported, plan, source
    from ..safeio import write_text
    from ..textui import counted

    name = function_prefix(args)
    try:
        steps = plan(args.model, **allow_arguments(args))
        text = source(steps, name, args.model.name, read_info(args.model).get("model_digest"))
    except Unsupported as e:
        raise CliError(f"{args.model}: cannot compile: {e}") from None
    except ValueError as e:
        raise CliError(f"{args.model}: {e}") from None
    write_text(args.output, text)
    emit(args, {"model": str(args.model), "output": str(args.output), "function": f"{name}_run",
                "steps": len(steps.steps), "bytes": len(text.encode())},
         lambda: f"{args.model} -> {args.output}: {name}_run, {counted(len(steps.steps), 'step')} of libposecorr's "
                 "one-pose plan as C")


VERB = Verb(
    help="write a model's one-pose function as a C99 file (the same bits as libposecorr)",
    rank=13,
    outputs={"output": SOURCE},
    models=("model",),
    add_arguments=add_arguments,
    run=run,
)
