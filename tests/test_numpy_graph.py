"""tests/numpy_graph.py (a numpy evaluator of posecorr's operator set) against its contract:
exactly the operators of export/operators.txt, and onnxruntime's results on graphs using them."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))

import graphs  # noqa: E402
from numpy_graph import OPERATORS, NumpyGraph  # noqa: E402

LISTED = frozenset(line.split("#")[0].strip() for line in (ROOT / "export" / "operators.txt").read_text().splitlines()
                   if line.split("#")[0].strip())
CASES = {**graphs.op_cases(), **graphs.cross_row_cases()}
SHIPPED = sorted((ROOT / "models").glob("*.onnx"))


def _onnxruntime(model: bytes, x: np.ndarray) -> np.ndarray:
    session = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    return session.run(["corrected"], {"pose": x})[0]


def test_implements_exactly_the_listed_operators() -> None:
    assert not LISTED - OPERATORS, f"listed in export/operators.txt, not in NumpyGraph: {sorted(LISTED - OPERATORS)}"
    assert not OPERATORS - LISTED, f"in NumpyGraph, not in export/operators.txt: {sorted(OPERATORS - LISTED)}"


def test_the_graphs_below_use_every_listed_operator() -> None:
    """The agreement tests below reach every operator (else one could be wrong unseen)."""
    used = {node.op_type for build in CASES.values() for m in build() for node in m.graph.node}
    assert LISTED <= used, f"no graph uses {sorted(LISTED - used)}"


@pytest.mark.parametrize("name", sorted(CASES))
def test_agrees_with_onnxruntime_on_each_operator_graph(name: str) -> None:
    x = graphs.op_inputs(4, seed=3)
    if name in graphs.CROSS_ROW:
        x = x[:1]
    for m in CASES[name]():
        blob = m.SerializeToString()
        np.testing.assert_allclose(NumpyGraph(blob)(x), _onnxruntime(blob, x), rtol=1e-5, atol=1e-5, err_msg=name)


def test_integer_division_truncates_toward_zero() -> None:
    """ONNX Div on integers truncates (-7 / 2 = -3); numpy's // floors (-4)."""
    g = graphs.G()
    a = g.op("Cast", [g.op("Mul", [g.cols("pose", list(range(7))), g.f32(2.0)])], to=onnx.TensorProto.INT64)
    q = g.op("Div", [a, g.i64([2, -2, 3, -3, 4, -4, 7])])
    blob = g.model(g.op("Cast", [q], to=onnx.TensorProto.FLOAT)).SerializeToString()
    x = np.array([[-3.5, -3.5, 3.5, -2.5, -4.5, 4.5, -6.5]], np.float32)  # 2x: exact integers
    expected = np.array([[-3, 3, 2, 1, -2, -2, -1]], np.float32)
    np.testing.assert_array_equal(_onnxruntime(blob, x), expected)
    np.testing.assert_array_equal(NumpyGraph(blob)(x), expected)


@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_agrees_with_onnxruntime_on_the_shipped_models(path: Path) -> None:
    x = graphs.random_poses(64, seed=5) * np.array([0.3, 0.3, 0.3, 1, 1, 1, 1], np.float32) \
        + np.array([0.0, -0.6, 0.5, 0, 0, 0, 0], np.float32)
    blob = path.read_bytes()
    np.testing.assert_allclose(NumpyGraph(blob)(x), _onnxruntime(blob, x), rtol=1e-5, atol=2e-5)
