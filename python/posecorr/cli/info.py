"""`posecorr info`."""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from ..jsonable import json_default
from .common import emit, printable

HELP = "print a model file's metadata"
OUTPUTS = ()  # arguments naming files the verb writes


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path)


def run(args: argparse.Namespace) -> None:
    from ..controller.onnx_meta import read_info

    info = read_info(args.model)
    # Metadata is whatever the file's author wrote: escape what a terminal would obey.
    emit(args, info, lambda: "\n".join(f"{printable(str(k)):>22}: {printable(_one_line(v))}"
                                        for k, v in info.items()))


def _one_line(value: Any) -> str:
    return json.dumps(value, default=json_default) if isinstance(value, (dict, list)) else str(value)

