"""Whether an effect's maps trace into an ONNX graph.

A fit ends in the model's export, where each effect's inverse map is traced on symbolic
tensors (`symbolic.Sym`): a map written with numpy functions on the pose (`np.sin(p)`) runs
in the fit and fails there, after the work, in the exporter's words. `fit` checks a user's
effect file when it loads, naming the line.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from posecorr.effects import EffectContext, raised_in

from .symbolic import Graph


def untraceable(effect: Any, source: str | Path) -> str | None:
    """What stops `effect.inverse` (which calls its forward map unless it has its own) from
    tracing into a graph, at the effect's default theta, with the line of `source` (the
    effect's file) it came from; None when it traces."""
    g = Graph()
    p, R = g.input("p", (-1, 3)), g.input("R", (-1, 3, 3))
    ctx = EffectContext.default(t=g.input("t", (-1,)) if effect.needs_time else None)
    try:
        effect.inverse(p, R, effect.default_theta(), ctx)
    except Exception as exc:  # the user's code: any exception is its error
        return (f"its map does not trace into the ONNX graph fit exports: {raised_in(exc, source)}; write it with "
                "its arguments' array namespace, as the effects guide shows (xp, p, R, theta = to_namespace(p, R, "
                "theta), from posecorr.effects; then xp.sin(p), not np.sin(p))")
    return None
