"""libposecorr (runtime_c): C unit tests, parity with onnxruntime for every operator and a
realistic pose->pose graph, the tools, sanitizers, valgrind and the installed package."""
from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

import graphs  # noqa: E402
from header import LOAD, STATUS  # noqa: E402
from posecorr.controller.runtime import Corrector as _Corrector, PoseCorrError, library_path  # noqa: E402


def Corrector(*args, **kw) -> _Corrector:
    """The shim as another producer's graphs need it here: these test graphs carry neither
    bounds nor a digest (PC_LOAD_ALLOW_UNBOUNDED | PC_LOAD_ALLOW_UNSIGNED). A digest or
    bounds a file does carry are checked whatever the flags; the refusals themselves are
    tests/test_checks.py's and tests/test_hostile.py's."""
    kw.setdefault("allow_unbounded", True)
    kw.setdefault("allow_unsigned", True)
    return _Corrector(*args, **kw)


ALLOW = LOAD["PC_LOAD_ALLOW_UNBOUNDED"] | LOAD["PC_LOAD_ALLOW_UNSIGNED"]
LEAN = LOAD["PC_LOAD_IN_PLACE"] | LOAD["PC_LOAD_NO_METADATA"]

BUILD = ROOT / "build"
OPERATORS = [ln.split("#")[0].strip() for ln in
             (ROOT / "export" / "operators.txt").read_text().splitlines()]
OPERATORS = [op for op in OPERATORS if op]
CASES = {**graphs.op_cases(), **graphs.cross_row_cases()}
CROSS_ROW = graphs.CROSS_ROW


@pytest.fixture(scope="session")
def c_build() -> Path:
    return graphs.build_test_runtime()


@pytest.fixture(scope="session")
def lib(c_build) -> str:
    return str(c_build / "libposecorr.so")


def ort_run(model_bytes: bytes, x: np.ndarray) -> np.ndarray:
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    s = ort.InferenceSession(model_bytes, so, providers=["CPUExecutionProvider"])
    return s.run(["corrected"], {"pose": x})[0]


def rel_err(got: np.ndarray, ref: np.ndarray) -> float:
    assert got.shape == ref.shape
    assert np.array_equal(np.isnan(got), np.isnan(ref)), "NaN pattern differs"
    ok = ~np.isnan(ref)
    if not ok.any():
        return 0.0
    return float(np.max(np.abs(got[ok] - ref[ok]) / np.maximum(1.0, np.abs(ref[ok]))))


def test_c_unit_tests(c_build):
    """The C unit tests, and every shipped model loaded and run at the centre of its fitted
    positions."""
    models = sorted(str(p) for p in (ROOT / "models").glob("*.onnx"))
    r = subprocess.run([str(c_build / "pc_unit_tests"), *models], capture_output=True, text=True,
                       timeout=120)
    tail = r.stdout.strip().splitlines()[-1]
    assert r.returncode == 0, r.stdout + r.stderr
    assert tail.endswith(" 0 failed"), tail
    assert int(tail.split()[0]) > 100


def test_every_operator_has_a_parity_case():
    used = {n.op_type for f in CASES.values() for m in f() for n in m.graph.node}
    missing = set(OPERATORS) - used
    assert not missing, f"operators without a parity case: {sorted(missing)}"


@pytest.mark.parametrize("case", sorted(CASES))
def test_operator_parity(case, lib):
    x = graphs.op_inputs(300, seed=1)
    worst = 0.0
    for model in CASES[case]():
        blob = model.SerializeToString()
        if case in CROSS_ROW:
            # Row i reads row j: refused at load (a batch would be split into chunks),
            # and run pose by pose when the caller asks for batches of one.
            with pytest.raises(PoseCorrError, match="mixes rows"):
                Corrector(blob, library=lib)
            c = Corrector(blob, library=lib, max_batch=1)
            got = np.stack([c.correct(p) for p in x[:20]]).astype(np.float32)
            ref = np.concatenate([ort_run(blob, p[None]) for p in x[:20]])
        else:
            c = Corrector(blob, library=lib)
            got = c.correct(x).astype(np.float32)
            ref = ort_run(blob, x)
            # single pose and small batches go through other plans
            np.testing.assert_array_equal(c.correct(x[5]).astype(np.float32), got[5])
            got3 = c.correct(x[:3]).astype(np.float32)
            assert rel_err(got3, ref[:3]) <= 1e-6
        err = rel_err(got, ref)
        worst = max(worst, err)
        if "Tanh" in case:
            assert float(np.nanmax(np.abs(got - ref))) <= 4e-7, case
        assert err <= 1e-6, f"{case}: max relative diff {err:.3g}"
    print(f"{case}: max rel diff {worst:.3g}")


@pytest.mark.parametrize("seed", [0, 1])
def test_pose_model_parity(seed, lib):
    model = graphs.pose_model(seed)
    blob = model.SerializeToString()
    ops = {n.op_type for n in model.graph.node}
    assert {"Gemm", "Tanh", "Where", "ArgMax", "Sqrt", "ReduceSum"} <= ops
    c = Corrector(blob, library=lib)
    for n in (1, 7, 300, 1000):
        x = graphs.random_poses(n, seed=seed + n)
        ref = ort_run(blob, x)
        got = c.correct(x)
        err = rel_err(got.astype(np.float32), ref)
        print(f"pose model seed={seed} N={n}: max rel diff {err:.3g}")
        assert err <= 2e-6
        q = got[:, 3:]
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)
        assert np.all(q[:, 0] >= 0)


MODELS = sorted((ROOT / "models").glob("*.onnx"))


@pytest.mark.parametrize("path", MODELS or [pytest.param(None, marks=pytest.mark.skip(
    reason="no shipped models in models/ yet"))], ids=lambda p: p.name if p else "none")
def test_shipped_model_parity(path, lib):
    blob = path.read_bytes()
    c = Corrector(blob, library=lib)
    x = graphs.random_poses(500, seed=3)
    x[:, :3] = x[:, :3] * 0.3 + np.array([0.0, -0.6, 0.5], dtype=np.float32)
    err = rel_err(c.correct(x).astype(np.float32), ort_run(blob, x))
    print(f"{path.name}: max rel diff {err:.3g}")
    assert err <= 1e-5


def test_physics_pipeline_one_pose_plan_equals_batch_plan_bit_for_bit(lib, tmp_path):
    """The demo's physics + PMC model is where one-pose programs do the most (557 nodes,
    3 launches per pose: sines, arctangents, Where, 3x3 products as dot products): each
    pose alone gives the 16-pose plan's bits, and onnxruntime's result."""
    from tools.models import demo_physics_pmc

    path = tmp_path / "physics+pmc-zhou.onnx"
    demo_physics_pmc(path)
    c = Corrector(path, library=lib)
    assert c._impl.n_steps <= 4, f"{c._impl.n_steps} launches per pose"
    lo, hi = (np.array(v, dtype=np.float32) for v in json.loads(c.metadata["input_bounds"]))
    x = graphs.random_poses(64, seed=21)
    x[:, :3] = lo + (hi - lo) * np.random.default_rng(4).uniform(0.05, 0.95, (64, 3))
    batch = c.correct(x)
    single = np.array([c.correct(row) for row in x])
    np.testing.assert_array_equal(single, batch)
    assert rel_err(batch.astype(np.float32), ort_run(path.read_bytes(), x)) <= 1e-5


@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.name)
def test_one_pose_plan_equals_batch_plan_bit_for_bit(path, lib):
    """The 1-pose plan runs fused scalar programs (k_scalar_program), the 16-pose plan the
    kernels one by one: the same operations in the same order, so the same bits."""
    c = Corrector(path, library=lib)
    x = graphs.random_poses(32, seed=12)
    x[:, :3] = x[:, :3] * 0.3 + np.array([0.0, -0.6, 0.5], dtype=np.float32)
    batch = c.correct(x)
    single = np.array([c.correct(row) for row in x])
    np.testing.assert_array_equal(single, batch)


def _bad_contract_models():
    g = graphs.G()
    yield "renamed input", g.model(g.op("Identity", ["measured"]), rename_input="measured"), "'measured'"
    g = graphs.G()
    yield "width 6", g.model(g.op("Concat", ["pose", g.f32(np.zeros((1, 1), np.float32))], axis=1),
                             width=6), "[N,7]"
    g = graphs.G()
    y = g.op("Pow", ["pose", g.f32(2.0)])
    yield "unsupported", g.model(y), "unsupported operator Pow in node"
    g = graphs.G()
    yield "wrong output width", g.model(g.op("Slice", ["pose", g.i64([0]), g.i64([6]), g.i64([1])])), "contract"
    g = graphs.G()
    yield "old opset", g.model(g.op("Identity", ["pose"]), opset=9), "opset 9"


@pytest.mark.parametrize("label,model,fragment", list(_bad_contract_models()),
                         ids=[m[0] for m in _bad_contract_models()])
def test_load_errors_name_the_problem(label, model, fragment, lib):
    with pytest.raises(PoseCorrError) as e:
        Corrector(model.SerializeToString(), library=lib)
    assert fragment in str(e.value)


