"""posecorr's benchmarks: `make bench` (`python -m bench` from the repository root).

A checkout-only package: it reads the shipped models, `tests/data` and `runtime_c/tools`,
so it is not part of the installed `posecorr` wheel. Results go to bench/results/.
"""
from __future__ import annotations

import os
import platform
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"


def latency_model() -> Path:
    """The shipped zhou MLP with the deepest architecture (the issue's 20-20-20-20 network)."""
    candidates = sorted((ROOT / "models").glob("mlp-zhou-*.onnx"), key=lambda p: (p.stem.count("x"), p.stem))
    if not candidates:
        raise SystemExit("no models/mlp-zhou-*.onnx: run `make models` first")
    return candidates[-1]


def cpu() -> str:
    """The processor a timing ran on, with its widest vector extension: the ratio of two
    functions timed in one process depends on it (cpuinfo's model name; the platform's
    words elsewhere)."""
    try:
        info = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return f"{platform.machine()} {platform.processor()}".strip()
    fields = {key.strip(): value.strip() for key, value in
              (line.split(":", 1) for line in info.splitlines() if ":" in line)}
    model = fields.get("model name") or platform.machine()
    flags = set(fields.get("flags", "").split())
    widest = next((name for name, flag in (("AVX-512", "avx512f"), ("AVX2", "avx2")) if flag in flags), "no AVX2")
    return f"{model}, {widest}, {os.cpu_count()} cpus"
