"""`bench/results/latency.json`: the shipped zhou MLP on every back-end (`posecorr.latency`),
and `pc_run` against a hand-written C function of the same network.

The hand-written reference needs a source checkout (runtime_c/tools/zhou_weights.py writes
its weights; `posecorr-bench --reference-zhou` times it), so it lives here, not in the
package.
"""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import tempfile
from pathlib import Path

from posecorr import latency

from . import RESULTS, ROOT, latency_model

ZHOU_WEIGHTS = ROOT / "runtime_c" / "tools" / "zhou_weights.py"


def reference_bench(path: str | os.PathLike, n_single: int = 20000, batch: int = 10000) -> dict | None:
    """pc_run against a hand-written C function of the same zhou MLP, timed in one process
    (`posecorr-bench --reference-zhou`, runtime_c/tools/zhou_reference.c): per-call ns and
    their ratios, single pose and batch, and how far the outputs differ. None without the
    tool, or for a model that is not the 9-20-20-20-20-9 zhou MLP."""
    exe = latency.bench_binary()
    if exe is None:
        return None
    spec = importlib.util.spec_from_file_location("zhou_weights", ZHOU_WEIGHTS)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    try:
        w = module.weights(str(path))
    except (ValueError, KeyError):
        return None
    with tempfile.TemporaryDirectory() as tmp:
        wfile = Path(tmp) / "zhou.bin"
        w.astype("<f4").tofile(wfile)
        r = subprocess.run([str(exe), str(path), "--n", str(n_single), "--batch", str(batch),
                            "--reference-zhou", str(wfile)], capture_output=True, text=True, check=True)
    return json.loads(r.stdout)["reference"]


def run(out_path: str | os.PathLike | None = None, batch: int = 10000) -> dict:
    model = latency_model()
    result = {**latency.bench_model(model, batch=batch), "model": str(model.relative_to(ROOT)),
              "hand_written_reference": reference_bench(model, batch=batch)}
    if out_path:
        Path(out_path).write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    print(json.dumps(run(RESULTS / "latency.json"), indent=2))
