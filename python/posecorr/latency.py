"""Latency benchmark of one exported corrector across back-ends.

`bench_model(path)` returns the layout of `posecorr bench --json` (docs/design.md, "Command line"):

    {"single_pose_median_us": {"c", "shim", "onnxruntime", "onnxruntime_iobinding"},
     "single_pose_p99_us": {same}, "batch_ns_per_pose": {same}, "machine": "..."}

- c: the `posecorr-bench` binary (pure C timing, no Python).
- shim: `posecorr.Corrector(backend="c").correct` on a (7,) array / a batch.
- onnxruntime: `InferenceSession.run` (1 thread); onnxruntime_iobinding: the same with
  pre-bound input/output buffers. null when onnxruntime is not importable.

Single-pose figures are the median / 99th percentile of per-call wall times
(time.perf_counter_ns around each call). onnxruntime, the slow one, is timed on fewer calls
(at most 20 000) to keep a run short; `counts` says how many.
Batch figures are the best of seven rounds of at least 50 ms each, for every back-end; the
Python-side back-ends take turns round by round, and posecorr-bench (its own process) runs
before and after them.
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

__all__ = ["bench_model", "machine_description", "bench_binary", "c_bench", "sample_poses"]

_KEYS = ("c", "shim", "onnxruntime", "onnxruntime_iobinding")


def machine_description() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}; {os.cpu_count()} cpus; {platform.system()} {platform.release()}; " \
           f"python {platform.python_version()}; numpy {np.__version__}"


def sample_poses(n: int, seed: int = 0, model: Any = None) -> np.ndarray:
    """n float32 poses, uniform rotations: positions uniform in the box `model` (a
    Corrector) was fitted in (its input_bounds: every runtime refuses a pose outside), else
    around Experiment III's workspace (-0.6, 0.5) m."""
    from .controller.checks import Limits

    rng = np.random.default_rng(seed)
    box = None if model is None else Limits.from_metadata(model.metadata, model.takes_time, True).box
    if box is None or not np.all(np.isfinite(box)):  # no model, or one loaded without bounds
        p = rng.uniform(-0.3, 0.3, (n, 3)) + np.array([0.0, -0.6, 0.5])
    else:
        p = rng.uniform(box[0], box[1], (n, 3))
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([p, q], axis=1).astype(np.float32)


def _time_single(fn: Callable[[np.ndarray], Any], poses: np.ndarray, n: int) -> tuple[float, float]:
    for i in range(min(200, n)):
        fn(poses[i % len(poses)])
    t = np.empty(n)
    clock = time.perf_counter_ns
    m = len(poses)
    for i in range(n):
        p = poses[i % m]
        t0 = clock()
        fn(p)
        t[i] = clock() - t0
    return float(np.median(t) / 1e3), float(np.percentile(t, 99) / 1e3)


def _time_batches(fns: dict[str, tuple[Callable[[np.ndarray], Any], np.ndarray]],
                  rounds: int = 7, min_seconds: float = 0.05) -> dict[str, float]:
    """ns per pose for each back-end: best of `rounds` rounds of >= min_seconds, the
    back-ends taking turns so that a slow phase of a shared machine hits them all."""
    best = {name: float("inf") for name in fns}
    for fn, poses in fns.values():
        fn(poses)
    for _ in range(rounds):
        for name, (fn, poses) in fns.items():
            reps, t0 = 0, time.perf_counter_ns()
            while True:
                fn(poses)
                reps += 1
                el = time.perf_counter_ns() - t0
                if el > min_seconds * 1e9 and reps >= 2:
                    break
            best[name] = min(best[name], el / (reps * len(poses)))
    return best


def bench_binary() -> Path | None:
    """posecorr-bench next to the library the shim uses, if present."""
    from .controller.runtime import library_path

    try:
        cand = library_path().parent / "posecorr-bench"
    except Exception:
        return None
    return cand if cand.exists() else None


def c_bench(path: str | os.PathLike, n_single: int = 100000, batch: int = 10000,
            allow: Sequence[str] = ()) -> dict | None:
    """The C runtime alone, timed by `posecorr-bench` (JSON: single_pose_median_us,
    single_pose_p99_us, batch_ns_per_pose, load_us); None when the tool is not built.
    allow: "unbounded", "unsigned" (its --allow-* options)."""
    exe = bench_binary()
    if exe is None:
        return None
    r = subprocess.run([str(exe), str(path), "--n", str(n_single), "--batch", str(batch),
                        *(f"--allow-{what}" for what in allow)], capture_output=True, text=True, check=True)
    return json.loads(r.stdout)