def test_truncated_file_names_byte(lib):
    blob = graphs.pose_model().SerializeToString()
    with pytest.raises(PoseCorrError, match=r"truncated file at byte \d+"):
        Corrector(blob[: len(blob) // 2], library=lib)


def test_nan_input_leaves_output_untouched(lib):
    from posecorr.controller.runtime import load_library

    c = Corrector(graphs.pose_model().SerializeToString(), library=lib)
    L = load_library(lib)
    x = graphs.random_poses(4)
    x[2, 5] = np.nan
    out = np.full((4, 7), 7.0, dtype=np.float32)
    st = L.pc_run(c._impl.handle, x.ctypes.data, 4, out.ctypes.data)
    assert st != 0 and np.all(out == 7.0)
    assert L.pc_model_message(c._impl.handle).startswith(b"pose 2: qy is not finite")
    with pytest.raises(PoseCorrError):
        c.correct(x)
    assert L.pc_run(c._impl.handle, None, 0, None) == 0


# -- the pose checks of pc_run and the load-time row check ---------------------------------

PMC_ZHOU = ROOT / "models" / "pmc-zhou.onnx"
MLP_ZHOU = ROOT / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"


def _status(name: str) -> int:
    """The C enum value of a pc_status, from its name in posecorr.h."""
    return STATUS[name]


def _run_raw(c: _Corrector, lib: str, x: np.ndarray) -> tuple[int, np.ndarray, bytes]:
    from posecorr.controller.runtime import load_library

    L = load_library(lib)
    out = np.full(x.shape, 7.0, dtype=np.float32)
    st = L.pc_run(c._impl.handle, x.ctypes.data, len(x), out.ctypes.data)
    return st, out, L.pc_model_message(c._impl.handle)


def _without_metadata(path: Path, *keys: str) -> bytes:
    return graphs.signed(graphs.without_metadata(onnx.load(path), *keys))


def test_nonfinite_output_is_an_error_naming_the_output(lib):
    # without its box, the model takes a pose 1e30 m away and overflows
    c = Corrector(_without_metadata(PMC_ZHOU, "input_bounds"), library=lib)
    x = np.array([[1e30, -0.6, 0.5, 1, 0, 0, 0]], dtype=np.float32)
    st, _, msg = _run_raw(c, lib, x)
    assert st == _status("PC_ERR_RUNTIME")
    assert b"output 'corrected'" in msg and b"not finite" in msg
    with pytest.raises(PoseCorrError, match="not finite"):
        c.correct(x[0])
    # the same model corrects a pose in range
    assert np.all(np.isfinite(c.correct(np.array([0.1, -0.6, 0.5, 1, 0, 0, 0]))))


def test_non_unit_quaternion_is_an_error_for_every_model(lib):
    """With or without the exporter's posecorr_version: the contract is the file's."""
    x = graphs.random_poses(20, seed=3)
    for meta in ({}, {"posecorr_version": "0.1.0"}):
        g = graphs.G()
        y = g.op("Mul", ["pose", g.f32(np.full(7, 1.5, np.float32))])  # |q| = 1.5
        c = Corrector(g.model(y, metadata=meta).SerializeToString(), library=lib)
        st, out, msg = _run_raw(c, lib, x)
        assert st == _status("PC_ERR_RUNTIME") and b"not unit" in msg
        assert msg.startswith(b"pose 0: ") and np.all(out == 7.0)


def _with_metadata(path: Path, **meta: str) -> bytes:
    """The model with `meta` in place of its entries of those keys (a key given twice is
    refused)."""
    m = graphs.without_metadata(onnx.load(path), *meta)
    for k, v in meta.items():
        e = m.metadata_props.add()
        e.key, e.value = k, v
    return graphs.signed(m)


def test_input_bounds_flag_poses_outside_the_fitted_range(lib):
    bounds = "[[-0.7, -0.8, 0.1], [0.7, 0.2, 0.9]]"
    plain = Corrector(_without_metadata(MLP_ZHOU, "input_bounds"), library=lib)
    c = Corrector(_with_metadata(MLP_ZHOU, input_bounds=bounds), library=lib)
    inside = graphs.random_poses(30, seed=4)
    inside[:, :3] = inside[:, :3] * 0.5 + np.array([0.0, -0.3, 0.5], np.float32)
    np.testing.assert_array_equal(c.correct(inside), plain.correct(inside))
    for col, value in ((0, 1e30), (1, -0.81), (2, 0.95)):
        x = inside[:5].copy()
        x[3, col] = value
        st, out, msg = _run_raw(c, lib, x)
        assert st == _status("PC_ERR_RANGE"), msg
        assert msg.startswith(f"pose 3: {'xyz'[col]} = ".encode()) and b" is outside the range" in msg
        assert np.all(out == 7.0), "output must stay untouched"
    with pytest.raises(PoseCorrError, match="input_bounds"):
        Corrector(_with_metadata(MLP_ZHOU, input_bounds="[[0, 0], [1, 1]]"), library=lib)
    with pytest.raises(PoseCorrError, match="input_bounds"):
        Corrector(_with_metadata(MLP_ZHOU, input_bounds="[[1, 0, 0], [0, 1, 1]]"), library=lib)


def _mixing_models():
    g = graphs.G()
    total = g.op("ReduceSum", ["pose", g.i64([0])], keepdims=1)  # over the batch axis
    yield "reduce over batch", g.model(g.op("Sub", ["pose", total]))
    g = graphs.G()
    first = g.op("Gather", ["pose", g.i64([0])], axis=0)  # every row reads row 0
    yield "gather row 0", g.model(g.op("Add", ["pose", first]))
    g = graphs.G()
    gram = g.op("MatMul", [g.op("Transpose", ["pose"], perm=[1, 0]), "pose"])  # [7,7] over rows
    yield "Gram matrix of the batch", g.model(g.op("MatMul", ["pose", gram]))


@pytest.mark.parametrize("label,model", list(_mixing_models()),
                         ids=[m[0] for m in _mixing_models()])
def test_graph_mixing_rows_is_refused_at_load(label, model, lib):
    with pytest.raises(PoseCorrError, match="mixes rows") as e:
        Corrector(model.SerializeToString(), library=lib)
    assert e.value.status == _status("PC_ERR_GRAPH")


def test_an_output_of_another_shape_is_named_with_every_dimension(lib):
    """A rank-6 result (Where broadcasting the pose against [1,1,1,1,1,7]) read "rank 6
    (1 x 1)": the message printed two dimensions of any rank."""
    g = graphs.G()
    mask = g.op("Greater", ["pose", g.f32(np.zeros(7))])
    wide = g.op("Where", [mask, "pose", g.f32(np.zeros((1, 1, 1, 1, 1, 7)))])
    with pytest.raises(PoseCorrError) as e:
        Corrector(g.model(wide).SerializeToString(), library=lib)
    assert str(e.value).endswith("output 'corrected' is float32 of shape [1, 1, 1, 1, 1, 7] for N=1, the "
                                 "contract needs float32 [N,7]"), str(e.value)
    assert e.value.status == _status("PC_ERR_CONTRACT")


def test_a_graph_past_the_runtime_s_limits_names_the_limit(lib):
    """16384 initializers (the runtime indexes 16383) read "graph too large" and no more."""
    g = graphs.G()
    for k in range(16384):
        g.f32([float(k)])
    with pytest.raises(PoseCorrError) as e:
        Corrector(g.model("pose").SerializeToString(), library=lib)
    assert str(e.value).endswith("graph too large (more than 16383 initializers, the runtime's limit)")
    assert e.value.status == _status("PC_ERR_UNSUPPORTED")


def _caller_buffer_api(lib):
    """The library with pc_required_bytes and pc_load_into typed (the shim uses neither)."""
    import ctypes

    from posecorr.controller.runtime import _Error, load_library

    L = load_library(lib)
    vp, sz = ctypes.c_void_p, ctypes.c_size_t
    L.pc_required_bytes.argtypes = [ctypes.c_char_p, sz, vp, ctypes.POINTER(sz), ctypes.POINTER(_Error)]
    L.pc_load_into.argtypes = [ctypes.c_char_p, sz, vp, vp, sz, ctypes.POINTER(vp), ctypes.POINTER(_Error)]
    return L


def test_load_into_caller_buffer_matches_load_memory(lib):
    import ctypes

    from posecorr.controller.runtime import _Error

    L = _caller_buffer_api(lib)
    blob = MLP_ZHOU.read_bytes()
    need, err, handle = ctypes.c_size_t(), _Error(), ctypes.c_void_p()
    assert L.pc_required_bytes(blob, len(blob), None, ctypes.byref(need), ctypes.byref(err)) == 0
    buf = np.zeros(need.value, dtype=np.uint8)
    assert L.pc_load_into(blob, len(blob), None, buf.ctypes.data, need.value // 2,
                          ctypes.byref(handle), ctypes.byref(err)) == _status("PC_ERR_MEMORY")
    assert b"too small" in err.message
    assert L.pc_load_into(blob, len(blob), None, buf.ctypes.data, need.value,
                          ctypes.byref(handle), ctypes.byref(err)) == 0, err.message
    assert L.pc_arena_bytes(handle.value) < need.value
    print(f"{MLP_ZHOU.name}: pc_required_bytes {need.value}, arena {L.pc_arena_bytes(handle.value)}")
    x = graphs.poses_in_box(MLP_ZHOU, 300, seed=5)
    out = np.zeros_like(x)
    assert L.pc_run(handle.value, x.ctypes.data, len(x), out.ctypes.data) == 0
    np.testing.assert_array_equal(out, Corrector(MLP_ZHOU, library=lib).correct(x).astype(np.float32))


def _load_with(L, blob, **fields):
    """pc_load_memory with pc_options fields set; the model handle (blob must outlive it)."""
    import ctypes

    from posecorr.controller.runtime import _Error, _Options

    handle, err = ctypes.c_void_p(), _Error()
    opts = _Options(**fields)
    assert L.pc_load_memory(blob, len(blob), ctypes.byref(opts), ctypes.byref(handle),
                            ctypes.byref(err)) == 0, err.message
    return handle.value


def test_a_flag_the_library_does_not_know_is_refused(lib):
    """A PC_LOAD_* flag of a newer header was ignored without a word; every flag the header
    lists loads."""
    import ctypes

    from posecorr.controller.runtime import _Error, _Options, load_library

    L = load_library(lib)
    blob = MLP_ZHOU.read_bytes()
    known = 0
    for value in LOAD.values():
        known |= value
        L.pc_free(_load_with(L, blob, flags=value))
    handle, err = ctypes.c_void_p(), _Error()
    opts = _Options(flags=known + 1 if known & (known + 1) == 0 else known | 0x100)
    status = L.pc_load_memory(blob, len(blob), ctypes.byref(opts), ctypes.byref(handle), ctypes.byref(err))
    assert status == _status("PC_ERR_ARGUMENT") and handle.value is None
    assert err.message.decode() == (f"options.flags holds bits {opts.flags & ~known:#x} that no PC_LOAD_* flag of "
                                    "this library names")


@pytest.mark.parametrize("max_batch", [1, 16])
def test_load_in_place_reads_the_weights_where_they_lie(lib, max_batch):
    """PC_LOAD_IN_PLACE on an aligned file: the float32 weights are not copied (the arena
    shrinks by at least their bytes, counted with onnx), the results do not change, and
    PC_LOAD_NO_METADATA keeps the checks that come from the metadata."""
    from posecorr.controller.runtime import load_library

    L = load_library(lib)
    model = graphs.without_metadata(onnx.load(str(MLP_ZHOU)), "input_bounds")
    entry = model.metadata_props.add()
    entry.key, entry.value = "input_bounds", "[[-1, -1, -1], [1, 1, 1]]"
    blob = graphs.signed(model, aligned=True)
    weights = sum(len(t.raw_data) for t in model.graph.initializer
                  if t.data_type == onnx.TensorProto.FLOAT)
    copy = _load_with(L, blob, max_batch=max_batch)
    lean = _load_with(L, blob, max_batch=max_batch, flags=LEAN)
    assert L.pc_arena_bytes(copy) - L.pc_arena_bytes(lean) >= weights > 6000
    assert L.pc_metadata_count(lean) == 0 and L.pc_metadata_count(copy) > 0
    x = graphs.random_poses(40, seed=9)
    outs = []
    for h in (copy, lean):
        out = np.zeros_like(x)
        assert L.pc_run(h, x.ctypes.data, len(x), out.ctypes.data) == 0
        outs.append(out)
        far = x[:1].copy()
        far[0, 0] = 999.0  # outside input_bounds: refused whether or not the strings are kept
        assert L.pc_run(h, far.ctypes.data, 1, out.ctypes.data) == _status("PC_ERR_RANGE")
        L.pc_free(h)
    np.testing.assert_array_equal(outs[0], outs[1])


def test_lean_load_peak_is_a_small_multiple_of_the_arena(lib):
    """At max_batch 1 with the small-target options, pc_required_bytes (the load's peak) is
    within 4x the arena the model keeps, and pc_load_into needs no more than it reports."""
    import ctypes

    from posecorr.controller.runtime import _Error, _Options

    L = _caller_buffer_api(lib)
    blob = MLP_ZHOU.read_bytes()
    opts = _Options(max_batch=1, flags=LEAN, program_ops=32)
    need, err, handle = ctypes.c_size_t(), _Error(), ctypes.c_void_p()
    assert L.pc_required_bytes(blob, len(blob), ctypes.byref(opts), ctypes.byref(need),
                               ctypes.byref(err)) == 0, err.message
    buf = np.zeros(need.value, dtype=np.uint8)
    assert L.pc_load_into(blob, len(blob), ctypes.byref(opts), buf.ctypes.data,
                          need.value * 3 // 4, ctypes.byref(handle), ctypes.byref(err)) != 0
    assert L.pc_load_into(blob, len(blob), ctypes.byref(opts), buf.ctypes.data, need.value,
                          ctypes.byref(handle), ctypes.byref(err)) == 0, err.message
    arena = L.pc_arena_bytes(handle.value)
    print(f"lean load: pc_required_bytes {need.value}, arena {arena}")
    assert need.value <= 4 * arena


@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.name)
def test_lean_load_options_give_the_same_bits(lib, path):
    """Small program budgets (more, shorter programs), no programs at all, weights in place,
    the interpreter instead of the compiled programs: one pose at a time, every shipped
    model gives the default load's bits."""
    from posecorr.controller.runtime import load_library

    L = load_library(lib)
    blob = path.read_bytes()
    x = graphs.poses_in_box(blob, 12, seed=4)
    results = []
    for fields in ({}, {"program_ops": 16}, {"program_ops": 48, "flags": LEAN},
                   {"program_ops": 32, "flags": LEAN},
                   {"program_ops": 32, "flags": LEAN | LOAD["PC_LOAD_INTERPRET"]},
                   {"flags": LOAD["PC_LOAD_NO_PROGRAMS"]}, {"flags": PC_LOAD_INTERPRET}):
        h = _load_with(L, blob, max_batch=1, **fields)
        out = np.zeros_like(x)
        for i in range(len(x)):
            assert L.pc_run(h, x[i:i + 1].ctypes.data, 1, out[i:i + 1].ctypes.data) == 0
        results.append(out)
        L.pc_free(h)
    for r in results[1:]:
        np.testing.assert_array_equal(r, results[0])


PC_LOAD_INTERPRET = LOAD["PC_LOAD_INTERPRET"]


@pytest.fixture(scope="session")
def testing_lib(c_build):
    import ctypes

    T = ctypes.CDLL(str(c_build / "libposecorr_testing.so"))
    sz = ctypes.POINTER(ctypes.c_size_t)
    T.pc_test_program_steps.argtypes = [ctypes.c_void_p, sz, sz]
    T.pc_test_load.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.c_void_p, ctypes.c_void_p]
    return T


def test_shipped_models_run_compiled_programs(c_build, testing_lib):
    """Every one-pose program of every shipped model has its compiled form
    (runtime_c/programs_compiled.c is what `make programs` writes for models/), at the
    default program_ops and at the small boards' 32 (runtime_c/embedded), and
    PC_LOAD_INTERPRET runs none of them."""
    import ctypes

    from posecorr.controller.runtime import _Error, _Options

    T = testing_lib
    with graphs.build_lock(c_build):
        subprocess.run(["cmake", "--build", str(c_build), "--target", "posecorr-print-shapes"],
                       check=True, capture_output=True)
    check = subprocess.run(
        [sys.executable, str(ROOT / "runtime_c" / "tools" / "compile_programs.py"), "--check",
         "--shapes", str(c_build / "posecorr-print-shapes"), *map(str, MODELS)],
        capture_output=True, text=True)
    assert check.returncode == 0, check.stderr
    T.pc_load_memory.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.POINTER(_Options),
                                 ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(_Error)]
    for path in MODELS:
        blob = path.read_bytes()
        for flags, ops, want_compiled in ((0, 0, True), (0, 32, True), (PC_LOAD_INTERPRET, 0, False)):
            handle, err = ctypes.c_void_p(), _Error()
            opts = _Options(max_batch=16, flags=flags, program_ops=ops)
            assert T.pc_load_memory(blob, len(blob), ctypes.byref(opts), ctypes.byref(handle),
                                    ctypes.byref(err)) == 0, err.message
            compiled, interpreted = ctypes.c_size_t(), ctypes.c_size_t()
            T.pc_test_program_steps(handle, ctypes.byref(compiled), ctypes.byref(interpreted))
            T.pc_free(handle)
            if want_compiled:
                assert compiled.value >= 1 and interpreted.value == 0, path.name
            else:
                assert compiled.value == 0 and interpreted.value >= 1, path.name


