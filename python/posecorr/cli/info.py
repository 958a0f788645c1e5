"""`posecorr info`."""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from ..jsonable import json_default
from .common import Verb, emit, printable


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path, help="the model (ONNX)")


def run(args: argparse.Namespace) -> None:
    from ..controller.onnx_meta import read_info

    info = read_info(args.model)
    info["integrity"] = _integrity(args.model)
    paths = _step_paths(args.model)
    if paths is not None:
        info["one_pose_steps"] = [{"path": p, "why": why} for p, why in paths]
    # Metadata is whatever the file's author wrote: escape what a terminal would obey.
    emit(args, info, lambda: "\n".join(
        [printable(line) for line in summary(info)] + ["", "metadata and structure:"] +
        [f"{printable(str(k)):>22}: {printable(_one_line(v))}{_unit(k)}" for k, v in info.items()
         if k not in ("one_pose_steps", "integrity")] +
        [f"{'one-pose step ' + str(i):>22}: {p}: {why}" for i, (p, why) in enumerate(paths or ())]))


# The units of the metadata values that are numbers of one kind (the design's metadata table);
# the metrics carry theirs in `units`.
METADATA_UNITS = {"input_bounds": "m", "time_bounds": "s", "correction_reach": "m, rad", "file_size": "bytes"}


def _unit(key: Any) -> str:
    unit = METADATA_UNITS.get(str(key))
    return f" [{unit}]" if unit else ""


def summary(info: dict[str, Any]) -> list[str]:
    """What a model file is and what it states of itself, in a few lines: what it corrects
    with, its size, its held-out figures, its parity, the poses it takes. Every metadata value
    may be missing or of another type (the author wrote it): what is not there is left out."""
    import math

    from .. import coverage
    from ..controller.onnx_meta import stated_metrics, stated_rigid
    from ..metrics import block_name, frames_unregistered

    lines = [f"{Path(str(info.get('file'))).name}: {_describe(info)}"]
    # the graph's constants hold the fitted parameters and the encodings' own numbers
    size = [f"{info[k]:,} {word}" for k, word in (("n_parameters", "fitted parameters"),
                                                   ("parameter_count", "numbers in the graph's constants"),
                                                   ("node_count", "nodes"), ("file_size", "bytes"))
            if isinstance(info.get(k), int)]
    lines.append("  " + ", ".join(size))
    integrity = info.get("integrity")
    if isinstance(integrity, dict) and not integrity.get("ok"):
        lines.append(f"  DAMAGED or unsigned, every runtime refuses it: {integrity.get('why')}")
    stated = stated_metrics(info)
    if stated is not None:
        kind, figures, raw = stated
        where = ("cross-validated" if kind == "cv" else "test split") + (
            f", {figures['n']} poses" if isinstance(figures.get("n"), int) else "")
        lines.append(f"  held out ({where}): {_errors(figures)}")
        rigid = stated_rigid(info)
        if rigid is not None:
            lines.append(f"  the best rigid fit ({block_name(rigid) or 'rigid'}), same poses: {_errors(rigid)}")
        if raw is not None:
            # raw measures the frames' offset where they are unregistered, not the tracker
            offset = (rigid is not None and isinstance(raw.get("rmse_pos"), (int, float))
                      and frames_unregistered(raw, rigid))
            lines.append(f"  raw: {_errors(raw)}" + (" (frames unregistered: their offset, not the tracker's error)"
                                                     if offset else ""))
    parity = info.get("parity")
    if isinstance(parity, dict) and isinstance(parity.get("passed"), bool):
        worst = (f", worst {parity['max_pos_m']:.1e} m / {parity['max_rot_rad']:.1e} rad"
                 if all(isinstance(parity.get(k), (int, float)) for k in ("max_pos_m", "max_rot_rad")) else "")
        broken = parity.get("broken_clause")
        worst += f"; the graph breaks the output contract: {broken}" if isinstance(broken, str) else ""
        lines.append(f"  parity with the fitted estimator: {'passed' if parity['passed'] else 'FAILED'}{worst}")
    box = info.get("input_bounds")
    if (isinstance(box, list) and len(box) == 2 and all(isinstance(b, list) and len(b) == 3 for b in box)
            and all(isinstance(v, (int, float)) for b in box for v in b)):
        lines.append("  corrects positions within " + ", ".join(
            f"{axis} {lo:.3f}..{hi:.3f}" for axis, lo, hi in zip("xyz", *box)) + " m")
    cone = coverage.cone_of(info.get(coverage.KEY)) if coverage.reads_orientation(info.get("representation")) else None
    if cone is not None:   # as apply reads it: what apply ignores, info does not show
        lines.append(f"  fitted on orientations within {math.degrees(cone['within']):.3g} deg of their mean "
                     "(apply counts the poses turned beyond)")
    span = info.get("time_bounds")
    if isinstance(span, list) and len(span) == 2 and all(isinstance(v, (int, float)) for v in span):
        lines.append(f"  takes each pose's time t (s since the session's start) within {span[0]:g}..{span[1]:g} s")
    return lines


def _describe(info: dict[str, Any]) -> str:
    from ..controller.onnx_meta import describe_corrector

    effects = info.get("effects")
    return (f"{describe_corrector(info)}; physical effects: "
            f"{', '.join(map(str, effects)) if isinstance(effects, list) and effects else 'none'}")


def _errors(figures: dict[str, Any]) -> str:
    out = [f"rmse_pos {1e3 * figures['rmse_pos']:.4g} mm"] if isinstance(figures.get("rmse_pos"), (int, float)) else []
    if isinstance(figures.get("rmse_rot"), (int, float)):
        out.append(f"rmse_rot {1e3 * figures['rmse_rot']:.4g} mrad")
    return ", ".join(out) or "no figures"


def _integrity(model: Path) -> dict[str, Any]:
    """{"ok", "why"}: whether the file's bytes give the digest its metadata states, as every
    loader checks before it runs a model (the metadata is shown either way)."""
    from ..controller.checks import PoseCorrError, check_digest

    try:
        check_digest(model.read_bytes(), model.name)
    except PoseCorrError as error:
        return {"ok": False, "why": str(error).split(": ", 1)[-1]}
    return {"ok": True, "why": None}


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
    models=("model",),
    add_arguments=add_arguments,
    run=run,
)