def _onnxruntime_backends(path: Path, single_poses: np.ndarray, batch_poses: np.ndarray,
                          n_single: int) -> dict[str, tuple] | None:
    """onnxruntime on one thread, plain and with bound buffers: per back-end the single-pose
    (median, p99), the batch function and its poses, and the count of single poses; None
    when onnxruntime is not installed."""
    try:
        import onnxruntime as ort
    except ImportError:
        return None
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    n_ort = min(n_single, 20000)
    # a model with a time input runs at t = 0, as posecorr-bench runs it
    timed = any(i.name == "t" for i in sess.get_inputs())

    def run_ort(p):
        pose = p.reshape(-1, 7)
        feeds = {"pose": pose, "t": np.zeros(len(pose), np.float32)} if timed else {"pose": pose}
        return sess.run(["corrected"], feeds)[0]

    x1 = np.zeros((1, 7), np.float32)
    y1 = np.zeros((1, 7), np.float32)
    io = sess.io_binding()
    io.bind_cpu_input("pose", x1)
    t1 = np.zeros(1, np.float32)
    if timed:
        io.bind_cpu_input("t", t1)
    io.bind_output("corrected", "cpu", 0, np.float32, [1, 7], y1.ctypes.data)

    def run_bound(p):
        x1[0] = p
        sess.run_with_iobinding(io)
        return y1

    # The bound buffers are raw pointers to onnxruntime: the function keeps them alive.
    run_bound.buffers = (x1, t1, y1)

    xb = np.ascontiguousarray(batch_poses)
    yb = np.zeros_like(xb)
    iob = sess.io_binding()
    iob.bind_cpu_input("pose", xb)
    t_batch = np.zeros(len(xb), np.float32)
    if timed:
        iob.bind_cpu_input("t", t_batch)
    iob.bind_output("corrected", "cpu", 0, np.float32, list(xb.shape), yb.ctypes.data)

    def run_batch_bound(p):
        sess.run_with_iobinding(iob)
        return yb

    run_batch_bound.buffers = (xb, t_batch, yb)

    return {
        "onnxruntime": (_time_single(run_ort, single_poses, n_ort),
                        (run_ort, batch_poses), n_ort),
        "onnxruntime_iobinding": (_time_single(run_bound, single_poses, n_ort),
                                  (run_batch_bound, xb), n_ort),
    }


def bench_model(path: str | os.PathLike, n_single: int = 100000, batch: int = 10000,
                allow_unbounded: bool = False, allow_unsigned: bool = False) -> dict:
    """Benchmarks one model on every available back-end (layout: see module doc); the allow
    flags load another producer's model as `Corrector` does."""
    from .controller.runtime import Corrector

    path = Path(path)
    corr = Corrector(path, allow_unbounded=allow_unbounded, allow_unsigned=allow_unsigned)
    allow = [what for what, given in (("unbounded", allow_unbounded), ("unsigned", allow_unsigned)) if given]
    poses = sample_poses(max(batch, 1000), model=corr)
    single_poses = poses[:1000]
    med: dict[str, float | None] = {k: None for k in _KEYS}
    p99: dict[str, float | None] = {k: None for k in _KEYS}
    bat: dict[str, float | None] = {k: None for k in _KEYS}
    counts: dict[str, int] = {}

    d = c_bench(path, n_single, batch, allow)
    load_us = None if d is None else d.get("load_us")
    if d is not None:
        med["c"], p99["c"] = d["single_pose_median_us"], d["single_pose_p99_us"]
        bat["c"] = d["batch_ns_per_pose"]
        counts["c"] = n_single

    med["shim"], p99["shim"] = _time_single(corr.correct, single_poses, n_single)
    batch_fns = {"shim": (corr.correct, poses[:batch])}
    counts["shim"] = n_single
    for name, ((m, q), fn, n) in (_onnxruntime_backends(path, single_poses, poses[:batch],
                                                         n_single) or {}).items():
        med[name], p99[name], batch_fns[name], counts[name] = m, q, fn, n

    bat.update(_time_batches(batch_fns))
    # posecorr-bench runs in its own process, so it cannot take turns with the others; a
    # second run after them gives it the same chance of missing a slow phase.
    d = c_bench(path, 1000, batch, allow) if bat["c"] is not None else None
    if d is not None:
        bat["c"] = min(bat["c"], d["batch_ns_per_pose"])
    return {"single_pose_median_us": med, "single_pose_p99_us": p99,
            "batch_ns_per_pose": bat, "c_load_us": load_us, "machine": machine_description(),
            "model": str(path), "counts": counts, "batch": batch,
            "load_average": list(os.getloadavg())}
