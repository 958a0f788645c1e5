"""`posecorr bench`."""
from __future__ import annotations

import argparse
from pathlib import Path

from . import options
from .common import Verb, allow_arguments, allow_options, emit


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path, help="the model (ONNX)")
    p.add_argument("--n", type=options.integer(1, 10_000_000), default=100_000, help="single-pose calls per backend")
    p.add_argument("--batch", type=options.integer(1, 1_000_000), default=10_000, help="poses per batch call")
    allow_options(p)


def run(args: argparse.Namespace) -> None:
    from ..controller.runtime import Corrector
    from ..latency import bench_model

    allow = allow_arguments(args)
    # Load it in every back end first: a file the runtimes refuse fails here, in one line.
    Corrector(args.model, **allow).close()
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        pass
    else:
        Corrector(args.model, backend="onnxruntime", **allow).close()
    result = bench_model(args.model, n_single=args.n, batch=args.batch, **allow)

    def text() -> str:
        from ..textui import table

        keys = list(result["single_pose_median_us"])
        rows = [[k, result["single_pose_median_us"][k], result["single_pose_p99_us"][k],
                 result["batch_ns_per_pose"][k]] for k in keys]
        load = result.get("c_load_us")
        # timings on a shared machine mean little without its load (what the benchmarks state)
        tail = [f"load average {result['load_average'][0]:.2f} while it ran"
                + (f"; the C runtime loads the file in {load:.0f} us (median of 21, file read included)"
                   if load is not None else "")]
        return "\n".join([table(["backend", "single median [us]", "single p99 [us]", "batch [ns/pose]"], rows,
                                title=f"{args.model} on {result.get('machine', '?')}")] + tail)

    emit(args, result, text)


VERB = Verb(
    help="single-pose latency and batch throughput, C runtime against the alternatives",
    rank=12,
    models=("model",),
    add_arguments=add_arguments,
    run=run,
)
