"""One check layer for every back end (issue 21, item 2).

Hostile models and poses go through libposecorr (the C back end, the judge: its checks
are run.c's and api.c's) and through onnxruntime behind `posecorr.controller.checks`; each
case must be refused by both, with the same status and, word for word, the same message
naming the pose and column and what was expected. Through `posecorr apply` each case ends in
one line naming file, row and column, exit 2, and no output file. The shipped models carry
the box they were fitted in, and every export writes it.
"""
from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from onnx import helper, numpy_helper  # noqa: E402

from posecorr.controller import checks  # noqa: E402
from posecorr.controller.runtime import Corrector, PoseCorrError  # noqa: E402
from posecorr.data import PoseTable, write_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))
import graphs  # noqa: E402
from test_hardening import _run  # noqa: E402
from test_hostile import _checksums  # noqa: E402

PMC_ZHOU = ROOT / "models" / "pmc-zhou.onnx"
MLP_ZHOU = ROOT / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"
SHIPPED = sorted((ROOT / "models").glob("*.onnx"))
BACKENDS = ("c", "onnxruntime")
S = checks.Status


def _both(model, poses, t=None) -> list[PoseCorrError]:
    """The error each back end raises for `correct(poses, t)` (fails when one accepts)."""
    errors = []
    for backend in BACKENDS:
        c = Corrector(model, backend=backend)
        with pytest.raises(PoseCorrError) as info:
            c.correct(poses, t)
        errors.append(info.value)
    return errors


def _same(errors: list[PoseCorrError], status: S, *fragments: str) -> str:
    c, ort = errors
    assert str(ort) == str(c), "the back ends disagree"
    assert c.status == ort.status == int(status), (c.status, ort.status, str(c))
    for fragment in fragments:
        assert fragment in str(c), str(c)
    return str(c)


def _load_errors(blob: bytes) -> list[PoseCorrError]:
    errors = []
    for backend in BACKENDS:
        with pytest.raises(PoseCorrError) as info:
            Corrector(blob, backend=backend)
        errors.append(info.value)
    return errors


def _edited(path: Path, **meta: str) -> onnx.ModelProto:
    model = onnx.load(path)
    kept = {e.key: e.value for e in model.metadata_props}
    kept.update(meta)
    del model.metadata_props[:]
    for key, value in sorted(kept.items()):
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    return model


def _inside(n: int = 12, seed: int = 0) -> np.ndarray:
    return graphs.poses_in_box(PMC_ZHOU, n, seed).astype(np.float64)


# --- the status table is libposecorr's -------------------------------------------------------

def test_statuses_and_names_are_the_librarys():
    from posecorr.controller.runtime import load_library

    lib = load_library()
    header = (ROOT / "runtime_c" / "posecorr.h").read_text()
    body = header[header.index("typedef enum pc_status {"):header.index("} pc_status;")]
    names = [ln.split(",")[0].split("=")[0].strip() for ln in body.splitlines()[1:]
             if ln.strip().startswith("PC_")]
    assert names[-1] == "PC_STATUS_COUNT"
    assert [f"PC_{'OK' if s == S.OK else 'ERR_' + s.name}" for s in S] == names[:-1]
    for status, name in checks.STATUS_NAMES.items():
        assert lib.pc_status_name(int(status)).decode() == name
    lo = int(header.split("#define PC_OPSET_MIN ")[1].split()[0])
    hi = int(header.split("#define PC_OPSET_MAX ")[1].split()[0])
    assert checks.OPSETS == (lo, hi)


# --- poses the shipped models refuse, on both back ends ---------------------------------------

@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
@pytest.mark.cpu_floats
def test_shipped_models_carry_their_training_box(path):
    """Each shipped model's input_bounds is the box to_onnx computes from its training
    positions (the seeded data regenerated), and poses inside are corrected alike."""
    from tools.models import SPECS, experiment_data
    from posecorr.export.onnx_export import input_bounds

    spec = next(s for s in SPECS if f"{s.name}.onnx" == path.name)
    data = _experiment(spec.experiment, experiment_data)
    box = json.loads({e.key: e.value for e in onnx.load(path).metadata_props}["input_bounds"])
    # The simulation's matrix products round by the CPU's BLAS kernels (OpenBLAS picks them at
    # run time), so the regenerated box agrees with the stored one to rounding, not to the bit.
    np.testing.assert_allclose(box, input_bounds(data["measured"][data["train"]]), rtol=1e-12, atol=0)
    x = graphs.poses_in_box(path, 50, seed=3).astype(np.float64)
    c, o = (Corrector(path, backend=b).correct(x) for b in BACKENDS)
    assert np.abs(c - o).max() < 1e-5


_DATA: dict[int, dict] = {}


def _experiment(experiment: int, make) -> dict:
    if experiment not in _DATA:
        _DATA[experiment] = make(experiment)
    return _DATA[experiment]


@pytest.mark.parametrize("column,value", [(0, 999.0), (1, 5.0), (2, -0.5), (0, -3e30), (1, -0.7975)])
def test_a_pose_outside_the_box_is_refused_alike(column, value):
    x = _inside()
    x[7, column] = value
    lo, hi = graphs.model_box(PMC_ZHOU)
    name = "xyz"[column]
    text = _same(_both(PMC_ZHOU, x), S.RANGE, f"pose 7: {name} = {checks.decimal(np.float32(value))} m is outside "
                 f"the range the model was fitted on, {checks.decimal(lo[column])} to "
                 f"{checks.decimal(hi[column])} m (metadata input_bounds)")
    assert text.startswith("pose outside the fitted range: ")


def test_range_messages_agree_on_many_values():
    """run.c's pc_decimal and checks.decimal write every value alike (C is the judge)."""
    rng = np.random.default_rng(7)
    values = np.concatenate([rng.uniform(-5, 5, 40), 10.0 ** rng.uniform(-3, 12, 30),
                             -(10.0 ** rng.uniform(-3, 12, 30)), [0.2055, -0.2277, 999.9995, 1e9, -1e9, 9.9996e12, -9.9996e12,
                                                                  0.2049999, 3.4e38]])
    c, o = (Corrector(PMC_ZHOU, backend=b) for b in BACKENDS)
    lo, hi = graphs.model_box(PMC_ZHOU)
    compared = 0
    for v in values.astype(np.float32):
        x = _inside(1)
        x[0, 0] = v
        if lo[0] <= v <= hi[0]:
            continue
        with pytest.raises(PoseCorrError) as ec:
            c.correct(x)
        with pytest.raises(PoseCorrError) as eo:
            o.correct(x)
        assert str(eo.value) == str(ec.value)
        compared += 1
    assert compared > 90


@pytest.mark.parametrize("value, text", [(1e9, "1.000e9"), (-3e30, "-3.000e30"), (9.9996e12, "1.000e13"),
                                         (9.9994e12, "9.999e12"), (999999999.0, "999999999.000"),
                                         (np.inf, "inf"), (-np.inf, "-inf"), (np.nan, "nan")])
def test_large_values_are_written_as_a_mantissa_and_a_power(value, text):
    """A value of 1e9 or more reads as a number, inf and nan (a reach or a distance) as such,
    and the text parses back to the value within its rounding."""
    assert checks.decimal(value) == text
    assert float(text) == pytest.approx(value, rel=5e-4, nan_ok=True)


def test_large_values_parse_back_within_their_rounding():
    for v in 10.0 ** np.random.default_rng(3).uniform(9, 38, 200):
        assert float(checks.decimal(v)) == pytest.approx(v, rel=5.1e-4)
        assert float(checks.decimal(-v, 6)) == pytest.approx(-v, rel=5.1e-7)


