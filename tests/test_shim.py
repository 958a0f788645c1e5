"""posecorr.controller.runtime (ctypes shim over libposecorr), posecorr.latency and the latency
benchmark's hand-written reference (bench/latency.py)."""
from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))

onnx = pytest.importorskip("onnx")
import graphs  # noqa: E402
from posecorr.controller.runtime import Corrector, PoseCorrError, library_path  # noqa: E402


@pytest.fixture(scope="module")
def lib() -> str:
    # A build of the current sources (the installed copy may predate them).
    return str(graphs.build_test_runtime() / "libposecorr.so")


def test_installed_library_is_found():
    try:
        p = library_path()
    except PoseCorrError:
        pytest.skip("posecorr is not installed (no _native/libposecorr.so)")
    assert p.exists()


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("shim") / "pose.onnx"
    p.write_bytes(graphs.signed(graphs.pose_model(2, metadata={"units": "m", "method": "mlp", **graphs.BOUNDED})))
    return p


def test_single_and_batch_shapes(lib, model_path):
    c = Corrector(model_path, library=lib)
    x = graphs.random_poses(50, seed=2)
    batch = c.correct(x)
    assert batch.shape == (50, 7) and batch.dtype == np.float64
    one = c.correct(x[3])
    assert one.shape == (7,) and one.dtype == np.float64
    np.testing.assert_array_equal(one, batch[3])
    np.testing.assert_array_equal(c.predict(x), batch)
    assert c.correct(np.zeros((0, 7))).shape == (0, 7)
    # float64 / list input is accepted and converted
    np.testing.assert_array_equal(c.correct(x[3].astype(np.float64).tolist()), one)


def test_matches_onnxruntime_backend(lib, model_path):
    pytest.importorskip("onnxruntime")
    c = Corrector(model_path, library=lib)
    o = Corrector(model_path, backend="onnxruntime")
    x = graphs.random_poses(300, seed=8)
    a, b = c.correct(x), o.correct(x)
    assert np.max(np.abs(a - b) / np.maximum(1, np.abs(b))) <= 2e-6
    np.testing.assert_allclose(c.correct(x[0]), o.correct(x[0]), rtol=0, atol=2e-6)
    assert c.metadata == o.metadata


def test_metadata(lib, model_path):
    c = Corrector(model_path, library=lib)
    expected = {p.key: p.value for p in onnx.load(model_path).metadata_props}
    assert c.metadata == expected and c.metadata["units"] == "m"
    assert c.n_inputs == c.n_outputs == 7


def test_errors(lib, model_path, tmp_path):
    c = Corrector(model_path, library=lib)
    bad = graphs.random_poses(3)
    bad[1, 0] = np.inf
    with pytest.raises(PoseCorrError, match="non-finite"):
        c.correct(bad)
    with pytest.raises(ValueError):
        c.correct(np.zeros((3, 6)))
    with pytest.raises(PoseCorrError, match="cannot open"):
        Corrector(tmp_path / "missing.onnx", library=lib)
    with pytest.raises(ValueError):
        Corrector(model_path, backend="tensorflow")


def test_repr_names_model_bytes_as_load_errors_do(lib, model_path):
    """repr of a Corrector loaded from bytes printed every byte of the model (65 kB for a
    shipped one); now it names them as a load error does."""
    data = model_path.read_bytes()
    with pytest.raises(PoseCorrError) as info:
        Corrector(data[:-1] + bytes([data[-1] ^ 1]), library=lib)   # the same size, one bit changed
    named = str(info.value).split(": ")[0]
    assert named == f"model of {len(data)} bytes"
    assert repr(Corrector(data, library=lib)) == f"Corrector(<{named}>, backend='c')"
    assert repr(Corrector(model_path, library=lib)) == f"Corrector({str(model_path)!r}, backend='c')"


