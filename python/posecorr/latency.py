"""Latency benchmark of one exported corrector across back-ends.

`bench_model(path)` returns the DESIGN.md `bench` layout:

    {"single_pose_median_us": {"c", "shim", "onnxruntime", "onnxruntime_iobinding", "numpy"},
     "single_pose_p99_us": {same}, "batch_ns_per_pose": {same}, "machine": "..."}

- c: the `posecorr-bench` binary (pure C timing, no Python).
- shim: `posecorr.runtime.Corrector(backend="c").correct` on a (7,) array / a batch.
- onnxruntime: `InferenceSession.run` (1 thread); onnxruntime_iobinding: the same with
  pre-bound input/output buffers. null when onnxruntime is not importable.
- numpy: a small numpy interpreter of posecorr's operator set (needs the `onnx` package
  to read the file; null without it).

Single-pose figures are the median / 99th percentile of per-call wall times
(time.perf_counter_ns around each call). The slow back-ends are timed on fewer calls
(at most 20 000 for onnxruntime, 2 000 for numpy) to keep a run short; `counts` says how many.
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
from typing import Any, Callable

import numpy as np

__all__ = ["bench_model", "NumpyGraph", "machine_description", "bench_binary"]

_KEYS = ("c", "shim", "onnxruntime", "onnxruntime_iobinding", "numpy")


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


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.3, 0.3, (n, 3)) + np.array([0.0, -0.6, 0.5])
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


# -- numpy interpreter -------------------------------------------------------------------

def _attr(node, name, default=None):
    from onnx import helper

    for a in node.attribute:
        if a.name == name:
            return helper.get_attribute_value(a)
    return default


class NumpyGraph:
    """Evaluates a posecorr ONNX graph with numpy (float32), one node at a time."""

    def __init__(self, path: str | os.PathLike | bytes) -> None:
        import onnx
        from onnx import numpy_helper

        m = onnx.load_from_string(path) if isinstance(path, bytes) else onnx.load(str(path))
        self.consts = {t.name: numpy_helper.to_array(t) for t in m.graph.initializer}
        self.nodes = list(m.graph.node)
        self._nh = numpy_helper

    def __call__(self, pose: np.ndarray) -> np.ndarray:
        env = dict(self.consts)
        env["pose"] = np.asarray(pose, dtype=np.float32).reshape(-1, 7)
        for n in self.nodes:
            ins = [env[i] if i else None for i in n.input]
            out = _OPS[n.op_type](n, ins, self)
            env[n.output[0]] = out
        return env["corrected"]


def _axes(n, ins):
    if len(ins) > 1 and ins[1] is not None:
        return tuple(int(a) for a in ins[1])
    a = _attr(n, "axes")
    return tuple(a) if a is not None else None


def _reduce(fn):
    def op(n, ins, g):
        axes = _axes(n, ins)
        keep = bool(_attr(n, "keepdims", 1))
        if axes is None or len(axes) == 0:
            if _attr(n, "noop_with_empty_axes", 0):
                return ins[0]
            axes = None
        return fn(ins[0], axis=axes, keepdims=keep)
    return op


def _slice(n, ins, g):
    x = ins[0]
    starts, ends = ins[1], ins[2]
    axes = ins[3] if len(ins) > 3 and ins[3] is not None else range(len(starts))
    steps = ins[4] if len(ins) > 4 and ins[4] is not None else [1] * len(starts)
    sl = [slice(None)] * x.ndim
    for s, e, a, st in zip(starts, ends, axes, steps):
        sl[int(a)] = slice(int(s), int(e), int(st))
    return x[tuple(sl)]


def _reshape(n, ins, g):
    shape = [int(d) for d in ins[1]]
    shape = [ins[0].shape[i] if d == 0 else d for i, d in enumerate(shape)]
    return ins[0].reshape(shape)


def _gemm(n, ins, g):
    a = ins[0].T if _attr(n, "transA", 0) else ins[0]
    b = ins[1].T if _attr(n, "transB", 0) else ins[1]
    y = np.float32(_attr(n, "alpha", 1.0)) * (a @ b)
    if len(ins) > 2 and ins[2] is not None:
        y = y + np.float32(_attr(n, "beta", 1.0)) * ins[2]
    return y.astype(np.float32)


def _softmax(n, ins, g):
    ax = _attr(n, "axis", -1)
    e = np.exp(ins[0] - ins[0].max(axis=ax, keepdims=True))
    return e / e.sum(axis=ax, keepdims=True)


def _argmax(n, ins, g):
    ax = _attr(n, "axis", 0)
    x = ins[0]
    if _attr(n, "select_last_index", 0):
        r = x.shape[ax] - 1 - np.argmax(np.flip(x, ax), axis=ax)
    else:
        r = np.argmax(x, axis=ax)
    return np.expand_dims(r, ax) if _attr(n, "keepdims", 1) else r


_CAST = {1: np.float32, 6: np.int32, 7: np.int64, 9: np.bool_, 11: np.float64}


def _constant(n, ins, g):
    for a in n.attribute:
        if a.name == "value":
            return g._nh.to_array(a.t)
        if a.name == "value_float":
            return np.float32(a.f)
        if a.name == "value_floats":
            return np.asarray(a.floats, np.float32)
        if a.name == "value_int":
            return np.int64(a.i)
        if a.name == "value_ints":
            return np.asarray(a.ints, np.int64)
    raise ValueError("Constant without value")


def _unsqueeze(n, ins, g):
    axes = _axes(n, ins)
    return np.expand_dims(ins[0], tuple(a if a >= 0 else a + ins[0].ndim + len(axes) for a in axes))


_OPS: dict[str, Callable] = {
    "Abs": lambda n, i, g: np.abs(i[0]), "Neg": lambda n, i, g: -i[0],
    "Add": lambda n, i, g: i[0] + i[1], "Sub": lambda n, i, g: i[0] - i[1],
    "Mul": lambda n, i, g: i[0] * i[1],
    "Div": lambda n, i, g: (i[0] // i[1]) if i[0].dtype.kind == "i" else i[0] / i[1],
    "And": lambda n, i, g: np.logical_and(i[0], i[1]), "Or": lambda n, i, g: np.logical_or(i[0], i[1]),
    "Not": lambda n, i, g: np.logical_not(i[0]),
    "Equal": lambda n, i, g: i[0] == i[1], "Greater": lambda n, i, g: i[0] > i[1],
    "GreaterOrEqual": lambda n, i, g: i[0] >= i[1], "Less": lambda n, i, g: i[0] < i[1],
    "LessOrEqual": lambda n, i, g: i[0] <= i[1],
    "Atan": lambda n, i, g: np.arctan(i[0]), "Cos": lambda n, i, g: np.cos(i[0]),
    "Sin": lambda n, i, g: np.sin(i[0]), "Tan": lambda n, i, g: np.tan(i[0]),
    "Exp": lambda n, i, g: np.exp(i[0]), "Sqrt": lambda n, i, g: np.sqrt(i[0]),
    "Tanh": lambda n, i, g: np.tanh(i[0]), "Relu": lambda n, i, g: np.maximum(i[0], 0),
    "Sigmoid": lambda n, i, g: (1 / (1 + np.exp(-i[0]))).astype(i[0].dtype),
    "Clip": lambda n, i, g: np.clip(i[0], i[1] if len(i) > 1 and i[1] is not None else None,
                                    i[2] if len(i) > 2 and i[2] is not None else None),
    "Max": lambda n, i, g: np.maximum.reduce(np.broadcast_arrays(*i)) if len(i) > 1 else i[0],
    "Min": lambda n, i, g: np.minimum.reduce(np.broadcast_arrays(*i)) if len(i) > 1 else i[0],
    "Cast": lambda n, i, g: i[0].astype(_CAST[_attr(n, "to")]),
    "Concat": lambda n, i, g: np.concatenate(i, axis=_attr(n, "axis")),
    "Constant": _constant, "Identity": lambda n, i, g: i[0],
    "Gather": lambda n, i, g: np.take(i[0], i[1], axis=_attr(n, "axis", 0)),
    "Gemm": _gemm, "MatMul": lambda n, i, g: np.matmul(i[0], i[1]),
    "ReduceSum": _reduce(np.sum), "ReduceMax": _reduce(np.max),
    "Reshape": _reshape, "Slice": _slice, "Softmax": _softmax, "ArgMax": _argmax,
    "Squeeze": lambda n, i, g: np.squeeze(i[0], axis=_axes(n, i)),
    "Unsqueeze": _unsqueeze,
    "Transpose": lambda n, i, g: np.transpose(i[0], _attr(n, "perm")),
    "Where": lambda n, i, g: np.where(i[0], i[1], i[2]),
}


def c_bench(path: str | os.PathLike, n_single: int = 100000, batch: int = 10000) -> dict | None:
    """The C runtime alone, timed by `posecorr-bench` (JSON: single_pose_median_us,
    single_pose_p99_us, batch_ns_per_pose, load_us); None when the tool is not built."""
    exe = bench_binary()
    if exe is None:
        return None
    r = subprocess.run([str(exe), str(path), "--n", str(n_single), "--batch", str(batch)],
                       capture_output=True, text=True, check=True)
    return json.loads(r.stdout)


def reference_bench(path: str | os.PathLike, n_single: int = 20000, batch: int = 10000) -> dict | None:
    """pc_run against a hand-written C function of the same zhou MLP, timed in one process
    (`posecorr-bench --reference-zhou`, runtime_c/tools/zhou_reference.c): per-call ns and
    their ratios, single pose and batch, and how far the outputs differ. None without the
    tool or a source checkout, or for a model that is not the 9-20-20-20-20-9 zhou MLP."""
    import importlib.util
    import tempfile

    exe = bench_binary()
    script = Path(__file__).resolve().parents[2] / "runtime_c" / "tools" / "zhou_weights.py"
    if exe is None or not script.exists():
        return None
    spec = importlib.util.spec_from_file_location("zhou_weights", script)
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


def bench_model(path: str | os.PathLike, n_single: int = 100000, batch: int = 10000) -> dict:
    """Benchmarks one model on every available back-end (layout: see module doc)."""
    path = Path(path)
    poses = _poses(max(batch, 1000))
    single_poses = poses[:1000]
    med: dict[str, float | None] = {k: None for k in _KEYS}
    p99: dict[str, float | None] = {k: None for k in _KEYS}
    bat: dict[str, float | None] = {k: None for k in _KEYS}
    counts: dict[str, int] = {}

    d = c_bench(path, n_single, batch)
    if d is not None:
        med["c"], p99["c"] = d["single_pose_median_us"], d["single_pose_p99_us"]
        bat["c"] = d["batch_ns_per_pose"]
        counts["c"] = n_single

    from .controller.runtime import Corrector

    corr = Corrector(path)
    med["shim"], p99["shim"] = _time_single(corr.correct, single_poses, n_single)
    batch_fns = {"shim": (corr.correct, poses[:batch])}
    counts["shim"] = n_single

    try:
        import onnxruntime as ort
    except ImportError:
        ort = None
    if ort is not None:
        so = ort.SessionOptions()
        so.intra_op_num_threads = 1
        so.inter_op_num_threads = 1
        sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        n_ort = min(n_single, 20000)

        def run_ort(p):
            return sess.run(["corrected"], {"pose": p.reshape(-1, 7)})[0]

        med["onnxruntime"], p99["onnxruntime"] = _time_single(run_ort, single_poses, n_ort)
        batch_fns["onnxruntime"] = (run_ort, poses[:batch])
        x1 = np.zeros((1, 7), np.float32)
        y1 = np.zeros((1, 7), np.float32)
        io = sess.io_binding()
        io.bind_cpu_input("pose", x1)
        io.bind_output("corrected", "cpu", 0, np.float32, [1, 7], y1.ctypes.data)

        def run_bound(p):
            x1[0] = p
            sess.run_with_iobinding(io)
            return y1

        med["onnxruntime_iobinding"], p99["onnxruntime_iobinding"] = _time_single(
            run_bound, single_poses, n_ort)
        xb = np.ascontiguousarray(poses[:batch])
        yb = np.zeros_like(xb)
        iob = sess.io_binding()
        iob.bind_cpu_input("pose", xb)
        iob.bind_output("corrected", "cpu", 0, np.float32, list(xb.shape), yb.ctypes.data)
        batch_fns["onnxruntime_iobinding"] = (lambda p: sess.run_with_iobinding(iob), xb)
        counts["onnxruntime"] = counts["onnxruntime_iobinding"] = n_ort

    try:
        g = NumpyGraph(path)
    except ImportError:
        g = None
    if g is not None:
        n_np = min(n_single, 2000)
        med["numpy"], p99["numpy"] = _time_single(g, single_poses, n_np)
        batch_fns["numpy"] = (g, poses[:batch])
        counts["numpy"] = n_np

    bat.update(_time_batches(batch_fns))
    # posecorr-bench runs in its own process, so it cannot take turns with the others; a
    # second run after them gives it the same chance of missing a slow phase.
    d = c_bench(path, 1000, batch) if bat["c"] is not None else None
    if d is not None:
        bat["c"] = min(bat["c"], d["batch_ns_per_pose"])
    return {"single_pose_median_us": med, "single_pose_p99_us": p99,
            "batch_ns_per_pose": bat, "machine": machine_description(),
            "model": str(path), "counts": counts, "batch": batch,
            "hand_written_reference": reference_bench(path, batch=batch),
            "load_average": list(os.getloadavg())}