@pytest.mark.parametrize("value", [np.inf, -np.inf, np.nan])
def test_a_non_finite_pose_is_refused_alike(value):
    x = _inside()
    x[3, 5] = value
    _same(_both(PMC_ZHOU, x), S.NONFINITE, "pose 3: qy is not finite (expected a finite number)")


@pytest.mark.parametrize("value", [1e39, -1e300])
def test_a_value_beyond_float32_is_refused_as_outside_not_as_not_finite(value):
    """A finite float64 beyond float32's range was cast to inf and refused as "not finite"
    (on onnxruntime after numpy's warning). Now both back ends refuse it, one pose or a batch,
    with no warning, in libposecorr's own words for float32's largest value of that sign
    outside input_bounds, but the value as given; a model without input_bounds, as not fitting
    in float32."""
    unbounded = graphs.signed(graphs.without_metadata(onnx.load(PMC_ZHOU), "input_bounds"))
    x = _inside()
    largest = x.astype(np.float32)
    x[3, 0], largest[3, 0] = value, np.copysign(checks.FLOAT32_MAX, value)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for poses, pose in ((x, 3), (x[3], 0)):
            said = _same(_both(PMC_ZHOU, poses), S.RANGE)
            with pytest.raises(PoseCorrError) as library:
                Corrector(PMC_ZHOU).correct(largest if poses.ndim == 2 else largest[3])
            as_given = checks.decimal(np.float32(largest[3, 0])), checks.decimal(value)
            assert said == str(library.value).replace(*as_given) and as_given[1] in said
            errors = []
            for backend in BACKENDS:
                with pytest.raises(PoseCorrError) as info:
                    Corrector(unbounded, backend=backend, allow_unbounded=True).correct(poses)
                errors.append(info.value)
            _same(errors, S.RANGE, f"pose {pose}: x = {value:.7g} m does not fit in float32")


@pytest.mark.parametrize("scale,norm", [(3.0, "3.000000"), (0.0, "0.000000"), (1.01, "1.010000")])
def test_a_quaternion_that_is_not_unit_is_refused_not_normalised(scale, norm):
    """The model normalises its input: a norm-3 or zero quaternion used to come out as a unit
    one. Now both back ends (and the shim's single-pose path) refuse it."""
    x = _inside()
    x[4, 3:] *= scale
    _same(_both(PMC_ZHOU, x), S.QUATERNION, f"pose 4: the quaternion qw, qx, qy, qz has norm {norm} "
          "(expected a unit quaternion: norm within 0.001 of 1)")
    one = _both(PMC_ZHOU, x[4])
    _same(one, S.QUATERNION, "pose 0: the quaternion qw, qx, qy, qz has norm")


@pytest.mark.parametrize("position", [(0.0, 0.0, 0.0), (999.0, -5.0, 3.0)])
def test_a_zero_quaternion_is_named_before_the_box(position):
    """SteamVR's "no pose" is all zeros: its position is outside the box too, and what is wrong
    is the quaternion. Both back ends check a pose's clauses in one order: finite, the unit
    quaternion, the box."""
    x = _inside()
    x[2, :3], x[2, 3:] = position, 0.0
    _same(_both(PMC_ZHOU, x), S.QUATERNION, "pose 2: the quaternion qw, qx, qy, qz has norm 0.000000")
    x[2, 4] = np.nan
    _same(_both(PMC_ZHOU, x), S.NONFINITE, "pose 2: qx is not finite")


def test_the_quaternion_tolerance_is_the_tables():
    """A quaternion the pose tables accept (norm within 1e-3) is corrected; one beyond is
    refused, on both back ends."""
    from posecorr.data import QUAT_NORM_TOLERANCE

    x = _inside(2)
    unit = x.copy()
    x[0, 3:] *= 1 + 0.9 * QUAT_NORM_TOLERANCE
    x[1, 3:] *= 1 - 0.9 * QUAT_NORM_TOLERANCE
    for backend in BACKENDS:
        # the model normalises its input: corrected as the unit quaternion would be
        # (float32 on both: a few ulps of the scaled quaternion's rounding)
        np.testing.assert_allclose(Corrector(PMC_ZHOU, backend=backend).correct(x),
                                   Corrector(PMC_ZHOU, backend=backend).correct(unit), atol=2e-6)
    x[1, 3:] *= 1 - 0.3 * QUAT_NORM_TOLERANCE
    _same(_both(PMC_ZHOU, x), S.QUATERNION, "pose 1: the quaternion qw, qx, qy, qz has norm 0.9988")


# --- results that are not poses ---------------------------------------------------------------

def _posecorr_graph(factor: list[float], op: str = "Mul") -> bytes:
    g = graphs.G()
    y = g.op(op, ["pose", g.f32(np.array(factor, np.float32))])
    return graphs.signed(g.model(y, metadata=graphs.BOUNDED))


def test_an_infinite_output_is_refused_alike():
    blob = _posecorr_graph([1, 1, 1, 1, 1, 1, 0], op="Div")  # qz / 0
    x = _inside()
    x[:, 6] = np.abs(x[:, 6]) + 0.1
    x[:, 3:] /= np.linalg.norm(x[:, 3:], axis=1, keepdims=True)
    _same(_both(blob, x), S.RUNTIME, "pose 0: qz of output 'corrected' is not finite (expected a finite number)")


def test_a_zero_output_quaternion_is_refused_alike():
    blob = _posecorr_graph([1, 1, 1, 0, 0, 0, 0])
    _same(_both(blob, _inside()), S.RUNTIME, "pose 0: the quaternion qw, qx, qy, qz of output 'corrected' is not "
          "unit (expected |q|^2 within 0.002 of 1)")


# --- models refused at load -------------------------------------------------------------------

def _used_weight(model: onnx.ModelProto) -> onnx.TensorProto:
    """The largest float initialiser a node reads."""
    used = {i for n in model.graph.node for i in n.input}
    return max((t for t in model.graph.initializer if t.data_type == onnx.TensorProto.FLOAT and t.name in used),
               key=lambda t: int(np.prod(t.dims)))


@pytest.mark.parametrize("value,raw", [(np.nan, True), (np.inf, True), (-np.inf, False)])
def test_a_model_with_non_finite_weights_is_refused_at_load(value, raw):
    model = onnx.load(MLP_ZHOU)
    tensor = _used_weight(model)
    w = numpy_helper.to_array(tensor).copy()
    w.flat[5] = value
    tensor.CopyFrom(numpy_helper.from_array(w, tensor.name) if raw else
                    helper.make_tensor(tensor.name, onnx.TensorProto.FLOAT, w.shape, w.ravel().tolist()))
    blob = graphs.signed(model)
    text = _same(_load_errors(blob), S.MALFORMED,
                 f"tensor '{tensor.name}' holds a non-finite value at element 5 (expected finite weights)")
    assert text.startswith(f"model of {len(blob)} bytes: ")


@pytest.mark.parametrize("blob", [b"hello, this is not a model\n", b"id,meas_x,meas_y\n0,1,2\n"])
def test_bytes_that_are_no_onnx_file_are_named_so_by_both_back_ends(blob, tmp_path):
    """A text file given as the model: both back ends (and `info`) say what it is not, not
    only which byte the protobuf parser stumbled on."""
    from posecorr.controller import read_info

    text = _same(_load_errors(blob), S.MALFORMED, "not a valid ONNX model (")
    path = tmp_path / "m.onnx"
    path.write_bytes(blob)
    with pytest.raises(ValueError) as info:
        read_info(path)
    assert str(info.value).split(": ", 1)[1] == text.split(": ", 1)[1]