def test_predict_passes_the_poses_times(lib):
    """predict had no t: a model that takes time corrected every pose as at t = 0. The test
    model adds t * rate to the pose (graphs.time_model)."""
    x = graphs.random_poses(6, seed=4)
    t = np.linspace(0.0, 3000.0, 6)
    expected = x + t[:, None] * np.array([1e-4, -2e-4, 3e-5, 0, 0, 0, 0])
    blob = graphs.time_model().SerializeToString()
    for c in (Corrector(blob, library=lib, allow_unbounded=True, allow_unsigned=True),
              Corrector(blob, backend="onnxruntime", allow_unbounded=True, allow_unsigned=True)):
        assert c.takes_time
        np.testing.assert_allclose(c.predict(x, t), expected, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(c.predict(x, t), c.correct(x, t))
        np.testing.assert_array_equal(c.predict(x[5], t[5]), c.correct(x, t)[5])
        np.testing.assert_array_equal(c.predict(x), c.correct(x, np.zeros(6)))


def test_model_bytes_in_any_bytes_like_object(lib, model_path):
    """Corrector(memoryview(data)) raised TypeError (expected str, bytes or os.PathLike):
    bytes, bytearray and memoryview load the model, on both back ends, named by their size."""
    data = model_path.read_bytes()
    x = graphs.random_poses(5, seed=3)
    for backend, kw in (("c", {"library": lib}), ("onnxruntime", {})):
        expected = Corrector(model_path, backend=backend, **kw).correct(x)
        for blob in (data, bytearray(data), memoryview(data), memoryview(bytearray(data))):
            buffer = blob.obj if isinstance(blob, memoryview) else blob
            c = Corrector(blob, backend=backend, **kw)
            if isinstance(buffer, bytearray):  # the model keeps its own copy
                buffer[:] = bytes(len(buffer))
            np.testing.assert_array_equal(c.correct(x), expected)
            assert repr(c) == f"Corrector(<model of {len(data)} bytes>, backend={backend!r})"
        with pytest.raises(PoseCorrError, match="^model of 100 bytes: "):
            Corrector(memoryview(data)[:100], backend=backend, **kw)


def test_single_pose_fast_path_equals_ctypes(lib, model_path):
    """The single-pose extension (posecorr.controller._call1) gives the ctypes path's result bit for
    bit, refuses what it refuses, and leaves other inputs to the general path."""
    c = Corrector(model_path, library=lib)
    impl = c._impl
    if impl._call1 is None:
        pytest.skip("posecorr.controller._call1 was not built (no Python headers)")
    x = graphs.random_poses(200, seed=5).astype(np.float64)
    assert all(impl._call1.run1(impl._run_address, impl.handle, p, np.empty(7)) == 0 for p in x)
    fast = np.array([c.correct(p) for p in x])
    impl._call1 = None
    slow = np.array([c.correct(p) for p in x])
    np.testing.assert_array_equal(fast, slow)
    np.testing.assert_array_equal(fast, c.correct(x))
    impl._call1 = importlib.import_module("posecorr.controller._call1")
    bad = x[0].copy()
    bad[4] = np.nan
    with pytest.raises(PoseCorrError, match="pose 0: qx is not finite"):
        c.correct(bad)
    # float32 takes the fast path too; strided and list inputs the general one: same result
    assert impl._call1.run1(impl._run_address, impl.handle, x[0].astype(np.float32),
                            np.empty(7)) == 0
    for p in (x[7].astype(np.float32), np.repeat(x[7], 2)[::2], list(x[7])):
        np.testing.assert_array_equal(c.correct(p), slow[7])
    assert impl._call1.run1(impl._run_address, impl.handle, x[0].astype(np.int64),
                            np.empty(7)) == -1
    assert impl._call1.run1(impl._run_address, impl.handle, x[0],
                            np.empty(7, np.float32)) == -1


def test_import_is_light():
    code = ("import sys, posecorr.controller; "
            "print(sorted(m for m in ('onnxruntime', 'onnx', 'torch', 'scipy') if m in sys.modules))")
    env_path = str(ROOT / "python")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env={"PYTHONPATH": env_path, "PATH": "/usr/bin:/bin"}, check=True)
    assert r.stdout.strip() == "[]"


def test_bench_model_layout(lib, model_path, monkeypatch):
    from posecorr import latency

    monkeypatch.setattr(latency, "bench_binary", lambda: Path(lib).parent / "posecorr-bench")
    import posecorr.controller.runtime as rt
    real = rt.Corrector
    monkeypatch.setattr(rt, "Corrector", lambda path, **kw: real(path, library=lib, **kw))
    d = latency.bench_model(model_path, n_single=300, batch=200)
    keys = {"c", "shim", "onnxruntime", "onnxruntime_iobinding"}
    for block in ("single_pose_median_us", "single_pose_p99_us", "batch_ns_per_pose"):
        assert set(d[block]) == keys
        for k in keys:
            assert d[block][k] is not None and d[block][k] > 0
    assert isinstance(d["machine"], str) and d["machine"]


def test_hand_written_reference_equals_pc_run(lib, model_path, monkeypatch):
    """posecorr-bench --reference-zhou (the latency benchmark's hand-written C function of
    the shipped zhou MLP, bench/latency.py) gives pc_run's outputs exactly; other models have
    no reference."""
    from bench.latency import reference_bench
    from posecorr import latency

    monkeypatch.setattr(latency, "bench_binary", lambda: Path(lib).parent / "posecorr-bench")
    zhou = ROOT / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"
    ref = reference_bench(zhou, n_single=1000, batch=100)
    assert ref["compared_poses"] == 1000 and ref["identical_poses"] == 1000
    assert ref["max_abs_diff"] == 0
    for key in ("pc_run_single_ns", "reference_single_ns", "pc_run_batch_ns_per_pose",
                "reference_batch_ns_per_pose"):
        assert ref[key] > 0
    assert reference_bench(model_path) is None


@pytest.mark.parametrize("backend", ["c", "onnxruntime"])
def test_a_corrector_copies_by_loading_its_model_again(backend, tmp_path):
    """pickle (a worker process) and deepcopy failed on the ctypes library; a copy is the
    model loaded again from what the first was given (a file or its bytes), checks and
    options included, and gives the same bits."""
    import copy
    import pickle

    path = ROOT / "models" / "pmc-zhou.onnx"
    poses = graphs.poses_in_box(path, 16, 3).astype(np.float64)
    for given in (path, path.read_bytes()):
        first = Corrector(given, backend, max_batch=4)
        for again in (pickle.loads(pickle.dumps(first)), copy.deepcopy(first)):
            assert again is not first and again.backend == backend and again._options["max_batch"] == 4
            np.testing.assert_array_equal(again.correct(poses), first.correct(poses))