def _layer_classes() -> tuple[set[int], set[int]]:
    """(pose vector sizes of the representations, table 1's hidden widths): the layers the
    project trains, from the trainer's own definitions."""
    from posecorr.train.base import encode_pose
    from posecorr.train.spec import ARCHITECTURES

    pose = np.array([[0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0]])
    vectors = {encode_pose(pose, rep).shape[1] for rep in ("pos", "eaa", "quat", "R", "zhou")}
    return vectors, {w for arch in ARCHITECTURES for w in arch}


def _chains(paths) -> list[tuple[str, list[int]]]:
    """(path, layer sizes) of each dense chain step in a step-path report."""
    return [(p, [int(k) for k in why.split()[2].rstrip(":").split("-")])
            for p, why in paths if why.startswith("dense chain ")]


def _specialised_by_rule(sizes: list[int], avx2: bool) -> bool:
    """A chain runs specialised when every layer goes into a hidden width from any trained
    size, or from a hidden width out to a pose vector."""
    vectors, hidden = _layer_classes()
    return avx2 and all((n in hidden and k in vectors | hidden) or (k in hidden and n in vectors)
                        for k, n in zip(sizes, sizes[1:]))


def test_chains_run_specialised_by_shape_class(lib, testing_lib):
    """Every dense chain of a shipped model runs the specialised kernels exactly when its
    layers are of a size the project trains (no table of shipped shapes); each shipped
    MLP's whole network (tansig, logsig or radbas) is one specialised chain."""
    avx2 = bool(testing_lib.pc_test_cpu_avx2())
    for path in MODELS:
        c = Corrector(path, library=lib)
        chains = _chains(c.step_paths())
        for p, sizes in chains:
            assert p == ("specialised" if _specialised_by_rule(sizes, avx2) else "general"), \
                (path.name, sizes)
        meta = c.metadata
        if meta.get("method") == "mlp":
            layers = [int(k) for k in meta["layers"].split("-")]
            assert chains == [("specialised" if avx2 else "general", layers)], path.name


