"""posecorr's benchmarks: `make bench` (`python -m bench` from the repository root).

A checkout-only package: it reads the shipped models, `tests/data` and `runtime_c/tools`,
so it is not part of the installed `posecorr` wheel. Results go to bench/results/.
"""
from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"


def latency_model() -> Path:
    """The shipped zhou MLP with the deepest architecture (the issue's 20-20-20-20 network)."""
    candidates = sorted((ROOT / "models").glob("mlp-zhou-*.onnx"), key=lambda p: (p.stem.count("x"), p.stem))
    if not candidates:
        raise SystemExit("no models/mlp-zhou-*.onnx: run `make models` first")
    return candidates[-1]
