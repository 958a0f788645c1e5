"""The ONNX exporter: symbolic namespace vs numpy, graphs in onnxruntime vs float64 predict,
operator refusal, dynamic batch size, metadata round trip."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from posecorr import rotations
from posecorr._xp import namespace
from posecorr.controller.onnx_meta import read_info
from posecorr.export import (OperatorNotSupported, build_model, check_operators, custom_op, data_digest,
                             load_operator_list, op_counts, run_onnx, to_onnx)
from posecorr.export.parity import quat_angle
from posecorr.export.symbolic import Graph

ACTIVATIONS = ("compet", "hardlim", "logsig", "purelin", "radbas", "satlin", "softmax", "tansig")
REPS = ("eaa", "quat", "R", "zhou")
REP_SIZE = {"eaa": 3, "quat": 4, "R": 9, "zhou": 6, "pos": 0}


# --- helpers: run an xp function through a one-input graph ----------------------------------

def run_sym(fn, *arrays: np.ndarray, extra_inputs: bool = True) -> np.ndarray:
    """Build a graph whose inputs are `arrays` (float32, first axis dynamic), apply fn on the
    symbolic tensors, run it in onnxruntime and return the output."""
    from onnx import TensorProto, helper

    g = Graph()
    syms = [g.input(f"in{k}", (-1,) + a.shape[1:]) for k, a in enumerate(arrays)]
    out = g.lift(fn(*syms))
    assert not out.is_const
    elem = {1: TensorProto.FLOAT, 9: TensorProto.BOOL, 7: TensorProto.INT64}[out.elem]
    needed, producer = set(), {n.outputs[0]: n for n in g.nodes}
    stack = [out.name]
    while stack:
        name = stack.pop()
        if name not in needed:
            needed.add(name)
            if name in producer:
                stack.extend(i for i in producer[name].inputs if i)
    nodes = [helper.make_node(n.op_type, n.inputs, n.outputs, name=n.name, **n.attrs)
             for n in g.nodes if n.outputs[0] in needed]
    from onnx import numpy_helper

    graph = helper.make_graph(
        nodes, "t", [helper.make_tensor_value_info(f"in{k}", TensorProto.FLOAT, ["N", *a.shape[1:]])
                     for k, a in enumerate(arrays)],
        [helper.make_tensor_value_info(out.name, elem, ["N" if d < 0 else d for d in out.shape])],
        initializer=[numpy_helper.from_array(v, k) for k, v in g.initializers.items() if k in needed])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    check_operators(model)
    onnx.checker.check_model(model, full_check=True)
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    res = sess.run(None, {f"in{k}": a.astype(np.float32) for k, a in enumerate(arrays)})[0]
    # The tracked symbolic shape must match what onnxruntime computed (-1 = the batch).
    assert len(out.shape) == res.ndim
    assert all(d == r or d == -1 for d, r in zip(out.shape, res.shape)), (out.shape, res.shape)
    return res


def f32(a: np.ndarray) -> np.ndarray:
    """The float32-rounded input as float64: what the graph actually receives."""
    return np.asarray(a, np.float32).astype(np.float64)


RNG = np.random.default_rng(1234)


# --- the namespace, function by function ---------------------------------------------------

@pytest.mark.parametrize("name, domain", [("sqrt", (0.01, 4)), ("sin", (-4, 4)), ("cos", (-4, 4)),
                                          ("tan", (-1.4, 1.4)), ("exp", (-5, 3)), ("tanh", (-4, 4)),
                                          ("abs", (-3, 3)), ("sigmoid", (-8, 8))])
def test_unary_functions_match_numpy(name, domain):
    x = RNG.uniform(*domain, size=(50, 3))
    got = run_sym(lambda s: getattr(namespace(s), name)(s), x)
    want = getattr(namespace(x), name)(f32(x))
    np.testing.assert_allclose(got, want, rtol=2e-6, atol=2e-7)


def test_atan2_all_quadrants_axes_and_origin():
    angles = np.linspace(-math.pi, math.pi, 97)[1:]     # includes every multiple of pi/4
    radii = np.array([1e-6, 1.0, 1e3])
    y = (radii[:, None] * np.sin(angles)[None, :]).ravel()
    x = (radii[:, None] * np.cos(angles)[None, :]).ravel()
    # Exact axes and the origin: (0, +-1), (+-1, 0), (0, 0).
    y = np.concatenate([y, [0.0, 0.0, 1.0, -1.0, 0.0, 2.5, -2.5]])
    x = np.concatenate([x, [1.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    got = run_sym(lambda a, b: namespace(a).atan2(a, b), y[:, None], x[:, None])[:, 0]
    want = np.arctan2(f32(y), f32(x))
    # +-pi are the same angle: compare on the circle.
    diff = np.angle(np.exp(1j * (got - want)))
    assert np.max(np.abs(diff)) < 1e-6
    assert got[-3] == 0.0                                # atan2(0, 0) = 0 as numpy
    assert abs(got[-6] - math.pi) < 1e-6                 # atan2(0, -1) = pi


def test_atan2_with_float_argument():
    y = RNG.normal(size=(20, 1))
    got = run_sym(lambda a: namespace(a).atan2(a, -0.5), y)
    np.testing.assert_allclose(got, np.arctan2(f32(y), -0.5), atol=1e-6)


def test_binary_operators_with_floats_on_both_sides():
    a, b = RNG.normal(size=(30, 4)), RNG.uniform(0.5, 2.0, size=(30, 4))

    def fn(x, y):
        return (2.0 - x) * y / 3.0 + 1.5 / y - (-x) + x * 1.0 + 0.0 - y / 1.0

    want = fn(f32(a), f32(b))
    np.testing.assert_allclose(run_sym(fn, a, b), want, rtol=1e-5, atol=1e-6)


def test_no_op_nodes_are_not_emitted():
    g = Graph()
    x = g.input("x", (-1, 3))
    y = ((x * 1.0 + 0.0) - 0.0) / 1.0
    assert y is x and not g.nodes
    z = -(-x)
    assert z.name == x.name


def test_constants_fold_and_are_shared():
    g = Graph()
    x = g.input("x", (-1, 3))
    c = g.ns.sqrt(g.const(np.array([4.0, 9.0, 16.0]))) * 2.0   # folded at build time
    assert c.is_const and np.allclose(c.value, [4, 6, 8])
    y1 = x * np.pi
    y2 = x + np.pi
    assert not any(n.op_type == "Sqrt" for n in g.nodes)
    assert g.producer(y1).inputs[1] == g.producer(y2).inputs[1]   # one initializer for pi
    assert len(g.initializers) == 1


def test_identical_nodes_are_reused():
    g = Graph()
    x = g.input("x", (-1, 3))
    a = x[..., 0] * x[..., 1]
    b = x[..., 0] * x[..., 1]
    assert a.name == b.name
    assert len(g.nodes) == 3


@pytest.mark.parametrize("op", ["<", "<=", ">", ">="])
def test_comparisons_and_where(op):
    a, b = RNG.normal(size=(40, 3)), RNG.normal(size=(40, 3))
    b[:5] = a[:5]                                       # ties
    cmp = {"<": lambda u, v: u < v, "<=": lambda u, v: u <= v,
           ">": lambda u, v: u > v, ">=": lambda u, v: u >= v}[op]

    def fn(x, y):
        xp = namespace(x, y)
        return xp.where(cmp(x, y), x, -2.0) + xp.where(cmp(0.1, y), 1.5, y)

    np.testing.assert_allclose(run_sym(fn, a, b), fn(f32(a), f32(b)), rtol=1e-6, atol=1e-6)


def test_maximum_minimum_clip():
    a, b = RNG.normal(size=(40, 5)), RNG.normal(size=(40, 5))

    def fn(x, y):
        xp = namespace(x, y)
        return xp.maximum(x, y) + xp.minimum(x, 0.2) + xp.maximum(-0.3, y) + xp.clip(x, -0.5, 0.7)

    np.testing.assert_allclose(run_sym(fn, a, b), fn(f32(a), f32(b)), rtol=1e-6, atol=1e-6)


def test_stack_with_floats_concat_and_indexing():
    a = RNG.normal(size=(25, 6))

    def fn(x):
        xp = namespace(x)
        s = xp.stack([x[..., 0], 1.0, x[..., 2] * x[..., 3], 0.0, -2.5, x[..., 5]], axis=-1)
        t = xp.stack([x[..., 1], x[..., 4]], axis=0)              # non-last axis
        u = xp.concat([x[..., 1:3], s, x[..., 4:6]], axis=-1)
        return xp.concat([u, xp.swap_last(t)], axis=-1)

    np.testing.assert_allclose(run_sym(fn, a), fn(f32(a)), rtol=1e-6, atol=1e-6)


def test_stack_of_gathers_becomes_one_gather():
    g = Graph()
    x = g.input("x", (-1, 9))
    z = g.ns.stack([x[..., 0], x[..., 3], x[..., 6], x[..., 1]], axis=-1)
    q = g.ns.stack([x[..., i] * x[..., j] for i in range(3) for j in range(i, 3)], axis=-1)
    assert g.producer(z).op_type == "Gather" and z.shape == (-1, 4)
    assert g.producer(q).op_type == "Mul" and q.shape == (-1, 6)
    a = RNG.normal(size=(10, 9))
    got = run_sym(lambda s: namespace(s).concat([namespace(s).stack([s[..., 0], s[..., 3], s[..., 6], s[..., 1]]),
                                                 namespace(s).stack([s[..., i] * s[..., j] for i in range(3)
                                                                     for j in range(i, 3)])]), a)
    b = f32(a)
    want = np.concatenate([b[:, [0, 3, 6, 1]], np.stack([b[:, i] * b[:, j] for i in range(3)
                                                         for j in range(i, 3)], axis=-1)], axis=-1)
    np.testing.assert_allclose(got, want, rtol=1e-6)


def test_sum_reshape_matmul_linear():
    a = RNG.normal(size=(12, 9))
    W, bias = RNG.normal(size=(9, 4)), RNG.normal(size=4)

    def fn(x):
        xp = namespace(x)
        m = xp.reshape(x, (-1, 3, 3))
        mm = xp.matmul(m, xp.swap_last(m))
        s = xp.sum(xp.reshape(mm, (-1, 9)), axis=-1, keepdims=True)
        return xp.concat([xp.linear(x, W, bias), s, xp.reshape(xp.sum(x * x, axis=-1), (-1, 1))], axis=-1)

    np.testing.assert_allclose(run_sym(fn, a), fn(f32(a)), rtol=1e-5, atol=1e-5)


def test_linear_is_one_gemm():
    g = Graph()
    x = g.input("x", (-1, 5))
    y = g.ns.linear(x, np.ones((5, 2)), np.zeros(2))
    assert [n.op_type for n in g.nodes] == ["Gemm"] and y.shape == (-1, 2)


@pytest.mark.parametrize("act", ["softmax", "step", "compet"])
def test_layer_activations_match_numpy(act):
    a = RNG.normal(size=(60, 5))
    a[:10, 1] = a[:10, 3] = 5.0                  # ties: compet must pick the FIRST maximum
    a[10:15] = 0.0                               # all equal; step(0) = 1
    got = run_sym(lambda s: getattr(namespace(s), act)(s), a)
    want = getattr(namespace(a), act)(f32(a))
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    if act == "compet":
        assert np.all(got[:10, 1] == 1.0) and np.all(got[:10, 3] == 0.0)
        assert np.all(got.sum(axis=1) == 1.0)


def test_const_and_bool_logic():
    a = RNG.normal(size=(30, 2))

    def fn(x):
        xp = namespace(x)
        both = (x[..., 0] > 0) & (x[..., 1] > 0)
        either = (x[..., 0] > 0) | ~(x[..., 1] > 0)
        return xp.stack([xp.where(both, 1.0, 0.0), xp.where(either, 2.0, -1.0),
                         x[..., 0] * xp.const(3.0, x)], axis=-1)

    np.testing.assert_allclose(run_sym(fn, a), fn(f32(a)), rtol=1e-6)


@pytest.mark.parametrize("rep", REPS)
def test_rotation_round_trip_matches_numpy(rep):
    """encode/decode of every representation: symbolic graph vs the numpy implementation."""
    q = RNG.normal(size=(500, 4))
    q[:5] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1e-4, 1, 0, 0]]  # Shepperd branches, 180 deg

    def fn(x):
        R = rotations.quat_to_matrix(x)
        return rotations.matrix_to_quat(rotations.decode(rotations.encode(R, rep), rep))

    got, want = run_sym(fn, q), fn(f32(q))
    assert np.all(got[:, 0] >= 0)
    assert np.max(quat_angle(got, want)) < 2e-6


def test_export_error_for_python_branching():
    from posecorr.export import ExportError

    class Bad:
        def forward(self, pose):
            return pose if pose[..., 0] > 0 else -pose

    with pytest.raises(ExportError, match="must not branch"):
        build_model(Bad().forward)


# --- test estimators following the estimator contract ------------------------------------

class ToyCorrector:
    """A small corrector with the estimator contract: encode -> core -> decode, xp-generic.

    core: "pmc" = scaled quadratic features -> one linear map (known coefficients), or
    "mlp" = linear + activation layers with random weights, residual around the identity.
    """

    def __init__(self, representation: str, core: str = "mlp", activation: str = "tansig",
                 hidden=(8, 8), seed: int = 0, scale: float = 0.05) -> None:
        from posecorr.train.mlp import activation_xp  # the train helper's activation table

        self.representation, self.core, self.activation = representation, core, activation
        self._act = activation_xp
        d = 3 + REP_SIZE[representation]
        rng = np.random.default_rng(seed)
        self.centre = np.array([0.0, -0.6, 0.5] + [0.0] * REP_SIZE[representation])
        self.gain = np.array([5.0] * 3 + [1.0] * REP_SIZE[representation])
        if core == "pmc":
            nf = d + d * (d + 1) // 2
            self.W = scale * rng.normal(size=(nf, d)) * 0.1
            self.W[np.arange(d), np.arange(d)] += 1.0 / self.gain
            self.b = self.centre.copy()
        else:
            sizes = [d, *hidden, d]
            self.layers = [(rng.normal(size=(i, o)) / np.sqrt(i), rng.normal(size=o) * 0.3)
                           for i, o in zip(sizes[:-1], sizes[1:])]
            self.out_scale = scale

    def _vec(self, pose):
        from posecorr.train.base import encode_pose
        return encode_pose(pose, self.representation)

    def forward(self, pose):
        from posecorr.train.base import decode_pose
        xp = namespace(pose)
        x = self._vec(pose)
        xs = (x - xp.const(self.centre, x)) * xp.const(self.gain, x)
        if self.core == "pmc":
            d = xs.shape[-1]
            feats = xp.concat([xs, xp.stack([xs[..., i] * xs[..., j] for i in range(d) for j in range(i, d)],
                                            axis=-1)], axis=-1)
            y = xp.linear(feats, self.W, self.b)
        else:
            h = xs
            for k, (w, b) in enumerate(self.layers):
                h = xp.linear(h, w, b)
                if k < len(self.layers) - 1:
                    h = self._act(self.activation, h)
            y = x + h * self.out_scale
        return decode_pose(y, pose, self.representation)

    def predict(self, measured):
        return np.asarray(self.forward(np.asarray(measured, np.float64)), np.float64)

    def export_info(self):
        return {"method": self.core, "representation": self.representation,
                "architecture": "toy", "activation": self.activation if self.core == "mlp" else None,
                "trainer": "none"}


def training_like_poses(n: int, seed: int = 0) -> np.ndarray:
    """Exp III-like poses: 0.2 m cube around (0, -0.6, 0.5), roll/pitch/yaw within 35 deg."""
    rng = np.random.default_rng(seed)
    p = np.array([0.0, -0.6, 0.5]) + rng.uniform(-0.1, 0.1, size=(n, 3))
    v = rng.uniform(-0.6, 0.6, size=(n, 3))
    q = rotations.matrix_to_quat(rotations.rotvec_to_matrix(v))
    return np.concatenate([p, q], axis=1)


def assert_parity(est, path, n=2000):
    poses = training_like_poses(n, seed=7)
    out = run_onnx(path, poses)
    ref = est.predict(f32(poses))
    dp = np.linalg.norm(out[:, :3] - ref[:, :3], axis=1)
    dr = quat_angle(out[:, 3:], ref[:, 3:])
    assert np.max(dp) < 1e-5 and np.max(dr) < 1e-5, (np.max(dp), np.max(dr))
    assert np.all(out[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(out[:, 3:], axis=1), 1.0, atol=1e-6)
    return out


@pytest.mark.parametrize("rep", REPS + ("pos",))
def test_pmc_like_export_parity(rep, tmp_path):
    est = ToyCorrector(rep, core="pmc")
    report = to_onnx(est, tmp_path / "m.onnx", measured=training_like_poses(500), n_random=2000)
    assert report["op_counts"].get("Gemm") == 1 and "MatMul" not in report["op_counts"]
    assert_parity(est, tmp_path / "m.onnx")


@pytest.mark.parametrize("act", ACTIVATIONS)
def test_mlp_every_activation_parity(act, tmp_path):
    est = ToyCorrector("zhou", core="mlp", activation=act, seed=ACTIVATIONS.index(act))
    report = to_onnx(est, tmp_path / "m.onnx", measured=training_like_poses(300), n_random=1000)
    assert report["op_counts"]["Gemm"] == 3
    assert_parity(est, tmp_path / "m.onnx")


@pytest.mark.parametrize("rep", REPS + ("pos",))
def test_mlp_every_representation_parity(rep, tmp_path):
    est = ToyCorrector(rep, core="mlp", activation="tansig", seed=3)
    to_onnx(est, tmp_path / "m.onnx", measured=training_like_poses(300), n_random=1000)
    out = assert_parity(est, tmp_path / "m.onnx")
    if rep == "pos":   # orientation passes through (sign-canonical)
        poses = training_like_poses(2000, seed=7)
        assert np.max(quat_angle(out[:, 3:], poses[:, 3:])) < 1e-6


def test_contract_names_types_and_dynamic_batch(tmp_path):
    est = ToyCorrector("zhou", core="pmc")
    to_onnx(est, tmp_path / "m.onnx", measured=training_like_poses(200), n_random=100)
    model = onnx.load(tmp_path / "m.onnx")
    onnx.checker.check_model(model, full_check=True)
    (inp,), (out,) = model.graph.input, model.graph.output
    assert inp.name == "pose" and out.name == "corrected"
    for v in (inp, out):
        assert v.type.tensor_type.elem_type == onnx.TensorProto.FLOAT
        dims = v.type.tensor_type.shape.dim
        assert dims[0].dim_param == "N" and dims[1].dim_value == 7
    assert model.opset_import[0].version == 17
    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    for n in (1, 7, 1000):
        poses = training_like_poses(n, seed=n)
        out = sess.run(None, {"pose": poses.astype(np.float32)})[0]
        assert out.shape == (n, 7) and out.dtype == np.float32
        np.testing.assert_allclose(out, est.predict(f32(poses)), atol=2e-6)


def test_only_listed_operators_in_exported_graphs(tmp_path):
    allowed = load_operator_list()
    assert {"Gemm", "Where", "Atan", "ArgMax"} <= allowed and "Atan2" not in allowed
    for rep in REPS:
        est = ToyCorrector(rep, core="mlp", activation="compet")
        report = to_onnx(est, tmp_path / f"{rep}.onnx", measured=training_like_poses(100), n_random=100)
        assert set(report["op_counts"]) <= allowed


def test_operator_outside_the_list_is_refused(tmp_path):
    class WithErf:
        representation = "pos"

        def forward(self, pose):
            xp = namespace(pose)
            bent = custom_op("Erf", pose[..., 0:3])
            return xp.concat([bent, pose[..., 3:7]], axis=-1)

    with pytest.raises(OperatorNotSupported) as info:
        build_model(WithErf().forward)
    message = f"{type(info.value).__name__}: {info.value}"
    assert message.startswith("OperatorNotSupported: operator 'Erf' in node '")
    assert "forward/Erf" in message and message.endswith("is not in export/operators.txt")
    assert not (tmp_path / "x.onnx").exists()

    # The same check on a hand-made model from outside the exporter.
    from onnx import TensorProto, helper
    node = helper.make_node("Erf", ["x"], ["y"], name="my_erf")
    graph = helper.make_graph([node], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])])
    with pytest.raises(OperatorNotSupported, match="operator 'Erf' in node 'my_erf' is not in export/operators.txt"):
        check_operators(helper.make_model(graph))


def test_operator_list_file_format(tmp_path):
    f = tmp_path / "ops.txt"
    f.write_text("# comment\nAdd\n  Mul  # trailing\n\n")
    assert load_operator_list(f) == {"Add", "Mul"}


def test_parity_failure_is_refused(tmp_path):
    from posecorr.export import ParityError

    class Liar(ToyCorrector):
        def predict(self, measured):   # disagrees with its own forward by 1 mm
            out = super().predict(measured)
            out[:, 0] += 1e-3
            return out

    est = Liar("zhou", core="pmc")
    with pytest.raises(ParityError, match="max position error"):
        to_onnx(est, tmp_path / "m.onnx", measured=training_like_poses(100), n_random=100)
    assert not (tmp_path / "m.onnx").exists()



class Flipper(ToyCorrector):
    """A corrector whose output quaternion is the same rotation in the sign the contract does
    not allow (qw < 0), in its graph and its predict alike."""

    def forward(self, pose):
        out = super().forward(pose)
        return namespace(out).concat([out[..., 0:3], -out[..., 3:7]], axis=-1)

    def predict(self, measured):
        out = super().predict(measured)
        out[:, 3:7] *= -1.0
        return out


def test_an_output_that_breaks_the_contract_is_named(tmp_path):
    """A graph whose output quaternion has qw < 0 was refused with its position and rotation
    errors, both within tolerance: the message named no cause."""
    from posecorr.export import ParityError

    with pytest.raises(ParityError, match=r"breaks the output contract: an output quaternion with qw = -[0-9.e-]+ < 0"):
        to_onnx(Flipper("zhou", core="pmc"), tmp_path / "m.onnx", measured=training_like_poses(100), n_random=100)
    assert not (tmp_path / "m.onnx").exists()


def test_a_pipeline_of_no_stage_gives_the_contracts_output(tmp_path):
    """Fitted with no effect and no core it passed its input through: a quaternion of norm
    1.0009 with qw < 0 came out, against the contract (unit, qw >= 0), and its export was
    refused. scipy's Rotation gives the canonical unit quaternion to compare with."""
    from scipy.spatial.transform import Rotation

    from posecorr.export.parity import run_onnx
    from posecorr.train.pipeline import CorrectionPipeline

    measured = training_like_poses(50)
    model = CorrectionPipeline().fit(measured, measured)
    poses = measured[:5].copy()
    poses[:, 3:] *= -1.0009
    q = Rotation.from_quat(poses[:, [4, 5, 6, 3]]).as_quat(canonical=True)[:, [3, 0, 1, 2]]
    expected = np.concatenate([poses[:, :3], q], axis=1)
    assert np.allclose(model.predict(poses), expected, atol=1e-12)
    model.to_onnx(tmp_path / "i.onnx", measured=measured, reference=measured)
    assert np.allclose(run_onnx(tmp_path / "i.onnx", poses), expected, atol=1e-6)