@pytest.mark.parametrize("rep", ["pos", "eaa", "quat", "R", "zhou"])
def test_unshipped_table1_mlp_runs_specialised_and_matches_portable(rep, lib, testing_lib, tmp_path):
    """A tansig MLP of each representation with a table-1 architecture nobody shipped, drawn
    from a seed of its own (the same every run; all 75 passed when all were run), exported by
    the project's exporter after two epochs:
    the path report says its one dense chain, the whole network, runs the specialised
    kernels, and its outputs equal the portable build's bit for bit, one pose at a time
    and in batches."""
    import random

    from posecorr.train.spec import ARCHITECTURES
    from tools.models import unshipped_mlp

    if not testing_lib.pc_test_cpu_avx2():
        pytest.skip("the specialised layers are AVX2 kernels")
    shipped = set()
    for path in MODELS:
        meta = Corrector(path, library=lib).metadata
        if meta.get("method") == "mlp":
            shipped.add((meta["representation"], tuple(int(k) for k in meta["architecture"].split("-"))))
    hidden = random.Random(f"unshipped {rep}").choice([arch for arch in ARCHITECTURES if (rep, arch) not in shipped])
    label = f"{rep} {'-'.join(map(str, hidden))}"
    path = unshipped_mlp(rep, hidden, tmp_path / "unshipped.onnx")

    c = Corrector(path, library=lib)
    layers = [int(k) for k in c.metadata["layers"].split("-")]
    assert layers[1:-1] == list(hidden), label
    paths = c.step_paths()
    assert _chains(paths) == [("specialised", layers)], (label, paths)

    portable = graphs.build_runtime(BUILD / "portable", "-DPC_NO_AVX2=ON")
    p = Corrector(path, library=str(portable / "libposecorr.so"))
    assert {path for path, _ in _chains(p.step_paths())} <= {"general"}, label
    x = graphs.poses_in_box(path, 64, seed=5)
    one, one_portable = (np.vstack([k.correct(x[i]) for i in range(len(x))]) for k in (c, p))
    np.testing.assert_array_equal(one, one_portable, err_msg=label)
    np.testing.assert_array_equal(c.correct(x), p.correct(x), err_msg=label)
    np.testing.assert_array_equal(one, c.correct(x), err_msg=label)


@pytest.mark.parametrize("rep, activation", [("pos", "logsig"), ("eaa", "radbas"), ("quat", "satlin"),
                                             ("R", "tansig"), ("zhou", "radbas")])
def test_mlp_of_any_width_runs_one_dense_chain(rep, activation, lib, testing_lib, tmp_path):
    """An MLP of hidden widths outside table 1, drawn from a seed of its own (the same every
    run: one drawn anew failed CI where it drew pos, whose position-only decoder had come to
    normalise the quaternion while the shipped pos models, and so the compiled programs, kept
    the old graph), in every representation: a width of 1 to 64 that no specialised kernel has and one past
    64 (two passes of the block kernel), with a hidden activation the chain applies (tansig
    in registers; logsig, radbas, whose three nodes become the layer's activation, and
    satlin after the store): its whole network is one dense chain of general layers, between
    the compiled programs of its representation's encoder and decoder (nothing interpreted);
    its outputs equal the portable build's bit for bit, one pose at a time and in batches,
    and onnxruntime's to float32 rounding."""
    import random

    from tools.models import unshipped_mlp

    vectors, hidden_widths = _layer_classes()
    draw = random.Random(f"any width {rep}")
    hidden = (draw.choice([w for w in range(1, 65) if w not in hidden_widths]), draw.randint(65, 80))
    label = f"{rep} {'-'.join(map(str, hidden))} {activation}"
    path = unshipped_mlp(rep, hidden, tmp_path / "any_width.onnx", activation)

    c = Corrector(path, library=lib)
    layers = [int(k) for k in c.metadata["layers"].split("-")]
    paths = c.step_paths()
    assert [p for p, _ in paths if p == "interpreted"] == [], (label, paths)
    assert _chains(paths) == [("general", layers)], (label, paths)

    portable = graphs.build_runtime(BUILD / "portable", "-DPC_NO_AVX2=ON")
    p = Corrector(path, library=str(portable / "libposecorr.so"))
    x = graphs.poses_in_box(path, 64, seed=6)
    one, one_portable = (np.vstack([k.correct(x[i]) for i in range(len(x))]) for k in (c, p))
    np.testing.assert_array_equal(one, one_portable, err_msg=label)
    np.testing.assert_array_equal(c.correct(x), p.correct(x), err_msg=label)
    np.testing.assert_array_equal(one, c.correct(x), err_msg=label)
    # onnxruntime has its own tanh and exp (the runtime's tanh is within 3.2e-7 of tanh)
    # and sums the up to 80 terms of a layer in another order; near-random weights through
    # a one-unit layer and a decoder amplify that (2.5e-5 seen on eaa 1-65): 1e-4. The
    # bits are pinned above, by the portable build.
    assert rel_err(one, ort_run(path.read_bytes(), x)) <= 1e-4, label


def test_wide_sigmoid_layers_one_pose_match_onnxruntime(lib, tmp_path):
    """A logsig layer of more than 32 outputs in a one-pose chain applies its sigmoid once:
    the AVX2 chain once handed such a layer to the rows kernel, which applied it, and then
    applied it again (with batches the model was refused at load as mixing rows; with
    max_batch=1 it answered 0.62 away from onnxruntime on zhou 20-40)."""
    from tools.models import unshipped_mlp

    for hidden in ((20, 40), (33,), (70,)):
        path = unshipped_mlp("zhou", hidden, tmp_path / f"logsig-{len(hidden)}-{hidden[-1]}.onnx", "logsig")
        x = graphs.poses_in_box(path, 32, seed=3)
        c = Corrector(path, library=lib, max_batch=1)
        one = np.vstack([c.correct(x[i]) for i in range(len(x))]).astype(np.float32)
        assert rel_err(one, ort_run(path.read_bytes(), x)) <= 1e-5, hidden
        np.testing.assert_array_equal(one, Corrector(path, library=lib).correct(x).astype(np.float32))


def test_a_value_beyond_the_element_limit_names_the_batch(lib):
    """[N, 20000] holds 2^24 elements or fewer at a batch of 256, more at 4096: the refusal
    said "output dimension 1 is invalid (20000)", which no model could change; it names the
    batch now, and the model loads with a smaller one."""
    g = graphs.G()
    wide = g.op("MatMul", ["pose", g.f32(np.eye(7, 20000, dtype=np.float32))])
    blob = g.model(g.op("Slice", [wide, g.i64([0]), g.i64([7]), g.i64([1])])).SerializeToString()
    with pytest.raises(PoseCorrError, match=r"more than 2\^24 elements \(dimension 1 is 20000, the first 4096: "
                                            r"the batch.*a smaller max_batch may load it"):
        Corrector(blob, library=lib, max_batch=4096)
    x = graphs.op_inputs(300, seed=1)
    np.testing.assert_allclose(Corrector(blob, library=lib, max_batch=256).correct(x), ort_run(blob, x), rtol=1e-6)


def test_shim_checks_the_library_version(lib):
    from posecorr.controller import runtime

    text = (ROOT / "runtime_c" / "posecorr.h").read_text()
    major, minor, patch = (int(text.split(f"#define PC_VERSION_{k} ")[1].split()[0])
                           for k in ("MAJOR", "MINOR", "PATCH"))
    assert runtime.load_library(lib).pc_version() == major * 10000 + minor * 100 + patch
    assert runtime.EXPECTED_VERSION == (major, minor)
    assert runtime.version_compatible(major * 10000 + minor * 100 + patch + 7)
    assert runtime.version_compatible(major * 10000 + (minor + 1) * 100)
    assert not runtime.version_compatible((major + 1) * 10000 + minor * 100)
    assert not runtime.version_compatible(major * 10000 + (minor - 1) * 100)
    assert not runtime.version_compatible(None)


# -- the time input (optional second input `t` float32 [N], seconds) ---------------------

def ort_run_timed(model_bytes: bytes, x: np.ndarray, t: np.ndarray) -> np.ndarray:
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    s = ort.InferenceSession(model_bytes, so, providers=["CPUExecutionProvider"])
    return s.run(["corrected"], {"pose": x, "t": t.astype(np.float32)})[0]