def test_weights_read_in_place_are_checked_too(tmp_path):
    """PC_LOAD_IN_PLACE reads an aligned file's weights where they lie: still checked."""
    import ctypes

    from posecorr.controller.runtime import _Error, _Options, load_library
    model = onnx.load(MLP_ZHOU)
    tensor = _used_weight(model)
    w = numpy_helper.to_array(tensor).copy()
    w.flat[0] = np.nan
    tensor.CopyFrom(numpy_helper.from_array(w, tensor.name))
    blob = graphs.signed(model, aligned=True)
    lib = load_library()
    handle, err = ctypes.c_void_p(), _Error()
    st = lib.pc_load_memory(blob, len(blob), ctypes.byref(_Options(flags=1)), ctypes.byref(handle),
                            ctypes.byref(err))
    assert st == S.MALFORMED and b"non-finite value at element 0" in err.message and not handle.value


@pytest.mark.parametrize("op,domain", [("Pow", ""), ("Gelu", "com.microsoft")])
def test_an_operator_outside_the_list_is_refused_alike(op, domain):
    g = graphs.G()
    if op == "Pow":
        y = g.op("Pow", ["pose", g.f32(np.float32(1.0))])
    else:
        y = g.op("Gelu", ["pose"])
    model = g.model(y, metadata=graphs.BOUNDED)
    if domain:
        model.opset_import.append(helper.make_opsetid(domain, 1))
    assert op not in checks.operator_list()
    node = next(n for n in model.graph.node if n.op_type == op)
    node.domain = domain
    node = node.name
    where = f" (domain '{domain}')" if domain else ""
    _same(_load_errors(graphs.signed(model)), S.UNSUPPORTED, f"unsupported operator {op}{where} in node '{node}'")


@pytest.mark.parametrize("bounds,fragment", [
    ("[[NaN, -1, -1], [1, 1, 1]]", "metadata input_bounds is '[[NaN, -1, -1], [1, 1, 1]]', expected [[x_lo"),
    ("[[-1, -1, -1], [1, Infinity, 1]]", "metadata input_bounds is '[[-1, -1, -1], [1, Infinity, 1]]'"),
    ("[[-1e400, -1, -1], [1, 1, 1]]", "metadata input_bounds: a bound is not a finite float32 in column 0"),
    ("[[-1, -1, -1], [1, 1, 1e39]]", "metadata input_bounds: a bound is not a finite float32 in column 2"),
    ("[[-1, 1, -1], [1, -1, 1]]", "metadata input_bounds: lower bound above upper bound in column 1"),
    ("[[-1, -1], [1, 1]]", "expected [[x_lo, y_lo, z_lo], [x_hi, y_hi, z_hi]] in metres"),
    ("[[-1, -1, true], [1, 1, 1]]", "metadata input_bounds is"),
    # an integer of 5000 digits is infinite in C; Python's json refused it (int digit limit)
    ("[[-" + "1" * 5000 + ", -1, -1], [1, 1, 1]]", "metadata input_bounds: a bound is not a finite float32 in column 0"),
    # C quotes a value up to a NUL byte
    ("[[-1, -1, -1], [1, 1, 1]]\0x", "metadata input_bounds is '[[-1, -1, -1], [1, 1, 1]]', expected"),
])
def test_edited_input_bounds_are_refused_at_load(bounds, fragment):
    blob = graphs.signed(_edited(PMC_ZHOU, input_bounds=bounds))
    _same(_load_errors(blob), S.MALFORMED, fragment)


def _json_numbers(text: str) -> list[float] | None:
    """The numbers of a JSON array of numbers, by Python's own parser (the truth both back
    ends must agree with), None where it is no such array."""
    def flat(value):
        if isinstance(value, list):
            return [x for v in value for x in flat(v)]
        return [value] if isinstance(value, (int, float)) and not isinstance(value, bool) else [None]
    try:
        got = flat(json.loads(text, parse_constant=lambda name: None))
    except ValueError:
        return None
    return None if None in got else [float(x) for x in got]


# Bounds metadata as JSON writes it and as hands edit it: pretty-printed, tabs, and what is no
# JSON (a number with two points, numbers without commas, closings left over, '+1', '.5', '01').
BOUNDS_TEXTS = ["[[-1, -1, -1], [1, 1, 1]]", "[\n [\n  -1,\n  -1,\n  -1\n ],\n [1, 1, 1]\n]",
                "[[-1,\t-1,\t-1],\r\n[1,1,1]]", " [[-1, -1, -1], [1, 1, 1]] ", "[[-1, -1, -1], [[1], [1, [1]]]]",
                "[[-1.2.3, -1, -1], [1, 1, 1]]", "[[-1 -1 -1], [1 1 1]]", "[[-1, -1, -1], [1, 1, 1]]]]",
                "[[-1, -1, -1], [+1, 1, 1]]", "[[-1, -1, -1], [.5, 1, 1]]", "[[-1, -1, -1], [01, 1, 1]]",
                "[[-1, -1, -1], [1., 1, 1]]", "[[-1, -1, -1,], [1, 1, 1]]", "[[-1, -1, -1] [1, 1, 1]]",
                "[[-1, -1, -1], [1, 1, 1e]]", "[[-1, -1, -1], [1, 1, 1E+0]]", "[[-1, -1, -1], [1, 1, -0]]",
                "[[-1, -1, -1], [1, 1, 1]] x", "[[-1, -1, -1], [], [1, 1, 1]]", "[[-1, -1, -1], [1, 1, 1]\u000b]",
                "[" * 40 + "-1, -1, -1, 1, 1, 1" + "]" * 40]


@pytest.mark.parametrize("text", BOUNDS_TEXTS)
def test_bounds_are_read_as_json_reads_them(text):
    """The C parser of input_bounds read '-1.2.3' as two numbers and '1 1 1' without commas,
    and refused pretty-printed JSON (a line break between numbers), where the other back end
    (json.loads) decided the opposite: both now load exactly what JSON's grammar holds."""
    numbers = _json_numbers(text)
    blob = graphs.signed(_edited(PMC_ZHOU, input_bounds=text))
    if numbers is not None and len(numbers) == 6 and text.count("[") <= checks.JSON_DEPTH:
        # Loaded alike, the box read alike: a pose above its top is refused with its figure.
        above = np.array([0.0, 0.0, numbers[5] + 0.5, 1.0, 0.0, 0.0, 0.0])
        errors = []
        for backend in BACKENDS:
            with pytest.raises(PoseCorrError) as info:
                Corrector(blob, backend=backend).correct(above)
            errors.append(info.value)
        _same(errors, S.RANGE, f"{checks.decimal(numbers[2])} to {checks.decimal(numbers[5])} m (metadata input_bounds)")
    else:
        _same(_load_errors(blob), S.MALFORMED, "metadata input_bounds is")


@pytest.mark.parametrize("text", ["[" + " " * 300 + "0.5, 1.0]", "[0.5" + "0" * 300 + ", 1.0]", "[\n 0.5,\n 1.0\n]"])
def test_a_long_or_pretty_reach_loads_alike(text):
    """The onnxruntime back end cut correction_reach at 255 bytes, which C reads whole."""
    blob = graphs.signed(_edited(PMC_ZHOU, correction_reach=text))
    for backend in BACKENDS:
        Corrector(blob, backend=backend)