def test_metadata_round_trip(tmp_path):
    est = ToyCorrector("zhou", core="mlp", activation="logsig")
    measured = training_like_poses(300)
    reference = measured + 0.001
    metrics = {"rmse_pos": 0.0012, "rmse_rot": 0.003, "rmse_total": 0.0041, "improvement_total": 17.1}
    report = to_onnx(est, tmp_path / "m.onnx", measured=measured, reference=reference, n_random=500,
                     test_metrics=metrics, effects=["station", "mount"], trainer="br")
    info = read_info(tmp_path / "m.onnx")
    model = onnx.load(tmp_path / "m.onnx")
    props = {p.key: p.value for p in model.metadata_props}
    assert info["method"] == "mlp" and info["representation"] == "zhou"
    assert info["activation"] == "logsig" and info["trainer"] == "br"
    assert info["test_metrics"] == metrics and json.loads(props["test_metrics"]) == metrics
    assert info["effects"] == ["station", "mount"]
    assert info["opset"] == 17 and info["opset_import"] == {"ai.onnx": 17}
    assert info["training_data_digest"] == data_digest(measured, reference)
    assert info["training_data_digest"] != data_digest(measured, reference + 1e-12)
    # the same rows in any order, and no others
    from posecorr.controller.digest import set_digest

    shuffle = np.random.default_rng(0).permutation(len(measured))
    assert info["training_set_digest"] == set_digest(measured[shuffle], reference[shuffle])
    assert info["training_set_digest"] != set_digest(measured[shuffle], reference[shuffle] + 1e-12)
    assert info["training_set_digest"] != set_digest(measured[1:], reference[1:])
    assert info["parity"]["passed"] is True and info["parity"]["max_pos_m"] < 1e-5
    assert info["posecorr_version"] and "pose" in info["units"]
    assert info["inputs"] == [{"name": "pose", "dtype": "float32", "shape": ["N", 7]}]
    assert info["outputs"] == [{"name": "corrected", "dtype": "float32", "shape": ["N", 7]}]
    assert info["op_counts"] == op_counts(model)
    assert info["node_count"] == len(model.graph.node)
    assert info["initializer_count"] == len(model.graph.initializer)
    assert info["parameter_count"] == sum(int(np.prod(t.dims)) for t in model.graph.initializer)
    assert info["file_size"] == (tmp_path / "m.onnx").stat().st_size == report["file_size"]