@pytest.fixture(scope="session")
def drift_model(tmp_path_factory) -> tuple[Path, np.ndarray, np.ndarray]:
    """A PhysicsModel with drift fitted on 60 poses of a simulated Experiment III and
    exported (it has the input `t`); returns the file, the poses and their times."""
    from posecorr.export import to_onnx
    from posecorr.simulate import simulate
    from posecorr.train.physics import PhysicsModel

    table = simulate(3, seed=0).table
    idx = np.linspace(0, len(table.measured) - 1, 60).astype(int)
    m, r, t = table.measured[idx], table.reference[idx], table.extras["t"][idx]
    est = PhysicsModel(effects=("station", "mount", "drift")).fit(m, r, t=t)
    path = tmp_path_factory.mktemp("drift") / "drift.onnx"
    to_onnx(est, path, measured=m, reference=r, t=t)
    return path, m.astype(np.float32), t


def test_drift_model_with_time_matches_onnxruntime(drift_model, lib):
    path, m, t = drift_model
    blob = path.read_bytes()
    assert [i.name for i in onnx.load(path).graph.input] == ["pose", "t"]
    c = Corrector(path, library=lib)
    assert c.takes_time and not Corrector(MLP_ZHOU, library=lib).takes_time
    # 300 poses: the 256-, 16- and 1-pose plans all run; times spread over 10 h
    rng = np.random.default_rng(0)
    x = m[rng.integers(0, len(m), 300)]
    tt = rng.uniform(0.0, 36000.0, 300).astype(np.float32)
    got = c.correct(x, tt).astype(np.float32)
    ref = ort_run_timed(blob, x, tt)
    err = rel_err(got, ref)
    print(f"drift model, 300 poses with t: max rel diff C vs onnxruntime {err:.3g}")
    assert err <= 2e-6
    # time matters in this model: the same poses at t = 0 are corrected differently
    at_zero = ort_run_timed(blob, x, np.zeros(300, np.float32))
    assert np.abs(ref[:, :3] - at_zero[:, :3]).max() > 1e-4
    # t = None is t = 0 (the session's start), in C and in onnxruntime
    np.testing.assert_array_equal(c.correct(x).astype(np.float32),
                                  c.correct(x, np.zeros(300)).astype(np.float32))
    assert rel_err(c.correct(x).astype(np.float32), at_zero) <= 2e-6
    ort_c = Corrector(path, backend="onnxruntime")
    assert ort_c.takes_time
    np.testing.assert_array_equal(ort_c.correct(x, tt).astype(np.float32), ref)
    np.testing.assert_array_equal(ort_c.correct(x).astype(np.float32), at_zero)
    # one pose with its time is the batch's row
    np.testing.assert_array_equal(c.correct(x[7], tt[7]), c.correct(x, tt)[7])


def test_pc_run_timed_with_null_time_is_pc_run(drift_model, lib):
    from posecorr.controller.runtime import load_library

    L = load_library(lib)
    c = Corrector(drift_model[0], library=lib)
    x = drift_model[1][:20].copy()
    a, b, z = (np.full_like(x, 7.0) for _ in range(3))
    h = c._impl.handle
    assert L.pc_model_takes_time(h) == 1
    assert L.pc_run(h, x.ctypes.data, 20, a.ctypes.data) == 0
    assert L.pc_run_timed(h, x.ctypes.data, None, 20, b.ctypes.data) == 0
    zeros = np.zeros(20, np.float32)
    assert L.pc_run_timed(h, x.ctypes.data, zeros.ctypes.data, 20, z.ctypes.data) == 0
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, z)
    # a non-finite time is refused, naming the pose, output untouched
    bad = np.zeros(20, np.float32)
    bad[4] = np.inf
    out = np.full_like(x, 7.0)
    st = L.pc_run_timed(h, x.ctypes.data, bad.ctypes.data, 20, out.ctypes.data)
    assert st == _status("PC_ERR_NONFINITE") and np.all(out == 7.0)
    assert L.pc_model_message(h).startswith(b"pose 4: t is not finite")
    with pytest.raises(PoseCorrError, match="pose 4: t is not finite"):
        c.correct(x, bad)


def test_time_input_in_either_order_and_ignored_by_models_without_it(lib):
    x = graphs.random_poses(40, seed=11)
    t = np.linspace(0.0, 5000.0, 40).astype(np.float32)
    for t_first in (False, True):
        blob = graphs.time_model(t_first).SerializeToString()
        c = Corrector(blob, library=lib)
        assert c.takes_time
        assert rel_err(c.correct(x, t).astype(np.float32), ort_run_timed(blob, x, t)) <= 1e-6
    plain = Corrector(graphs.pose_model().SerializeToString(), library=lib)
    assert not plain.takes_time
    np.testing.assert_array_equal(plain.correct(x, t), plain.correct(x))
    with pytest.raises(ValueError, match="t must have shape"):
        plain.correct(x, t[:5])


def _bad_time_models():
    from onnx import TensorProto

    def model(**kw):
        g = graphs.G()
        return g.model(g.op("Identity", ["pose"]), **kw)

    yield "t int64", model(inputs_after=[graphs.time_input(TensorProto.INT64)]), "'t' has element type"
    yield "t rank 2", model(inputs_after=[graphs.time_input(shape=("N", 1))]), "'t' must have shape [N]"
    yield "t fixed N", model(inputs_after=[graphs.time_input(shape=(4,))]), "fixed batch size"
    yield "third input", model(inputs_after=[graphs.time_input(), graphs.time_input(name="u")]), "'u'"
    g = graphs.G()
    yield "t of width 7", g.model(g.op("Identity", ["t"]), rename_input="t"), "'t' must have shape [N]"
    g = graphs.G()
    only_t = g.model(g.op("Identity", ["t"]))
    del only_t.graph.input[:]
    only_t.graph.input.append(graphs.time_input())
    yield "no pose", only_t, "no input 'pose'"


@pytest.mark.parametrize("label,model,fragment", list(_bad_time_models()),
                         ids=[m[0] for m in _bad_time_models()])
def test_time_input_contract_errors(label, model, fragment, lib):
    with pytest.raises(PoseCorrError) as e:
        Corrector(model.SerializeToString(), library=lib)
    assert fragment in str(e.value) and e.value.status == _status("PC_ERR_CONTRACT")


# -- tools --------------------------------------------------------------------------------

@pytest.fixture(scope="session")
def pose_file(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("models") / "pose.onnx"
    p.write_bytes(graphs.signed(graphs.pose_model(metadata=graphs.BOUNDED)))
    return p


def test_posecorr_run_csv(c_build, pose_file):
    x = graphs.random_poses(40, seed=9)
    text = "x,y,z,qw,qx,qy,qz\n" + "\n".join(",".join(f"{v:.9g}" for v in row) for row in x) + "\n"
    r = subprocess.run([str(c_build / "posecorr-run"), str(pose_file)], input=text,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert lines[0] == "x,y,z,qw,qx,qy,qz"
    got = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]], dtype=np.float32)
    ref = ort_run(pose_file.read_bytes(), x)
    assert got.shape == (40, 7) and rel_err(got, ref) <= 2e-6


