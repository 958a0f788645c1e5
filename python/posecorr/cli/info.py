"""`posecorr info`."""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from ..jsonable import json_default
from .common import Verb, emit, printable


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path)


def run(args: argparse.Namespace) -> None:
    from ..controller.onnx_meta import read_info

    info = read_info(args.model)
    paths = _step_paths(args.model)
    if paths is not None:
        info["one_pose_steps"] = [{"path": p, "why": why} for p, why in paths]
    # Metadata is whatever the file's author wrote: escape what a terminal would obey.
    emit(args, info, lambda: "\n".join(
        [f"{printable(str(k)):>22}: {printable(_one_line(v))}" for k, v in info.items()
         if k != "one_pose_steps"] +
        [f"{'one-pose step ' + str(i):>22}: {p}: {why}" for i, (p, why) in enumerate(paths or ())]))


def _step_paths(model: Path) -> list[tuple[str, str]] | None:
    """What each step of one pose runs in libposecorr, or None where the library is missing
    or refuses the file (info still shows the metadata of a file it cannot run)."""
    from ..controller.runtime import Corrector
    from ..controller.checks import PoseCorrError

    try:
        with Corrector(model, max_batch=1) as c:
            return c.step_paths()
    except PoseCorrError:
        return None


def _one_line(value: Any) -> str:
    return json.dumps(value, default=json_default) if isinstance(value, (dict, list)) else str(value)


VERB = Verb(
    help="print a model file's metadata",
    rank=9,
    add_arguments=add_arguments,
    run=run,
)
