"""`make bench`: every benchmark, JSON results in bench/results/ (timings live here, never in tests).

* `train.json`: seconds per LM epoch of the 9-20-20-20-20-9 network on 2360 samples against
  the torch-levenberg-marquardt package, and the wall time of 30 repeats of the paper's best
  Experiment III configuration (`posecorr.train.bench_train`).
* `fit.json`: wall time of `posecorr fit` on robot-cell tables (36-pose sessions, leave one
  out; 3375 simulated poses), with the load average (`posecorr.train.bench_fit`).
* `latency.json`: single-pose latency and batch throughput of the shipped zhou MLP in the C
  runtime, the Python shim and onnxruntime (plain and IOBinding) (`posecorr.latency`).
* `targets.json`: the runtime's speed goals as ratios taken in one run: `pc_run` against the
  hand-written zhou MLP (single pose, batch), the demo's physics + PMC model against the
  zhou MLP, the Python shim's single pose (`posecorr.bench_targets`).
* `apply.json`: `posecorr apply` on 10^6 rows (wall and CPU time, peak memory) against
  the csv module's read-and-write-back floor on the same file (`posecorr.bench_apply`).
* `ingest.json`: seconds to ingest a 10-minute recording (300k joint states, 150k tracker
  poses) from a ROS 1 bag, an MCAP file and a CSV log (`posecorr.ingest.bench`).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "bench" / "results"


def latency_model() -> Path:
    """The shipped zhou MLP with the deepest architecture (the issue's 20-20-20-20 network)."""
    candidates = sorted((ROOT / "models").glob("mlp-zhou-*.onnx"), key=lambda p: (p.stem.count("x"), p.stem))
    if not candidates:
        raise SystemExit("no models/mlp-zhou-*.onnx: run `make models` first")
    return candidates[-1]


def _latency() -> dict:
    from .latency import bench_model

    model = latency_model()
    result = {**bench_model(model), "model": str(model.relative_to(ROOT))}
    (RESULTS / "latency.json").write_text(json.dumps(result, indent=2))
    return result


def _targets() -> dict:
    from .bench_targets import run as run_targets

    return run_targets(latency_model(), str(RESULTS / "targets.json"))


def _fit() -> dict:
    from .train import bench_fit

    return bench_fit.run(str(RESULTS / "fit.json"))


def _apply() -> dict:
    from .bench_apply import run as run_apply

    return run_apply(str(RESULTS / "apply.json"))


def _train() -> dict:
    from .train import bench_train

    return bench_train.run(str(RESULTS / "train.json"))


def _ingest() -> dict:
    from .ingest import bench as bench_ingest

    return bench_ingest.run(str(RESULTS / "ingest.json"))


# name -> runner writing bench/results/NAME.json; `make bench` runs them in this order.
BENCHMARKS = {"latency": _latency, "targets": _targets, "fit": _fit, "apply": _apply, "ingest": _ingest, "train": _train}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=tuple(BENCHMARKS), help="run one benchmark")
    args = parser.parse_args(argv)
    RESULTS.mkdir(parents=True, exist_ok=True)
    for name, run in BENCHMARKS.items():
        if args.only in (None, name):
            print(json.dumps(run(), indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