def test_tools_are_on_path_after_pip_install(pose_file):
    """The package's console scripts start the C tools it built: posecorr-run answers the
    same pose as the shim, posecorr-bench prints its JSON, posecorr-plan its plan, all from
    the venv's bin."""
    bindir = Path(sys.executable).parent
    run, bench = shutil.which("posecorr-run", path=bindir), shutil.which("posecorr-bench", path=bindir)
    assert run and bench, f"console scripts missing in {bindir}"
    x = graphs.poses_in_box(MLP_ZHOU, 3, seed=2)
    text = "\n".join(",".join(f"{v:.9g}" for v in row) for row in x) + "\n"
    r = subprocess.run([run, str(MLP_ZHOU)], input=text, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    got = np.array([[float(v) for v in ln.split(",")] for ln in r.stdout.split()], np.float32)
    want = Corrector(MLP_ZHOU).correct(x.astype(np.float64)).astype(np.float32)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    r = subprocess.run([bench, str(MLP_ZHOU), "--n", "200", "--batch", "50"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["batch_ns_per_pose"] > 0
    plan = shutil.which("posecorr-plan", path=bindir)
    assert plan, f"posecorr-plan missing in {bindir}"
    r = subprocess.run([plan, str(MLP_ZHOU)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.splitlines()[0].startswith("sop "), r
    for tool in (run, bench, plan):   # --help is usage on stdout, not a file named --help
        r = subprocess.run([tool, "--help"], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and r.stdout.startswith("usage: ") and "MODEL.onnx" in r.stdout, (tool, r)


def test_hot_swap_example_serves_every_pose_from_exactly_one_model(c_build, tmp_path):
    """runtime_c/examples/hot_swap.c: a new file replacing the model (atomically) is taken
    between two poses; every pose is answered, each by the model of its generation (bit for
    bit as the shim gives it); a corrupt file is refused while the running model serves."""
    import time

    first, second = ROOT / "models" / "pmc-zhou.onnx", MLP_ZHOU
    path = tmp_path / "model.onnx"
    shutil.copy(first, path)
    proc = subprocess.Popen([str(c_build / "pc_hot_swap"), str(path)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1)
    # The box of both models; poses enough to keep sending for the whole wait below (a busy
    # machine may take seconds to load the new file).
    x = graphs.poses_in_box(first, 10_500, seed=12)
    assert all(np.array_equal(a, b) for a, b in zip(graphs.model_box(first), graphs.model_box(second)))
    answers: list[tuple[int, np.ndarray]] = []

    def send() -> int:
        row = x[len(answers)]
        proc.stdin.write(",".join(f"{v:.9g}" for v in row) + "\n")
        proc.stdin.flush()
        gen, *vals = proc.stdout.readline().split(",")
        answers.append((int(gen), np.array(vals, dtype=np.float32)))
        return int(gen)

    def replace_with(data: bytes) -> None:
        tmp = tmp_path / "incoming.onnx"
        tmp.write_bytes(data)
        os.replace(tmp, path)

    def run_until(gen: int, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while send() != gen and time.monotonic() < deadline:
            time.sleep(0.002)

    try:
        for _ in range(100):
            assert send() == 1
        replace_with(second.read_bytes())
        run_until(2, 20.0)
        assert answers[-1][0] == 2, "the new model was not taken"
        replace_with(b"\x08\x07not an onnx file")
        run_until(3, 0.5)  # the loader polls every 10 ms: plenty of time to refuse it
        for _ in range(50):
            send()
    finally:
        proc.stdin.close()
        err = proc.stderr.read()
        proc.wait(timeout=30)
    assert proc.returncode == 0, err
    gens = [g for g, _ in answers]
    assert gens == sorted(gens) and set(gens) == {1, 2}, "a pose went back to the old model"
    assert "loaded generation 2" in err and f"refused {path}" in err, err
    for gen, model in ((1, first), (2, second)):
        idx = [i for i, (g, _) in enumerate(answers) if g == gen]
        want = Corrector(model).correct(x[idx].astype(np.float64)).astype(np.float32)
        got = np.stack([answers[i][1] for i in idx])
        np.testing.assert_array_equal(got, want)
    print(f"hot swap: {gens.count(1)} poses by the first model, {gens.count(2)} by the second")


def test_posecorr_run_time_column(c_build, drift_model, pose_file):
    """An 8th value per line is t: a model that takes time gets it (as onnxruntime with
    the same t), a line without it is t = 0, and a model without time ignores it."""
    path, m, t = drift_model
    x, tt = m[:12], t[:12].astype(np.float32)

    def run(model, rows):
        text = "x,y,z,qw,qx,qy,qz,t\n" + "\n".join(",".join(f"{v:.9g}" for v in row)
                                                  for row in rows) + "\n"
        r = subprocess.run([str(c_build / "posecorr-run"), str(model)], input=text,
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        lines = r.stdout.strip().splitlines()
        assert lines[0] == "x,y,z,qw,qx,qy,qz,t"
        return np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]], np.float32)

    blob = path.read_bytes()
    with_t = run(path, np.column_stack([x, tt]))
    assert with_t.shape == (12, 7) and rel_err(with_t, ort_run_timed(blob, x, tt)) <= 2e-6
    without = run(path, x)
    assert rel_err(without, ort_run_timed(blob, x, np.zeros(12, np.float32))) <= 2e-6
    assert np.abs(with_t - without).max() > 1e-4
    plain = run(pose_file, np.column_stack([x, tt]))
    np.testing.assert_array_equal(plain, run(pose_file, x))


def test_posecorr_run_binary_time(c_build, drift_model):
    """--binary --timed reads records of 8 float32, t last: the poses of the text stream with
    the same t; 7-float records of a model that takes time are t = 0, said once on stderr."""
    path, m, t = drift_model
    x, tt = m[:12].astype(np.float32), t[:12].astype(np.float32)
    tool = str(c_build / "posecorr-run")

    def run(records, *flags):
        return subprocess.run([tool, str(path), "--binary", *flags], input=records.astype("<f4").tobytes(),
                              capture_output=True, timeout=60)

    timed = run(np.column_stack([x, tt]), "--timed")
    assert timed.returncode == 0 and timed.stderr == b"", timed.stderr
    got = np.frombuffer(timed.stdout, "<f4").reshape(-1, 7)
    blob = path.read_bytes()
    assert rel_err(got, ort_run_timed(blob, x, tt)) <= 2e-6
    untimed = run(x)
    assert untimed.returncode == 0
    assert rel_err(np.frombuffer(untimed.stdout, "<f4").reshape(-1, 7),
                   ort_run_timed(blob, x, np.zeros(12, np.float32))) <= 2e-6
    assert untimed.stderr.decode().count("\n") == 1 and "--timed" in untimed.stderr.decode()
    partial = run(np.column_stack([x, tt])[:2].ravel()[:12], "--timed")  # 1.5 records of 8
    assert partial.returncode == 1 and b"partial record of 16 bytes" in partial.stderr
    assert b"32 bytes: 8 float32" in partial.stderr and len(partial.stdout) == 28
    text = subprocess.run([tool, str(path), "--timed"], input="", capture_output=True, text=True, timeout=60)
    assert text.returncode == 2 and "--timed is for --binary" in text.stderr


def test_posecorr_run_reports_line_numbers(c_build, pose_file):
    text = "0.1,0.2,0.3,1,0,0,0\n0.1,0.2,0.3,1,0,0,0\n0.1,oops,0.3,1,0,0,0\n"
    r = subprocess.run([str(c_build / "posecorr-run"), str(pose_file), "--strict"], input=text,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "line 3" in r.stderr
    assert len(r.stdout.strip().splitlines()) == 2
    r = subprocess.run([str(c_build / "posecorr-run"), str(pose_file), "--strict"],
                       input="0.1,0.2,0.3,1,0,0,0\nnan,0,0,1,0,0,0\n", capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 1 and "line 2" in r.stderr and "non-finite" in r.stderr


def test_posecorr_run_binary(c_build, pose_file):
    x = graphs.random_poses(10, seed=4)
    r = subprocess.run([str(c_build / "posecorr-run"), str(pose_file), "--binary"],
                       input=x.tobytes(), capture_output=True, timeout=60)
    assert r.returncode == 0, r.stderr
    got = np.frombuffer(r.stdout, dtype=np.float32).reshape(-1, 7)
    assert rel_err(got, ort_run(pose_file.read_bytes(), x)) <= 2e-6


def test_posecorr_bench_json(c_build, pose_file):
    r = subprocess.run([str(c_build / "posecorr-bench"), str(pose_file), "--n", "2000",
                        "--batch", "300"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    for k in ("single_pose_median_us", "single_pose_p99_us", "batch_ns_per_pose", "load_us"):
        assert isinstance(d[k], float) and d[k] > 0
    assert d["single_pose_p99_us"] >= d["single_pose_median_us"]
    assert d["steps"] < d["nodes"]  # folding, aliasing and fusion removed work
    # the path report: one entry per one-pose step, the shim's words
    assert [(e["path"], e["why"]) for e in d["paths"]] == \
        Corrector(pose_file, library=str(c_build / "libposecorr.so")).step_paths()


def test_info_reports_the_path_of_each_step(lib):
    """`posecorr info` says what each one-pose step of the shipped zhou MLP runs."""
    model = ROOT / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"
    r = subprocess.run([sys.executable, "-c", "import sys; from posecorr.cli import main; "
                        f"sys.exit(main(['info', '--json', {str(model)!r}]))"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    steps = json.loads(r.stdout)["one_pose_steps"]
    assert [(e["path"], e["why"]) for e in steps] == Corrector(model).step_paths()
    assert any(e["why"].startswith("dense chain 9-20-20-20-20-9: ") for e in steps)


def test_portable_kernels_match_avx2_bit_for_bit(lib):
    """The AVX2 dense kernels picked at load sum in the portable kernels' order."""
    portable = graphs.build_runtime(BUILD / "portable", "-DPC_NO_AVX2=ON")
    for path in sorted((ROOT / "models").glob("*.onnx")):
        x = graphs.poses_in_box(path, 300, seed=11)
        a = Corrector(path, library=lib).correct(x)
        b = Corrector(path, library=str(portable / "libposecorr.so")).correct(x)
        np.testing.assert_array_equal(a, b, err_msg=path.name)
        # one pose at a time: the one-pose plans (unrolled chains, compiled programs)
        ones = [Corrector(path, library=lib), Corrector(path, library=str(portable / "libposecorr.so"))]
        a1, b1 = (np.vstack([c.correct(x[i:i + 1]) for i in range(40)]) for c in ones)
        np.testing.assert_array_equal(a1, b1, err_msg=path.name)
        np.testing.assert_array_equal(a1, a[:40], err_msg=path.name)


def test_portable_checks_refuse_as_the_sse2_ones(lib):
    """pc_run's input checks, SSE2 on x86-64 and portable in a -DPC_NO_AVX2 build, accept the
    same poses and refuse the same ones with the same status and message (the first bad pose
    and column named), in a batch and one pose at a time."""
    portable = graphs.build_runtime(BUILD / "portable", "-DPC_NO_AVX2=ON")
    path = ROOT / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"
    fast, plain = Corrector(path, library=lib), Corrector(path, library=str(portable / "libposecorr.so"))
    good = graphs.poses_in_box(path, 8, seed=3)
    np.testing.assert_array_equal(fast.correct(good), plain.correct(good))
    breaks = {"qx is not finite": (2, (4,), np.nan),
              "x is not finite": (5, (0,), np.inf),
              "qz is not finite": (1, (6,), -np.inf),
              "qw, qx, qy, qz has norm 1.010000": (6, (3, 4, 5, 6), None)}
    for col in range(3):
        for side in (-100.0, 100.0):    # each bound of each position column
            breaks[f"{'xyz'[col]} = {side:.3f} m ({side})"] = (col + 2, (col,), side)
    for expected, (row, cols, value) in breaks.items():
        x = good.copy()
        x[row, list(cols)] = x[row, list(cols)] * 1.01 if value is None else value
        for poses, pose in ((x, row), (x[row:row + 1], 0)):
            refusals = []
            for c in (fast, plain):
                with pytest.raises(PoseCorrError) as info:
                    c.correct(poses)
                refusals.append((info.value.status, str(info.value)))
            assert refusals[0] == refusals[1], expected
            assert f"pose {pose}: " in refusals[0][1] and expected.split(" (")[0] in refusals[0][1], refusals[0]


def test_a_model_without_bounds_still_refuses_non_finite_poses(lib):
    """pc_run leaves the finite tests to the box and the reach where both are finite (a pose
    inside the box is finite); without them (PC_LOAD_ALLOW_UNBOUNDED) an infinite position
    would pass the box [-inf, inf] and an infinite result the reach: both are still refused,
    on both builds, one pose and in a batch."""
    portable = graphs.build_runtime(BUILD / "portable", "-DPC_NO_AVX2=ON")
    blob = _without_metadata(MLP_ZHOU, "input_bounds", "correction_reach")
    x = graphs.poses_in_box(MLP_ZHOU, 4, seed=2)
    for library in (lib, str(portable / "libposecorr.so")):
        c = Corrector(blob, library=library)
        for value in (np.inf, -np.inf, np.nan):
            bad = x.copy()
            bad[1, 0] = value
            for poses, pose in ((bad, 1), (bad[1:2], 0)):
                with pytest.raises(PoseCorrError, match=f"pose {pose}: x is not finite"):
                    c.correct(poses)
    # a result overflowing to infinity: the model without its box, a pose 1e30 m away
    c = Corrector(_without_metadata(PMC_ZHOU, "input_bounds", "correction_reach"), library=lib)
    far = np.array([[1e30, -0.6, 0.5, 1, 0, 0, 0]], dtype=np.float32)
    with pytest.raises(PoseCorrError, match="pose 0: x of output 'corrected' is not finite"):
        c.correct(far)


def test_input_quaternion_test_is_the_double_rule_at_its_edges_on_both_builds(lib):
    """pc_run sums |q|^2 in float first and in double only outside a band inside the
    tolerance (formulas.h, PC_QUAT_NORM2_BAND): quaternions scaled to |q|^2 a few 1e-8 around
    the tolerance's ends (0.998001, 1.002001) and the band's (1 -+ 0.00199) are accepted
    exactly when the double sum (numpy, float64 in column order) is inside [0.998001,
    1.002001], on the SSE2 and the portable build, pose by pose."""
    portable = str(graphs.build_runtime(BUILD / "portable", "-DPC_NO_AVX2=ON") / "libposecorr.so")
    base = graphs.poses_in_box(MLP_ZHOU, 8, seed=9)
    rows = []
    for target in (0.998001, 1.002001, 1 - 0.00199, 1 + 0.00199):
        for k in range(-40, 41, 4):
            x = base[len(rows) % len(base)].copy()
            x[3:] = (x[3:] * np.sqrt(target * (1 + k * 1e-8))).astype(np.float32)
            rows.append(x)
    x = np.array(rows, dtype=np.float32)
    q = x[:, 3:].astype(np.float64)
    n2 = ((q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1]) + q[:, 2] * q[:, 2]) + q[:, 3] * q[:, 3]
    expected = (n2 >= 0.998001) & (n2 <= 1.002001)
    assert 0 < expected.sum() < len(x)
    for library in (lib, portable):
        c = Corrector(MLP_ZHOU, library=library)
        got = []
        for i in range(len(x)):
            try:
                c.correct(x[i:i + 1])
                got.append(True)
            except PoseCorrError as e:
                assert e.status == _status("PC_ERR_QUATERNION"), str(e)
                got.append(False)
        assert got == expected.tolist(), library


def _reach_rule(x: np.ndarray, y: np.ndarray, metres: np.float32, radians: np.float32) -> np.ndarray:
    """formulas.h's reach rule (pc_move_of, pc_within_reach) in float32, each sum in column
    order, for float32 inputs x and outputs y; the metadata's numbers as the loader keeps
    them."""
    d = y[:, :3] - x[:, :3]
    d2 = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2]
    q, qi = y[:, 3:], x[:, 3:]
    total = lambda a: ((a[:, 0] + a[:, 1]) + a[:, 2]) + a[:, 3]
    n2, dot, n_in2 = total(q * q), total(q * qi), total(qi * qi)
    cos2 = np.float32(np.cos(0.5 * np.float64(radians)) ** 2 if radians < np.pi else 0.0)
    return (d2 <= metres * metres) & (dot * dot >= (cos2 * n_in2) * n2)


def _steps(v: float, k: int) -> np.float32:
    """The float32 k steps (ulps) from float32(v)."""
    x = np.float32(v)
    for _ in range(abs(k)):
        x = np.nextafter(x, np.float32(np.inf if k > 0 else -np.inf))
    return x


def _one_by_one(c: _Corrector, x: np.ndarray, y: np.ndarray) -> list:
    """For each pose alone: "kept" (its output y's row) or the refusal's status and text."""
    answers = []
    for i in range(len(x)):
        try:
            np.testing.assert_array_equal(c.correct(x[i:i + 1]), y[i:i + 1])
            answers.append("kept")
        except PoseCorrError as e:
            answers.append((e.status, str(e)))
    return answers


def test_output_checks_refuse_as_the_rule_and_alike_on_both_builds(lib):
    """pc_run's output check (formulas.h's pc_move_of and pc_within_reach, the finite test
    left to the reach) refuses exactly the poses the reach rule refuses, computed here in
    float32: the
    shipped zhou MLP with its correction_reach cut to the median correction (of position,
    then of rotation), and to float32 steps around three poses' own corrections (where the
    last bit of each sum decides), pose by pose and in one batch, the same status and
    message from both builds."""
    portable = str(graphs.build_runtime(BUILD / "portable", "-DPC_NO_AVX2=ON") / "libposecorr.so")
    x = graphs.poses_in_box(MLP_ZHOU, 120, seed=5)
    y = Corrector(MLP_ZHOU, library=lib).correct(x).astype(np.float32)  # float32 results
    moved = np.linalg.norm(y[:, :3].astype(np.float64) - x[:, :3], axis=1)
    cos = np.abs(np.sum(y[:, 3:].astype(np.float64) * x[:, 3:], axis=1))
    turned = 2 * np.arccos(np.minimum(cos / np.linalg.norm(x[:, 3:], axis=1)
                                      / np.linalg.norm(y[:, 3:], axis=1), 1.0))
    cases = [(None, np.median(moved), 4.0), (None, 1.0, np.median(turned))]
    cases += [(k, _steps(moved[k], step), 4.0) for k in range(3) for step in range(-3, 4)]
    cases += [(k, 1.0, _steps(turned[k], step)) for k in range(3) for step in range(-3, 4)]
    probed: dict = {}
    for pose, metres, radians in cases:
        metres, radians = np.float32(metres), np.float32(radians)
        model = graphs.without_metadata(onnx.load(MLP_ZHOU), "correction_reach")
        entry = model.metadata_props.add()
        entry.key, entry.value = "correction_reach", f"[{float(metres)!r}, {float(radians)!r}]"
        blob = graphs.signed(model)
        kept = _reach_rule(x, y, metres, radians)
        if pose is None:
            assert 0 < kept.sum() < len(x)
        else:
            probed.setdefault((pose, radians < 4.0), []).append(bool(kept[pose]))
        answers = []
        for library in (lib, portable):
            c = Corrector(blob, library=library)
            answers.append(_one_by_one(c, x, y))
            assert [a == "kept" for a in answers[-1]] == kept.tolist(), (metres, radians)
            assert all("pose 0: output 'corrected' moves the pose by" in a[1] for a in answers[-1] if a != "kept")
            if not kept.all():
                with pytest.raises(PoseCorrError, match=f"pose {int(np.argmin(kept))}: output 'corrected' moves"):
                    c.correct(x)
        assert answers[0] == answers[1]
    # each probed pose is refused at its lowest step and kept at its highest: the steps
    # straddle the reach, so the last bit of its sums was compared
    assert all(seq[0] is False and seq[-1] is True for seq in probed.values()), probed


# -- sanitizers, valgrind, install ---------------------------------------------------------

@pytest.fixture(scope="session")
def asan_build() -> Path:
    return graphs.build_runtime(BUILD / "asan", "-DPC_BUILD_TESTS=ON", "-DPC_SANITIZE=ON",
                                build_type="RelWithDebInfo")


def _san_env():
    env = dict(os.environ)
    env["ASAN_OPTIONS"] = "detect_leaks=1:abort_on_error=1"
    env["UBSAN_OPTIONS"] = "print_stacktrace=1:halt_on_error=1"
    return env


def test_asan_unit_tests(asan_build):
    """The unit tests under the sanitizers, with the shipped models (each also loaded from
    its file with PC_LOAD_IN_PLACE, whose bytes pc_load_file frees)."""
    models = sorted(str(p) for p in (ROOT / "models").glob("*.onnx"))
    r = subprocess.run([str(asan_build / "pc_unit_tests"), *models], capture_output=True, text=True,
                       timeout=300, env=_san_env())
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-4000:]
    assert r.stdout.strip().endswith(" 0 failed")


def test_asan_valid_and_malformed_models(asan_build, tmp_path):
    files = []
    for name, f in sorted(CASES.items()):
        for k, m in enumerate(f()):
            p = tmp_path / f"{name}_{k}.onnx"
            onnx.save(m, p)
            files.append(str(p))
    for label, m, _ in _bad_contract_models():
        p = tmp_path / f"bad_{label.replace(' ', '_')}.onnx"
        onnx.save(m, p)
        files.append(str(p))
    pose = tmp_path / "pose.onnx"
    onnx.save(graphs.pose_model(), pose)
    small = tmp_path / "small.onnx"
    onnx.save(CASES["unary_Abs"]()[0], small)
    exe = str(asan_build / "pc_load_check")
    # inputs that crashed earlier versions (found by the fuzzer)
    files += [str(p) for p in sorted((ROOT / "runtime_c" / "tests" / "regress").glob("*"))]
    runs = [[exe, *files, str(pose)],
            [exe, "--prefixes", str(small), str(pose)],
            [exe, "--flips", "1500", str(pose), "--flips", "1500", str(small)],
            [exe, "--random", "3000"]]
    for cmd in runs:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=_san_env())
        assert r.returncode == 0, " ".join(cmd[:3]) + "\n" + r.stdout[-2000:] + r.stderr[-4000:]
        assert "0 failures" in r.stdout
    # The valid models must all have loaded.
    r = subprocess.run([exe, *files[:10]], capture_output=True, text=True, env=_san_env())
    assert "10 loaded" in r.stdout


@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not on PATH")
def test_valgrind_posecorr_run(c_build, pose_file):
    x = graphs.random_poses(20, seed=5)
    text = "\n".join(",".join(f"{v:.9g}" for v in row) for row in x) + "\n"
    r = subprocess.run(["valgrind", "--error-exitcode=3", "--leak-check=full",
                        "--errors-for-leak-kinds=definite,indirect", "-q",
                        str(c_build / "posecorr-run"), str(pose_file)],
                       input=text, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-4000:]
    assert len(r.stdout.strip().splitlines()) == 20


CONSUMER_C = r"""
#include <posecorr.h>
#include <stdio.h>
int main(int argc, char **argv) {
    pc_model *m; pc_error e;
    float in[7] = {0.1f, -0.5f, 0.4f, 1.0f, 0.0f, 0.0f, 0.0f}, out[7];
    if (pc_load_file(argv[1], NULL, &m, &e) != PC_OK) { fprintf(stderr, "%s\n", e.message); return 1; }
    if (pc_run(m, in, 1, out) != PC_OK) return 2;
    printf("%.9g %.9g %.9g %.9g %.9g %.9g %.9g\n", out[0], out[1], out[2], out[3], out[4], out[5], out[6]);
    pc_free(m);
    return 0;
}
"""


def test_install_find_package_and_pkg_config(c_build, pose_file, tmp_path):
    """The installed library, found by CMake and by pkg-config, at the header's version (the
    CMake project said 0.2.0, the header 0.6.0: find_package(posecorr 0.6) refused it)."""
    text = (ROOT / "runtime_c" / "posecorr.h").read_text()
    version = ".".join(text.split(f"#define PC_VERSION_{k} ")[1].split()[0] for k in ("MAJOR", "MINOR", "PATCH"))
    prefix = tmp_path / "prefix"
    subprocess.run(["cmake", "--install", str(c_build), "--prefix", str(prefix)], check=True,
                   capture_output=True)
    libdir = next(p.parent for p in prefix.rglob("libposecorr.so"))
    assert (libdir / f"libposecorr.so.{version}").exists()
    assert (prefix / "include" / "posecorr.h").exists()
    assert (prefix / "bin" / "posecorr-run").exists()
    env = dict(os.environ, LD_LIBRARY_PATH=str(libdir))
    x = np.array([[0.1, -0.5, 0.4, 1.0, 0.0, 0.0, 0.0]], dtype=np.float32)
    ref = ort_run(pose_file.read_bytes(), x)[0]
    # find_package
    proj = tmp_path / "consumer"
    proj.mkdir()
    (proj / "main.c").write_text(CONSUMER_C)
    (proj / "CMakeLists.txt").write_text(
        "cmake_minimum_required(VERSION 3.16)\nproject(consumer C)\n"
        f"find_package(posecorr {version} EXACT REQUIRED)\nadd_executable(consumer main.c)\n"
        "target_link_libraries(consumer PRIVATE posecorr::posecorr)\n")
    subprocess.run(["cmake", "-S", str(proj), "-B", str(proj / "b"),
                    f"-DCMAKE_PREFIX_PATH={prefix}"], check=True, capture_output=True)
    subprocess.run(["cmake", "--build", str(proj / "b")], check=True, capture_output=True)
    r = subprocess.run([str(proj / "b" / "consumer"), str(pose_file)], capture_output=True,
                       text=True, env=env, check=True)
    np.testing.assert_allclose([float(v) for v in r.stdout.split()], ref, rtol=0, atol=2e-6)
    # pkg-config
    if shutil.which("pkg-config") is None:
        pytest.skip("pkg-config not on PATH")
    penv = dict(env, PKG_CONFIG_PATH=str(libdir / "pkgconfig"))
    assert subprocess.run(["pkg-config", "--modversion", "posecorr"], env=penv, capture_output=True, text=True,
                          check=True).stdout.strip() == version
    # pkg-config escapes for a shell, byte by byte: a space or a non-ASCII prefix comes out as
    # backslashed bytes, as make's $(shell ...) and a shell's eval expect them
    flags = shlex.split(os.fsdecode(subprocess.run(["pkg-config", "--cflags", "--libs", "posecorr"], env=penv,
                                                   capture_output=True, check=True).stdout))
    exe = tmp_path / "consumer_pc"
    subprocess.run([os.environ.get("CC", "cc"), str(proj / "main.c"), "-o", str(exe), *flags],
                   check=True, capture_output=True)
    r = subprocess.run([str(exe), str(pose_file)], capture_output=True, text=True, env=env,
                       check=True)
    np.testing.assert_allclose([float(v) for v in r.stdout.split()], ref, rtol=0, atol=2e-6)


def test_a_program_links_against_the_library_pip_placed(pose_file, tmp_path):
    """A C program built against the copy beside the package, with the header beside it, finds
    it at run time: that copy had the installed layout's SONAME, libposecorr.so.0, which no
    file there is named, and no header."""
    lib_file = library_path()
    exe = tmp_path / "consumer"
    # the header beside the library, as a wheel install has it (no source checkout)
    assert (lib_file.parent / "posecorr.h").read_bytes() == (ROOT / "runtime_c" / "posecorr.h").read_bytes()
    subprocess.run([os.environ.get("CC", "cc"), "-std=c99", f"-I{lib_file.parent}", "-x", "c", "-",
                    "-o", str(exe), f"-L{lib_file.parent}", "-lposecorr", "-lm"],
                   input=CONSUMER_C, text=True, check=True, capture_output=True)
    r = subprocess.run([str(exe), str(pose_file)], capture_output=True, text=True, check=True,
                       env=dict(os.environ, LD_LIBRARY_PATH=str(lib_file.parent)))
    x = np.array([[0.1, -0.5, 0.4, 1.0, 0.0, 0.0, 0.0]], dtype=np.float32)
    np.testing.assert_allclose([float(v) for v in r.stdout.split()], ort_run(pose_file.read_bytes(), x)[0],
                               rtol=0, atol=2e-6)


def test_shim_load_flags_are_the_headers():
    from posecorr.controller import runtime

    assert (runtime._ALLOW_UNBOUNDED, runtime._ALLOW_UNSIGNED) == (LOAD["PC_LOAD_ALLOW_UNBOUNDED"],
                                                                   LOAD["PC_LOAD_ALLOW_UNSIGNED"])


def test_the_runtime_readme_counts_what_the_code_holds():
    """runtime_c/README.md's counts are the code's: the compiled programs' functions, and
    the files (numbered steps, each naming its file) that adding an operator touches."""
    import re

    readme = (ROOT / "runtime_c" / "README.md").read_text()
    compiled = (ROOT / "runtime_c" / "programs_compiled.c").read_text()
    count = int(re.search(r"pc_n_compiled_programs = (\d+);", compiled)[1])
    assert f"its {count} functions are" in readme
    words = {3: "three", 4: "four", 5: "five", 6: "six"}
    section = readme[readme.index("## Adding an operator"):readme.index("## Tests")]
    steps = re.findall(r"^\d+\. .*?`([^`]+)`", section, flags=re.M)   # each step's first file
    assert section.startswith(f"## Adding an operator ({words[len(steps)]} files)"), (section[:60], steps)
    for step in steps:
        assert (ROOT / step).exists() or (ROOT / "runtime_c" / step).exists(), step
