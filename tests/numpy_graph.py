"""NumpyGraph: a small numpy evaluator of posecorr's ONNX operator set, a test oracle.

A third implementation of the operators beside runtime_c and onnxruntime, written straight
from the ONNX operator specification (float32, one node at a time, no fusion). The tests
hold it to `export/operators.txt` (it implements exactly the listed operators) and to
onnxruntime on the single-operator parity graphs and the shipped models
(tests/test_numpy_graph.py).
"""
from __future__ import annotations

import os
from typing import Callable

import numpy as np
import onnx
from onnx import helper, numpy_helper

def _attr(node, name, default=None):
    for a in node.attribute:
        if a.name == name:
            return helper.get_attribute_value(a)
    return default


class NumpyGraph:
    """Evaluates a posecorr ONNX graph with numpy (float32), one node at a time."""

    def __init__(self, path: str | os.PathLike | bytes) -> None:
        m = onnx.load_from_string(path) if isinstance(path, bytes) else onnx.load(str(path))
        self.consts = {t.name: numpy_helper.to_array(t) for t in m.graph.initializer}
        self.nodes = list(m.graph.node)

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
            return numpy_helper.to_array(a.t)
        if a.name == "value_float":
            return np.float32(a.f)
        if a.name == "value_floats":
            return np.asarray(a.floats, np.float32)
        if a.name == "value_int":
            return np.int64(a.i)
        if a.name == "value_ints":
            return np.asarray(a.ints, np.int64)
    raise ValueError("Constant without value")


def _div(n, ins, g):
    a, b = ins
    if a.dtype.kind in "iu":
        # ONNX (like C) truncates integer quotients toward zero; numpy's // floors.
        return (np.sign(a) * np.sign(b) * (np.abs(a) // np.abs(b))).astype(np.result_type(a, b))
    return a / b


def _unsqueeze(n, ins, g):
    axes = _axes(n, ins)
    return np.expand_dims(ins[0], tuple(a if a >= 0 else a + ins[0].ndim + len(axes) for a in axes))


_OPS: dict[str, Callable] = {
    "Abs": lambda n, i, g: np.abs(i[0]), "Neg": lambda n, i, g: -i[0],
    "Add": lambda n, i, g: i[0] + i[1], "Sub": lambda n, i, g: i[0] - i[1],
    "Mul": lambda n, i, g: i[0] * i[1],
    "Div": _div,
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

OPERATORS = frozenset(_OPS)