@pytest.mark.parametrize("key", ["input_bounds", "time_bounds", "correction_reach"])
def test_a_bound_given_twice_is_refused_at_load(key):
    """onnx.checker refuses a key given twice; libposecorr's checks took the last value and
    pc_metadata_lookup the first, so a file could say one box and enforce another."""
    model = onnx.load(PMC_ZHOU)
    value = {e.key: e.value for e in model.metadata_props}.get(key, "[0, 1]")
    for _ in range(2):
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    _same(_load_errors(graphs.signed(model)), S.MALFORMED, f"metadata {key} appears twice")


# --- time outside the fitted span -------------------------------------------------------------

@pytest.fixture(scope="module")
def drift(tmp_path_factory) -> tuple[Path, PoseTable, list[float]]:
    """A PhysicsModel with drift fitted on 60 poses of a simulated Experiment III, exported:
    (file, its training table, its time_bounds)."""
    from posecorr.export import to_onnx
    from posecorr.export.onnx_export import time_bounds
    from posecorr.simulate import simulate
    from posecorr.train.physics import PhysicsModel

    table = simulate(3, seed=0).table
    idx = np.linspace(0, len(table.measured) - 1, 60).astype(int)
    m, r, t = table.measured[idx], table.reference[idx], table.extras["t"][idx]
    est = PhysicsModel(effects=("station", "mount", "drift")).fit(m, r, t=t)
    path = tmp_path_factory.mktemp("drift") / "drift.onnx"
    report = to_onnx(est, path, measured=m, reference=r, t=t)
    assert report["metadata"]["time_bounds"] == time_bounds(t)
    sub = PoseTable(m[:, :3], m[:, 3:], r[:, :3], r[:, 3:], {"t": t})
    return path, sub, time_bounds(t)


def test_time_bounds_are_the_training_span_widened(drift):
    """Widened by half the span on both sides, but from no earlier than 60 s before the
    session's start: times are seconds since it."""
    _, table, span = drift
    t = table.extras["t"]
    margin = max(0.5 * (t.max() - t.min()), 60.0)
    assert t.min() - margin < -60.0     # the session's start bounds this table's span
    assert span == pytest.approx([-60.0, t.max() + margin], abs=1e-9)
    from posecorr.export.onnx_export import time_bounds
    assert time_bounds(np.array([1000.0, 1100.0])) == pytest.approx([940.0, 1160.0])
    assert time_bounds(np.array([-30.0, 10.0])) == pytest.approx([-90.0, 70.0])


def _drift_alone(seed: int):
    """drift alone fitted on 60 poses of a simulated Experiment III: the fit pins its time
    constant at the lower bound (a minute), where 1 - exp(-t / tau) overflows float32 an
    hour and a half before the session's start."""
    from posecorr.simulate import simulate
    from posecorr.train.physics import PhysicsModel

    table = simulate(3, seed=seed).table
    idx = np.linspace(0, len(table.measured) - 1, 60).astype(int)
    m, r, t = table.measured[idx], table.reference[idx], table.extras["t"][idx]
    return PhysicsModel(effects=("drift",)).fit(m, r, t=t), m, r, t


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_drift_alone_exports_with_the_reach_of_its_formula(tmp_path, seed):
    """`posecorr fit E3.csv --effects drift` failed at export ("correction_reach is
    '[null, ...]'"): the reach was drawn at times down to hours before the session's start.
    Now the reach is finite and within the formula's: |d| (exp(60 s / tau) - 1) at most on
    the span, |d| (1 - exp(-t / tau)) at least on the training times."""
    from posecorr.export import to_onnx

    est, m, r, t = _drift_alone(seed)
    d, tau = est.params_["drift"][:3], est.params_["drift"][3]
    assert tau == pytest.approx(60.0, rel=1e-3)   # the case of the bug (see _drift_alone)
    report = to_onnx(est, tmp_path / "drift.onnx", measured=m, reference=r, t=t)
    reach = report["metadata"]["correction_reach"][0]
    size = float(np.linalg.norm(d))
    assert 2 * size * np.max(1 - np.exp(-t / tau)) + 0.01 - 1e-5 <= reach
    assert reach <= 2 * size * (np.exp(60.0 / tau) - 1) + 0.01 + 1e-5


def test_a_model_with_non_finite_corrections_is_not_exported(tmp_path):
    """Given a span reaching far before the start, drift's correction overflows: the export
    is refused in one line naming the drawn pose and its time, and writes nothing."""
    from posecorr.export import ExportError, to_onnx

    est, m, r, t = _drift_alone(0)
    path = tmp_path / "drift.onnx"
    with pytest.raises(ExportError) as info:
        to_onnx(est, path, measured=m, reference=r, t=t, time_bounds=[-1e5, 1e5])
    text = str(info.value)
    assert "\n" not in text and not path.exists()
    assert "the model's correction of pose " in text and "drawn inside input_bounds and time_bounds" in text
    assert "is not finite" in text and "cannot be given a correction_reach" in text
    when = float(text.split(" at t = ")[1].split(" s ")[0])
    tau = est.params_["drift"][3]
    assert -when / tau > np.log(np.finfo(np.float32).max)   # exp(-t / tau) overflows float32 there


@pytest.mark.parametrize("when", [-100000.0, 1e7, 1e39, np.nan])
def test_a_time_outside_the_span_is_refused_alike(drift, when):
    path, table, span = drift
    x, t = table.measured[:10].copy(), table.extras["t"][:10].copy()
    t[6] = when
    if np.isnan(when):
        _same(_both(path, x, t), S.NONFINITE, "pose 6: t is not finite (expected seconds since the session's start)")
        return
    lo, hi = np.float32(span)
    _same(_both(path, x, t), S.RANGE, f"pose 6: t = {checks.decimal(when)} s is outside the span the "
          f"model was fitted on, {checks.decimal(lo)} to {checks.decimal(hi)} s (metadata time_bounds)")
    if when == -100000.0:  # without the check (a span opened wide) kilometres away: the reach
        wide = graphs.signed(_edited(path, time_bounds="[-1e30, 1e30]"))  # catches it still
        errors = _both(wide, x[6:7], t[6:7])
        text = _same(errors, S.RUNTIME, "pose 0: output 'corrected' moves the pose by ",
                     "(metadata correction_reach)")
        assert float(text.split("moves the pose by ")[1].split(" m")[0]) > 1000.0


def test_no_time_is_time_zero_and_is_checked_too(drift):
    """pc_run without times runs a time model at t = 0: outside a span that excludes 0 it is
    refused (C: pc_run_timed with t NULL), the same on onnxruntime."""
    path, table, _ = drift
    blob = graphs.signed(_edited(path, time_bounds="[10, 20]"))
    _same(_both(blob, table.measured[:3]), S.RANGE, "pose 0: no t given, so t = 0 s, outside the span the model "
          "was fitted on, 10.000 to 20.000 s (metadata time_bounds): the model takes each pose's time")
    for backend in BACKENDS:  # inside the span: corrected
        assert np.all(np.isfinite(Corrector(blob, backend=backend).correct(table.measured[:3], np.full(3, 15.0))))


@pytest.mark.parametrize("span,fragment", [("[5, 1]", "lower bound above upper bound in column 0"),
                                           ("[-1e400, 1]", "a bound is not a finite float32 in column 0"),
                                           ("[0, 1, 2]", "expected [t_lo, t_hi] in seconds")])
def test_edited_time_bounds_are_refused_at_load(drift, span, fragment):
    path, _, _ = drift
    _same(_load_errors(graphs.signed(_edited(path, time_bounds=span))), S.MALFORMED,
          "metadata time_bounds", fragment)


# --- every export carries its bounds ----------------------------------------------------------

