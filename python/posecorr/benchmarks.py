"""`make bench`: every benchmark, JSON results in bench/results/ (timings live here, never in tests).

* `train.json`: seconds per LM epoch of the 9-20-20-20-20-9 network on 2360 samples against
  the torch-levenberg-marquardt package, and the wall time of 30 repeats of the paper's best
  Experiment III configuration (`posecorr.train.bench_train`).
* `latency.json`: single-pose latency and batch throughput of the shipped zhou MLP in the C
  runtime, the Python shim, onnxruntime (plain and IOBinding) and numpy (`posecorr.latency`).
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=("train", "latency", "ingest"), help="run one benchmark")
    args = parser.parse_args(argv)
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.only in (None, "latency"):
        from .latency import bench_model

        model = latency_model()
        result = {"model": str(model.relative_to(ROOT)), **bench_model(model)}
        (RESULTS / "latency.json").write_text(json.dumps(result, indent=2))
        print(json.dumps(result, indent=2))
    if args.only in (None, "train"):
        from .train import bench_train

        result = bench_train.run(str(RESULTS / "train.json"))
        print(json.dumps(result, indent=2, default=str))
    if args.only in (None, "ingest"):
        from .ingest import bench as bench_ingest

        result = bench_ingest.run(str(RESULTS / "ingest.json"))
        print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