def test_read_info_rejects_malformed_files(tmp_path):
    good = tmp_path / "m.onnx"
    to_onnx(ToyCorrector("pos", core="pmc"), good, measured=training_like_poses(100), n_random=50)
    data = good.read_bytes()
    # Random bytes: a field whose length runs past the end reads as a file cut short (1 in 12
    # seeds), the rest as no ONNX at all; a local generator, so the bytes do not depend on
    # which tests ran before in this worker.
    garbage = [bytes(np.random.default_rng(seed).integers(0, 256, 4000, dtype=np.uint8)) for seed in range(24)]
    cases = {"text": b"hello, this is not a model\n", **{f"garbage{i}": blob for i, blob in enumerate(garbage)}}
    for name, blob in cases.items():
        p = tmp_path / f"{name}.onnx"
        p.write_bytes(blob)
        with pytest.raises(ValueError, match="not a valid ONNX model|truncated file at byte"):
            read_info(p)
    # Cut short: libposecorr's protobuf reader (C) and this one name the same byte in the same words.
    from posecorr.controller.runtime import Corrector, PoseCorrError

    cut = {"empty": b"", "half": data[: len(data) // 2], "text ending in a length": b"hi\n",
           "a fixed32 cut": b"\x0d\x01\x02"}
    for name, blob in cut.items():
        p = tmp_path / "cut.onnx"
        p.write_bytes(blob)
        with pytest.raises(ValueError) as info:
            read_info(p)
        with pytest.raises(PoseCorrError) as in_c:
            Corrector(p, backend="c", allow_unsigned=True)
        said = str(info.value).removeprefix(f"{p}: ")
        assert said.startswith("truncated file at byte ") and said == str(in_c.value).removeprefix(f"{p}: "), name


# --- weights readable in place: aligned raw_data --------------------------------------------

SHIPPED = sorted((Path(__file__).resolve().parents[1] / "models").glob("*.onnx"))


def _assert_aligned(data: bytes) -> None:
    """Every initializer's raw_data, found by walking the wire format, is the bytes onnx's
    parser gives for it and starts on a 16-byte boundary."""
    from posecorr.export.aligned import raw_data_offsets

    tensors = [t for t in onnx.load_from_string(data).graph.initializer if t.raw_data]
    offsets = raw_data_offsets(data)
    assert len(offsets) == len(tensors) > 0
    for t, at in zip(tensors, offsets):
        assert data[at:at + len(t.raw_data)] == t.raw_data, t.name
        assert at % 16 == 0, (t.name, at)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_models_have_aligned_weights(path):
    data = path.read_bytes()
    _assert_aligned(data)
    onnx.checker.check_model(onnx.load_from_string(data))


def test_export_aligns_weights_and_changes_nothing_else(tmp_path):
    from posecorr.export.aligned import serialize_aligned

    est = ToyCorrector("zhou", core="mlp", activation="tansig", seed=3)
    to_onnx(est, tmp_path / "m.onnx", measured=training_like_poses(300), n_random=500)
    data = (tmp_path / "m.onnx").read_bytes()
    _assert_aligned(data)
    plain = onnx.load_from_string(data)
    for t in plain.graph.initializer:  # the padding is all that alignment adds
        assert set(t.doc_string) <= {" "}, t.name
        t.ClearField("doc_string")
    plain_bytes = plain.SerializeToString()  # protobuf's own layout, unaligned
    assert serialize_aligned(plain) == data  # same model, same layout: nothing else moved
    x = training_like_poses(64).astype(np.float32)
    runs = [ort.InferenceSession(b, providers=["CPUExecutionProvider"]).run(None, {"pose": x})[0]
            for b in (data, plain_bytes)]
    np.testing.assert_array_equal(runs[0], runs[1])


@pytest.mark.parametrize("make", ["pmc-pos", "physics-position-only"])
def test_a_position_only_model_passes_the_orientation_through_as_a_unit_quaternion(tmp_path, make):
    """A table's quaternions are unit within 1e-3; a position-only core or physics stage
    passed them through as they came, and the export refused its own graph (the output
    quaternion's norm off 1 by 0.0005). scipy's Rotation gives the canonical unit
    quaternion the output must be."""
    from scipy.spatial.transform import Rotation

    from posecorr.export.parity import run_onnx
    from posecorr.train import PMC
    from posecorr.train.physics import PhysicsModel

    measured = training_like_poses(60)
    measured[:, 3:] *= 1.0005
    reference = measured.copy()
    reference[:, :3] += 0.002 * measured[:, :3] ** 2
    model = (PMC("pos") if make == "pmc-pos" else PhysicsModel(("station",), with_rotation=False)).fit(measured, reference)
    to_onnx(model, tmp_path / "m.onnx", measured=measured, reference=reference)
    q = Rotation.from_quat(measured[:, [4, 5, 6, 3]]).as_quat(canonical=True)[:, [3, 0, 1, 2]]
    assert np.allclose(model.predict(measured)[:, 3:], q, atol=1e-12)
    assert np.allclose(run_onnx(tmp_path / "m.onnx", measured)[:, 3:], q, atol=1e-6)


def test_a_model_written_despite_a_broken_contract_says_which_clause(tmp_path, capsys):
    """parity="warn" writes the model and records the failure; the clause was not kept, so
    `posecorr info` printed FAILED beside errors within tolerance and no cause."""
    from posecorr.cli import main

    to_onnx(Flipper("zhou", core="pmc"), tmp_path / "m.onnx", measured=training_like_poses(100), n_random=100,
            parity="warn")
    assert read_info(tmp_path / "m.onnx")["parity"]["broken_clause"].startswith("an output quaternion with qw = -")
    assert main(["info", str(tmp_path / "m.onnx")]) == 0
    line = next(l for l in capsys.readouterr().out.splitlines() if "parity with the fitted estimator" in l)
    assert "FAILED" in line and "the graph breaks the output contract: an output quaternion with qw" in line, line