def test_an_export_without_training_data_is_refused(tmp_path):
    from posecorr.export import ExportError, to_onnx
    from posecorr.train.pmc import PMC

    t = _inside(80).copy()
    model = PMC(representation="zhou").fit(t, t)
    with pytest.raises(ExportError, match="input_bounds need the training positions"):
        to_onnx(model, tmp_path / "m.onnx", parity="skip")
    with pytest.raises(ExportError, match="input_bounds: lower bound above upper bound in column 0"):
        to_onnx(model, tmp_path / "m.onnx", parity="skip", input_bounds=[[1, -1, -1], [0, 1, 1]],
                correction_reach=[0.1, 0.1])
    assert not (tmp_path / "m.onnx").exists()
    report = to_onnx(model, tmp_path / "m.onnx", measured=t)
    lo, hi = report["metadata"]["input_bounds"]
    extent = t[:, :3].max(0) - t[:, :3].min(0)
    np.testing.assert_allclose(lo, t[:, :3].min(0) - np.maximum(extent / 2, 0.1))
    np.testing.assert_allclose(hi, t[:, :3].max(0) + np.maximum(extent / 2, 0.1))


# --- through the command line: one line, exit 2, no output ------------------------------------

def _table(tmp_path: Path, edit=None, t=None, n: int = 30) -> Path:
    x = _inside(n, seed=5)
    extras = {} if t is None else {"t": t}
    table = PoseTable(x[:, :3], x[:, 3:], x[:, :3], x[:, 3:], extras)
    path = tmp_path / "in.csv"
    write_table(table, path)
    if edit:
        lines = path.read_text().splitlines()
        header = lines[0].split(",")
        row, column, value = edit
        cells = lines[row - 1].split(",")
        cells[header.index(column)] = value
        lines[row - 1] = ",".join(cells)
        path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("column,value", [("meas_x", "999"), ("meas_y", "5")])
def test_apply_refuses_a_pose_outside_the_box(tmp_path, capsys, backend, column, value):
    table = _table(tmp_path, (17, column, value))
    out = tmp_path / "out.csv"
    before = _checksums(tmp_path)
    code, err, escaped = _run(["apply", str(PMC_ZHOU), str(table), "-o", str(out), "--backend", backend], capsys)
    assert escaped is None and code == 2, err
    assert len(err.strip().splitlines()) == 1
    name = column.split("_")[1]
    assert f"row 17, column {column}: " in err and f": {name} = {value}.000 m is outside the range the model was " \
        "fitted on, " in err and "pose 0" not in err
    assert _checksums(tmp_path) == before


@pytest.mark.parametrize("backend", BACKENDS)
def test_apply_refuses_a_time_outside_the_span(tmp_path, capsys, drift, backend):
    path, table, _ = drift
    t = np.linspace(100.0, 3000.0, 30)
    csv = _table(tmp_path, (9, "t", "-100000"), t=t)
    out = tmp_path / "out.csv"
    before = _checksums(tmp_path)
    code, err, escaped = _run(["apply", str(path), str(csv), "-o", str(out), "--backend", backend], capsys)
    assert escaped is None and code == 2, err
    assert len(err.strip().splitlines()) == 1
    assert "row 9, column t: " in err and ": t = -100000.000 s is outside the span" in err and "pose 0" not in err
    assert _checksums(tmp_path) == before


@pytest.mark.parametrize("backend", BACKENDS)
def test_apply_refuses_a_model_with_nan_weights(tmp_path, capsys, backend):
    model = onnx.load(PMC_ZHOU)
    tensor = _used_weight(model)
    w = numpy_helper.to_array(tensor).copy()
    w.flat[0] = np.nan
    tensor.CopyFrom(numpy_helper.from_array(w, tensor.name))
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(graphs.signed(model))
    out = tmp_path / "out.csv"
    table = _table(tmp_path)
    before = _checksums(tmp_path)
    code, err, escaped = _run(["apply", str(bad), str(table), "-o", str(out), "--backend", backend], capsys)
    assert escaped is None and code == 2, err
    assert len(err.strip().splitlines()) == 1
    assert str(bad) in err and f"tensor '{tensor.name}' holds a non-finite value" in err
    assert _checksums(tmp_path) == before


def test_apply_refuses_a_result_that_is_not_a_pose(tmp_path, capsys):
    """onnxruntime used to write the infinity; now it refuses, naming the row."""
    model = tmp_path / "inf.onnx"
    model.write_bytes(_posecorr_graph([1, 1, 1, 1, 1, 1, 0], op="Div"))
    out = tmp_path / "out.csv"
    table = _table(tmp_path)
    before = _checksums(tmp_path)
    code, err, _ = _run(["apply", str(model), str(table), "-o", str(out), "--backend", "onnxruntime"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "row 2: " in err and "runtime error: qz of output 'corrected' is not finite" in err and "pose 0" not in err
    assert _checksums(tmp_path) == before


def test_a_model_onnxruntime_fails_to_run_is_named_in_one_line(tmp_path):
    """A Gather whose constant index is past its data: libposecorr refuses it at load;
    onnxruntime loads it and fails on the first pose. `apply` (its own process, so that
    onnxruntime's log, written to the stderr file itself, would be seen) names the row, the
    model once and onnxruntime's reason in one line, as pc_run names a fault: its status
    first. onnxruntime's log printed the failure again, a dozen coloured lines."""
    g = graphs.G()
    past = g.op("Gather", [g.f32(np.ones(7, np.float32)), g.i64([9])], axis=0)
    model = tmp_path / "past.onnx"
    model.write_bytes(graphs.signed(g.model(g.op("Add", ["pose", past]), metadata=graphs.BOUNDED)))
    table = _table(tmp_path)
    with pytest.raises(PoseCorrError, match="index 9 out of range for axis of 7"):
        Corrector(model, backend="c")
    r = subprocess.run([sys.executable, "-m", "posecorr.cli", "apply", str(model), str(table), "-o",
                        str(tmp_path / "out.csv"), "--backend", "onnxruntime"], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.startswith(f"posecorr apply: error: {table}, row 2: {model}: runtime error: onnxruntime failed "
                               "to run it: ") and "indices element out of data bounds" in r.stderr, r.stderr
    assert len(r.stderr.splitlines()) == 1 and r.stderr.count(str(model)) == 1, r.stderr
    assert not (tmp_path / "out.csv").exists()


def _posecorr_run(model, text: str | bytes, *args: str) -> subprocess.CompletedProcess:
    run = Path(sys.executable).parent / "posecorr-run"
    return subprocess.run([str(run), str(model), *args], input=text, capture_output=True,
                          text=isinstance(text, str), timeout=60)


def _lines(x: np.ndarray, t: np.ndarray | None = None) -> str:
    rows = x if t is None else np.column_stack([x, t])
    return "\n".join(",".join(f"{v:.9g}" for v in row) for row in rows) + "\n"


def test_posecorr_run_refuses_a_pose_outside_the_box():
    x = _inside(2)
    x[1, 0] = 999.0
    r = _posecorr_run(PMC_ZHOU, _lines(x))
    lines = r.stdout.splitlines()
    assert r.returncode == 1 and len(lines) == 2 and "nan" in lines[1].lower()
    lo, hi = graphs.model_box(PMC_ZHOU)
    assert r.stderr == (f"posecorr-run: line 2: pose outside the fitted range: x = 999.000 m is outside the range "
                        f"the model was fitted on, {checks.decimal(lo[0])} to {checks.decimal(hi[0])} m (metadata "
                        "input_bounds)\n")


def test_posecorr_run_names_each_refusal_by_its_line_alone():
    """A line is a call of one pose: the tool gives the library's clause after the line's
    number, without the call's "pose 0", in the words of the Python back ends (whose messages
    name the pose in its call)."""
    x = _inside(5)
    x[1, 4] = np.inf
    x[2, :3], x[2, 3:] = (5.0, 5.0, 5.0), 0.0      # a zero quaternion, outside the box too
    x[3, 1] = 5.0
    r = _posecorr_run(PMC_ZHOU, _lines(x))
    assert r.returncode == 1 and len(r.stdout.splitlines()) == 5
    said = {}
    for k in (1, 2, 3):
        with pytest.raises(PoseCorrError) as info:
            Corrector(PMC_ZHOU).correct(x[k])
        status, pose, clause = str(info.value).split(": ", 2)
        assert pose == "pose 0"
        said[k] = f"posecorr-run: line {k + 1}: {status}: {clause}"
    assert r.stderr.splitlines() == [said[1], said[2], said[3]]
    assert said[1].endswith("line 2: non-finite input: qx is not finite (expected a finite number)")
    assert said[2].endswith("line 3: quaternion not unit: the quaternion qw, qx, qy, qz has norm 0.000000 "
                            "(expected a unit quaternion: norm within 0.001 of 1)")
    assert said[3].startswith("posecorr-run: line 4: pose outside the fitted range: y = 5.000 m is outside")
    # --binary: the record's number, the same clause
    r = _posecorr_run(PMC_ZHOU, x.astype("<f4").tobytes(), "--binary")
    assert r.returncode == 1 and r.stderr.decode().splitlines()[1] == said[2].replace("line 3", "record 3")


def test_posecorr_run_names_a_value_beyond_float32_as_such(drift):
    """1e39 is finite: strtof made it infinite, and the line read 'x is not finite'. A t beyond
    float32 is refused by a model that takes time and ignored, as every t, by one that does not."""
    x = _inside(2)
    text = _lines(x)
    lines = text.splitlines()
    lines[1] = "1e39," + lines[1].split(",", 1)[1]
    r = _posecorr_run(PMC_ZHOU, "\n".join(lines) + "\n")
    assert r.returncode == 1 and r.stdout.splitlines()[1] == "nan,nan,nan,nan,nan,nan,nan"
    assert r.stderr == ("posecorr-run: line 2: x = 1e+39 m does not fit in float32, the numbers the model computes "
                        "in (their largest is 3.402823e+38)\n")
    r = _posecorr_run(PMC_ZHOU, _lines(x, np.array([1.0, 1e40])))
    assert r.returncode == 0 and r.stderr == "", r.stderr
    path, table, _ = drift
    r = _posecorr_run(path, _lines(table.measured[:2], np.array([1.0, 1e40])))
    assert r.returncode == 1 and r.stderr == ("posecorr-run: line 2: t = 1e+40 s does not fit in float32, the numbers "
                                              "the model computes in (their largest is 3.402823e+38)\n")


def test_posecorr_run_names_a_time_and_an_output_by_their_line(drift):
    path, table, span = drift
    x, t = table.measured[:3].copy(), table.extras["t"][:3].copy()
    t[1] = -100000.0
    r = _posecorr_run(path, _lines(x, t))
    assert r.returncode == 1
    assert r.stderr == (f"posecorr-run: line 2: pose outside the fitted range: t = -100000.000 s is outside the span "
                        f"the model was fitted on, {checks.decimal(np.float32(span[0]))} to "
                        f"{checks.decimal(np.float32(span[1]))} s (metadata time_bounds)\n")
    blob = _posecorr_graph([1, 1, 1, 1, 1, 1, 0], op="Div")  # qz / 0
    x = _inside(1)
    x[:, 6] = np.abs(x[:, 6]) + 0.1
    x[:, 3:] /= np.linalg.norm(x[:, 3:], axis=1, keepdims=True)
    model = path.parent / "inf.onnx"
    model.write_bytes(blob)
    r = _posecorr_run(model, _lines(x))
    assert r.stderr == ("posecorr-run: line 1: runtime error: qz of output 'corrected' is not finite (expected a "
                        "finite number)\n")


def _protobuf_varint(n: int) -> bytes:
    out = bytearray()
    while True:
        out.append((n & 0x7F) | (0x80 if n > 0x7F else 0))
        n >>= 7
        if not n:
            return bytes(out)


def _pose_model(**kw) -> onnx.ModelProto:
    g = graphs.G()
    return g.model(g.op("Mul", ["pose", g.f32(np.ones(7, np.float32))]), metadata=graphs.BOUNDED, **kw)


def _graph_with(extra: bytes) -> tuple[bytes, int]:
    """A pose model whose graph's bytes end in `extra` (fields onnx.helper would not write),
    and the byte of the file `extra` starts on."""
    model = _pose_model()
    graph = model.graph.SerializeToString() + extra
    model.ClearField("graph")
    blob = model.SerializeToString() + b"\x3a" + _protobuf_varint(len(graph)) + graph
    return blob, len(blob) - len(extra)


def _edited_io(edit) -> bytes:
    model = _pose_model()
    edit(model.graph)
    return graphs.signed(model)


def _fixed_batch(graph) -> None:
    graph.input[0].type.tensor_type.shape.dim[0].dim_value = 1


def _negative_batch(graph) -> None:
    graph.input[0].type.tensor_type.shape.dim[0].dim_value = -3


def _second_output(graph) -> None:
    graph.output.append(helper.make_tensor_value_info("corrected", onnx.TensorProto.FLOAT, ["N", 7]))


def _renamed_output(graph) -> None:
    graph.output[0].name = "y"


def _float64_pose(graph) -> None:
    graph.input[0].type.tensor_type.elem_type = onnx.TensorProto.DOUBLE


def _edited_weight(edit, constant: bool = False) -> bytes:
    """A pose model whose one weight tensor, an initializer (or the value of a Constant
    node), `edit` changed."""
    model = _pose_model()
    tensor = model.graph.initializer[0]
    if constant:
        value = onnx.TensorProto()
        value.CopyFrom(tensor)
        del model.graph.initializer[:]
        model.graph.node.insert(0, helper.make_node("Constant", [], [value.name], name="w", value=value))
        tensor = model.graph.node[0].attribute[0].t
    edit(tensor)
    return graphs.signed(model)


def _one_value_short(tensor) -> None:
    values = numpy_helper.to_array(tensor).ravel()
    tensor.ClearField("raw_data")
    tensor.float_data.extend(values[:-1])


def _rank_seven(tensor) -> None:
    tensor.ClearField("dims")
    tensor.dims.extend([1] * 6 + [7])


def _tensor_cases() -> list[tuple[str, bytes, str]]:
    """A weight whose shape, element type or size libposecorr does not take (onnx.c's
    onnx_tensor_header), and an operator it does not know in one node before a node cut
    short: the operator is named, as libposecorr looks at each node before reading the next."""
    def edited(field: str, value):
        return lambda tensor: setattr(tensor, field, value)

    rank_seven = _edited_weight(_rank_seven)
    # dims are not packed (onnx.proto is proto2): the seventh dims field's key is named
    rank_at = rank_seven.find(b"\x08\x01" * 6 + b"\x08\x07") + 12
    unknown_then_cut, cut_at = _graph_with(b"\x0a\x06\x22\x04Nope" + b"\x0a\x04\x22\x10ab")
    return [
        ("raw_data size", _edited_weight(edited("raw_data", bytes(32))), "tensor 'c1': raw_data has 32 bytes, shape needs 28"),
        ("values short", _edited_weight(_one_value_short), "tensor 'c1' has 6 values, shape needs 7"),
        ("constant short", _edited_weight(_one_value_short, constant=True), "tensor 'c1' has 6 values, shape needs 7"),
        ("negative dim", _edited_weight(lambda tensor: tensor.dims.__setitem__(0, -7)), "tensor 'c1' has an invalid shape"),
        ("float64 weight", _edited_weight(edited("data_type", onnx.TensorProto.DOUBLE)),
         "tensor 'c1' has unsupported data type 11"),
        ("external weight", _edited_weight(edited("data_location", onnx.TensorProto.EXTERNAL)),
         "tensor 'c1' uses external data"),
        ("weight rank", rank_seven, f"tensor at byte {rank_at} has rank > 6"),
        ("operator before a cut", unknown_then_cut, "unsupported operator Nope in node ''"),
    ]


def test_a_tensor_is_read_field_by_field_as_protobuf_reads_it():
    """An empty packed dims field (a scalar's, as a hand-written writer may emit it) adds no
    dimension and does not stop the values after it from being read: onnx's own parser is
    the judge."""
    import struct

    from posecorr.controller import onnx_meta

    value = struct.pack("<f", 1.5)
    buf = b"\x0a\x00" + b"\x10\x01" + b"\x22\x04" + value + b"\x42\x01w"   # dims, data_type, float_data, name
    judge = onnx.TensorProto.FromString(buf)
    assert list(judge.dims) == [] and list(judge.float_data) == [1.5] and judge.name == "w"
    assert onnx_meta.tensor_fault(buf) is None
    assert onnx_meta.float_tensor(buf) == {"name": "w", "raw": None, "float_data": value}
    assert onnx_meta._initializer(buf) == ("w", 1)


def _structure_cases() -> list[tuple[str, bytes, str]]:
    """(case, the model's bytes, what every reader says after the file's name)."""
    field, at = _graph_with(b"\x60\x01")           # graph output (12) as a varint
    node, node_at = _graph_with(b"\x0a\x02\x20\x01")  # a node whose op_type (4) is a varint
    no_default = _pose_model(opset=17)
    no_default.opset_import[0].domain = "com.example"
    time_2d = helper.make_tensor_value_info("t", onnx.TensorProto.FLOAT, ["N", 1])
    return [
        ("text", b"hello, this is not a model\n", "not a valid ONNX model (unsupported wire type 4 at byte 2)"),
        ("model field", b"8 is not bytes", "not a valid ONNX model (model field 7 at byte 0 is not bytes)"),
        ("no graph", b"\x08\x08", "not a valid ONNX model (no graph)"),
        ("no default opset", graphs.signed(no_default), "default-domain opset -1 is not supported (13..28)"),
        ("graph field", field, f"graph field 12 at byte {at} is not bytes"),
        ("node field", node, f"node field 4 at byte {node_at + 2} is not bytes"),
        ("input name", graphs.signed(_pose_model(rename_input="x")),
         "model input is 'x', the contract needs 'pose' float32 [N,7] and optionally 't' float32 [N]"),
        # no bounds as well: the contract is named first, as libposecorr meets it first
        ("input name, unbounded", _pose_model(rename_input="x").SerializeToString(),
         "model input is 'x', the contract needs 'pose' float32 [N,7] and optionally 't' float32 [N]"),
        ("pose width", graphs.signed(_pose_model(width=6)), "input 'pose' must have shape [N,7] (rank 2, width 6)"),
        ("pose batch", _edited_io(_fixed_batch), "input 'pose' has a fixed batch size 1; N must be dynamic"),
        # as -1 it read as symbolic: the model loaded in C
        ("negative batch", _edited_io(_negative_batch), "value 'pose' has dimension -3, expected a size of 0 or more"),
        ("pose type", _edited_io(_float64_pose), "input 'pose' has element type 11, the contract needs float32"),
        ("time shape", graphs.signed(_pose_model(inputs_after=[time_2d])), "input 't' must have shape [N] (rank 2)"),
        ("output name", _edited_io(_renamed_output), "model output is 'y', the contract needs 'corrected' float32 [N,7]"),
        ("two outputs", _edited_io(_second_output), "model has 2 outputs, the contract needs exactly one ('corrected')"),
        *_tensor_cases(),
    ]


@pytest.mark.parametrize("case,blob,said", _structure_cases(), ids=lambda v: v if isinstance(v, str) else "")
def test_a_file_that_is_no_pose_model_is_named_alike_by_every_reader(tmp_path, case, blob, said):
    """A fault of a model's structure, of its pose contract or of a weight tensor reads the
    same from `posecorr-run` (libposecorr), both back ends of the shim (`apply`), and, where
    the top level is no model, from `info`: libposecorr's words, and of two faults the one
    its load meets first."""
    from posecorr.controller import read_info

    model = tmp_path / "m.onnx"
    model.write_bytes(blob)
    r = _posecorr_run(model, "", "--allow-unsigned")
    assert r.returncode == 1 and r.stderr == f"posecorr-run: {model}: {said}\n", r.stderr
    statuses = set()
    for backend in BACKENDS:
        with pytest.raises(PoseCorrError) as info:
            Corrector(model, backend=backend, allow_unsigned=True)
        assert str(info.value) == f"{model}: {said}", backend
        statuses.add(info.value.status)
    assert len(statuses) == 1
    if said.startswith("not a valid ONNX model"):
        with pytest.raises(ValueError) as info:
            read_info(model)
        assert str(info.value) == f"{model}: {said}"


def _name_spans(blob: bytes, model: onnx.ModelProto) -> list[tuple[int, int]]:
    """(start, end) in `blob` of every string field that holds a name of the graph (nodes'
    op types, names, inputs and outputs, initializers', graph inputs' and outputs'): the
    bytes after a one-byte length equal to the name's."""
    g = model.graph
    names = {n for node in g.node for n in (node.op_type, node.name, *node.input, *node.output)}
    names |= {t.name for t in g.initializer} | {v.name for v in (*g.input, *g.output)}
    spans = []
    for name in (n.encode() for n in names if 3 <= len(n) < 128):
        at = blob.find(name)
        while at >= 0:
            if blob[at - 1] == len(name):
                spans.append((at, at + len(name)))
            at = blob.find(name, at + 1)
    return sorted(spans)


@pytest.mark.parametrize("path", [PMC_ZHOU, MLP_ZHOU], ids=lambda p: p.name)
def test_a_model_with_a_name_changed_is_refused_alike(path):
    """One letter of one name changed, 150 ways (seeded) in each of two shipped models
    without their digest: an operator no runtime has, a value read that nothing produces,
    a graph output nobody writes, a value written twice. Both back ends load or refuse each
    alike, with the same status and words (the Python layer's check of the pose contract,
    the operators and the graph's references are libposecorr's, in its order)."""
    model = graphs.without_metadata(onnx.load(path), "model_digest")
    blob = model.SerializeToString()
    spans = _name_spans(blob, model)
    rng = np.random.default_rng(0)
    outcomes = set()
    for _ in range(150):
        start, end = spans[rng.integers(len(spans))]
        damaged = bytearray(blob)
        damaged[rng.integers(start, end)] = ord(rng.choice(list("abcxyzQ_0")))
        said = []
        for backend in BACKENDS:
            try:
                Corrector(bytes(damaged), backend=backend, allow_unsigned=True)
                said.append(("loads", None))
            except PoseCorrError as exc:
                said.append((str(exc), exc.status))
        assert said[0] == said[1]
        outcomes.add(said[0][1])
    # the damage reaches every kind of fault it can make, and some names (a node's own) are free
    assert {None, int(S.UNSUPPORTED), int(S.GRAPH)} <= outcomes, outcomes


def test_a_name_that_is_not_utf8_loads_in_c_and_is_named_by_its_byte_for_onnxruntime(tmp_path):
    """libposecorr reads names as bytes and loads such a file; onnxruntime cannot, and its
    back end says so by the byte of the file, after every check libposecorr makes; `info`
    reads it."""
    from posecorr.controller import digest, read_info

    model = _pose_model()
    model.graph.node[0].name = "scale-by-one"
    blob = bytearray(graphs.signed(model))
    # the node's name: a byte not UTF-8, the digest made again over it
    at = bytes(blob).index(b"scale-by-one") + 5
    blob[at] = 0xFF
    span = digest.digest_span(bytes(blob))
    path = tmp_path / "m.onnx"
    path.write_bytes(bytes(blob[:span[0]]) + digest.file_digest(bytes(blob), span).encode() + bytes(blob[span[1]:]))
    x = _inside()
    np.testing.assert_allclose(Corrector(path).correct(x), x, atol=1e-6)   # the graph multiplies by one
    with pytest.raises(PoseCorrError) as info:
        Corrector(path, backend="onnxruntime")
    assert str(info.value) == (f"{path}: the string at byte {at} is not UTF-8, which onnxruntime cannot load (the C "
                               "back end can)") and info.value.status == S.MALFORMED
    assert read_info(path)["op_counts"] == {"Identity": 1, "Mul": 1}


# --- the digest, the reach and the allow flags: the same words on both back ends --------------

def _strip_where(errors: list[PoseCorrError]) -> list[PoseCorrError]:
    """Load errors without the file's name in front (both back ends put it there)."""
    return [PoseCorrError(str(e).split(": ", 1)[1], e.status) for e in errors]


def test_a_changed_file_is_refused_alike():
    blob = bytearray(PMC_ZHOU.read_bytes())
    tensor = _used_weight(onnx.load(PMC_ZHOU))
    blob[bytes(blob).index(tensor.raw_data) + 3] ^= 0x40  # one exponent bit
    errors = _load_errors(bytes(blob))
    text = _same(_strip_where(errors), S.INTEGRITY, "the file's bytes give crc32c:",
                 "where its metadata model_digest says crc32c:", "changed or damaged after export")
    stored = {e.key: e.value for e in onnx.load(PMC_ZHOU).metadata_props}["model_digest"]
    assert stored in text and str(errors[0]).startswith(f"model of {len(blob)} bytes: ")


@pytest.mark.parametrize("drop,status,fragment", [
    ("model_digest", S.INTEGRITY, "no metadata model_digest: the file carries no digest of its bytes (to run "
                                  "it anyway, load with PC_LOAD_ALLOW_UNSIGNED, on the command line --allow-unsigned)"),
    ("input_bounds", S.CONTRACT, "no metadata input_bounds: the model does not say which positions it was fitted "
                                 "on (to run it anyway, load with PC_LOAD_ALLOW_UNBOUNDED, on the command line "
                                 "--allow-unbounded)"),
    ("correction_reach", S.CONTRACT, "no metadata correction_reach: the model does not say how far its "
                                     "corrections reach"),
])
def test_a_missing_key_is_refused_alike_unless_allowed(drop, status, fragment):
    model = graphs.without_metadata(onnx.load(PMC_ZHOU), drop)
    blob = model.SerializeToString() if drop == "model_digest" else graphs.signed(model)
    _same(_strip_where(_load_errors(blob)), status, fragment)
    allow = {"allow_unsigned": True} if drop == "model_digest" else {"allow_unbounded": True}
    x = _inside()
    c, o = (Corrector(blob, backend=b, **allow).correct(x) for b in BACKENDS)
    np.testing.assert_allclose(c, o, atol=2e-6)
    np.testing.assert_array_equal(c, Corrector(PMC_ZHOU).correct(x))


@pytest.mark.parametrize("dx", [0.05, 5000.0])
def test_a_correction_is_refused_alike_beyond_the_reach_only(dx):
    """A graph that adds dx to x after the model: within its reach (0.05 m, pmc-zhou's reach
    0.101 m), the model's answer moved by dx on both back ends; beyond it, refused with the
    figures on both; the reach is what the metadata says (float32 on squares)."""
    model = graphs.offset_graph(onnx.load(PMC_ZHOU), dx)
    blob = graphs.signed(model)
    x = _inside(12)
    reach = json.loads({e.key: e.value for e in model.metadata_props}["correction_reach"])
    moved = np.linalg.norm(Corrector(PMC_ZHOU).correct(x)[:, :3] + [dx, 0, 0] - x[:, :3], axis=1)
    if dx < reach[0]:
        assert moved.max() < 0.99 * reach[0]
        for backend in BACKENDS:
            np.testing.assert_allclose(Corrector(blob, backend=backend).correct(x),
                                       Corrector(PMC_ZHOU, backend=backend).correct(x) + [dx, 0, 0, 0, 0, 0, 0],
                                       atol=2e-6)
        return
    first = int(np.argmax(moved > 1.01 * reach[0]))
    _same(_both(blob, x), S.RUNTIME, f"pose {first}: output 'corrected' moves the pose by "
          f"{checks.decimal(moved[first])[:-1]}", f"beyond the model's reach of {checks.decimal(reach[0])} m "
          f"and {checks.decimal(reach[1])} rad (metadata correction_reach)")


def test_input_bounds_of_any_length_are_read_whole():
    """A valid input_bounds longer than the 255 bytes the C reader kept (numbers written
    with 45 decimals, then 10,000 blanks before them): loaded by both back ends, the same
    poses corrected, the same box enforced."""
    box = json.loads({e.key: e.value for e in onnx.load(PMC_ZHOU).metadata_props}["input_bounds"])
    long = "[" + ", ".join("[" + ", ".join(f"{v:.45f}" for v in row) + "]" for row in box) + "]"
    assert len(long) > 300
    poses = _inside()
    far = poses[:1].copy()
    far[0, 0] = box[1][0] + 0.01
    for text in (long, " " * 10_000 + long):
        blob = graphs.signed(_edited(PMC_ZHOU, input_bounds=text))
        for backend in BACKENDS:
            np.testing.assert_array_equal(Corrector(blob, backend=backend).correct(poses),
                                          Corrector(PMC_ZHOU, backend=backend).correct(poses))
            with pytest.raises(PoseCorrError, match="metadata input_bounds") as info:
                Corrector(blob, backend=backend).correct(far)
            assert info.value.status == S.RANGE


def test_a_position_only_model_passes_through_every_quaternion_the_input_rule_accepts():
    """A position-only model passes the input's quaternion through: one with norm 1.0009 (the
    input rule allows 1e-3) came out refused as the model's failure (PC_ERR_RUNTIME, |q|^2
    within 1e-3), while 1.0004 passed. Both back ends now hold the output to the input's rule,
    and the exporter makes the quaternion it passes unit (the contract's form of a rotation)."""
    model = ROOT / "models" / "pmc-pos.onnx"
    x = np.repeat(graphs.poses_in_box(model, 1, 0).astype(np.float64), 6, axis=0)
    x[:, 3:] = [1.0, 0.0, 0.0, 0.0]
    x[:, 3] = [1.0009, 0.9991, 1.0006, 0.9994, 1.0004, 1.0]
    for backend in BACKENDS:
        out = Corrector(model, backend=backend).correct(x)
        np.testing.assert_allclose(out[:, 3:], x[:, 3:] / np.linalg.norm(x[:, 3:], axis=1, keepdims=True),
                                   rtol=0, atol=1e-6)
    x[0, 3] = 1.0011                                          # beyond the input rule: refused as input
    _same(_both(model, x), S.QUATERNION, "pose 0: the quaternion qw, qx, qy, qz has norm 1.001100")
