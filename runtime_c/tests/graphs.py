"""ONNX test graphs for libposecorr, built with onnx.helper.

Every graph honours the contract: input `pose` float32 [N,7] (and, in `time_model`, `t`
float32 [N]) -> output `corrected` float32 [N,7]. Single-operator graphs feed the operator with exact data movement from the pose
columns (Gather/Reshape, no arithmetic), flatten its result per row and emit a 7-column
window of it, so any wrong element shows up in the output. Used by the pytest suite, the
sanitizer runs and the fuzz seed corpus.
"""
from __future__ import annotations

import contextlib

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17


class G:
    def __init__(self, seed: int = 0) -> None:
        self.nodes: list = []
        self.inits: list = []
        self.n = 0
        self.rng = np.random.default_rng(seed)

    def name(self, p: str = "t") -> str:
        self.n += 1
        return f"{p}{self.n}"

    def const(self, arr, dtype=None) -> str:
        a = np.asarray(arr, dtype=dtype)
        nm = self.name("c")
        self.inits.append(numpy_helper.from_array(a, nm))
        return nm

    def i64(self, vals) -> str:
        return self.const(np.asarray(vals, dtype=np.int64))

    def f32(self, vals) -> str:
        return self.const(np.asarray(vals, dtype=np.float32))

    def op(self, op_type: str, inputs, n_out: int = 1, **attrs):
        outs = [self.name() for _ in range(n_out)]
        self.nodes.append(helper.make_node(op_type, list(inputs), outs, name=self.name("n"),
                                           **attrs))
        return outs[0] if n_out == 1 else outs

    # -- shaped views of the pose ----------------------------------------------------
    def cols(self, x: str, idx) -> str:
        """[N, len(idx)] picked from pose columns (exact)."""
        return self.op("Gather", [x, self.i64(idx)], axis=1)

    def shaped(self, x: str, shape_tail, offset: int = 0) -> str:
        """[N, *shape_tail] filled with pose columns (cyclic), exact."""
        m = int(np.prod(shape_tail))
        idx = [(offset + k * 3) % 7 for k in range(m)]
        return self.op("Reshape", [self.cols(x, idx), self.i64([0] + list(shape_tail))])

    def model(self, out: str, metadata: dict | None = None, rename_input: str | None = None,
              width: int = 7, opset: int = OPSET, inputs_before=(), inputs_after=()
              ) -> onnx.ModelProto:
        """inputs_before/after: more graph inputs (ValueInfoProto) around `pose`."""
        inp = helper.make_tensor_value_info(rename_input or "pose", TensorProto.FLOAT, ["N", width])
        outp = helper.make_tensor_value_info("corrected", TensorProto.FLOAT, ["N", 7])
        nodes = list(self.nodes)
        nodes.append(helper.make_node("Identity", [out], ["corrected"], name="final"))
        g = helper.make_graph(nodes, "g", [*inputs_before, inp, *inputs_after], [outp],
                              self.inits)
        m = helper.make_model(g, opset_imports=[helper.make_opsetid("", opset)],
                              producer_name="posecorr-tests")
        m.ir_version = 8
        for k, v in (metadata or {}).items():
            e = m.metadata_props.add()
            e.key, e.value = k, v
        return m


# Values of y a model emits at once: the position columns. The quaternion columns carry the
# pose's own (unit) quaternion, because every runtime refuses a result whose quaternion is
# not unit (the pose contract holds for every graph).
WINDOW = 3


def window(g: G, y: str, width: int, start: int, x: str = "pose") -> str:
    """The per-row flattened y ([N, width]) from `start` in the position columns (up to
    WINDOW of them), the rest of the pose after them: the output is a pose whose quaternion
    is the input's."""
    take = min(WINDOW, width - start)
    parts = [g.op("Slice", [y, g.i64([start]), g.i64([start + take]), g.i64([1])]),
             g.op("Slice", [x, g.i64([take]), g.i64([7]), g.i64([1])])]
    return g.op("Concat", parts, axis=1)


def finish(g: G, y: str, per_row: int, to_float: bool = False) -> list[onnx.ModelProto]:
    """Models emitting every element of y ([N, ...], per_row elements per row)."""
    flat = g.op("Reshape", [y, g.i64([0, -1])])
    if to_float:
        flat = g.op("Cast", [flat], to=TensorProto.FLOAT)
    models = []
    for start in range(0, per_row, WINDOW):
        gg = G()
        gg.nodes, gg.inits, gg.n = list(g.nodes), list(g.inits), g.n
        models.append(gg.model(window(gg, flat, per_row, start)))
    return models


# -- single-operator cases ------------------------------------------------------------
# Each returns (list of models, input value range, note). Input ranges keep the math
# well conditioned (Sqrt of Abs, Tan away from its poles is handled by tolerance).

def _unary(op, **kw):
    def build():
        g = G()
        x = g.shaped("pose", [2, 3])
        if op == "Sqrt":
            x = g.op("Abs", [x])
        return finish(g, g.op(op, [x], **kw), 6)
    return build


def _binary(op, sa, sb, out_bool=False, dtype="f"):
    def build():
        g = G(1)
        a = g.shaped("pose", sa, 0)
        b = g.shaped("pose", sb, 2) if sb and sb[0] == "N" else None
        if b is None:
            a = g.shaped("pose", sa, 0)
            b = g.shaped("pose", sb, 2) if sb else None
        if dtype == "i":
            a = g.op("Cast", [g.op("Mul", [a, g.f32(3.0)])], to=TensorProto.INT64)
            b = g.op("Cast", [g.op("Mul", [b, g.f32(3.0)])], to=TensorProto.INT64)
        y = g.op(op, [a, b])
        tail = np.broadcast_shapes(tuple(sa), tuple(sb))
        if dtype == "i" and not out_bool:
            return finish(g, y, int(np.prod(tail)), to_float=True)
        return finish(g, y, int(np.prod(tail)), to_float=out_bool)
    return build


def _const_rhs(op, sa, const_shape, out_bool=False, seed=3):
    def build():
        g = G(seed)
        a = g.shaped("pose", sa)
        c = g.f32(np.round(g.rng.uniform(-1, 1, const_shape), 1).astype(np.float32))
        y = g.op(op, [a, c])
        tail = np.broadcast_shapes((1, *sa), tuple(const_shape))[1:]
        return finish(g, y, int(np.prod(tail)), to_float=out_bool)
    return build


def _const_lhs(op, sa, const_shape, seed=4):
    def build():
        g = G(seed)
        a = g.shaped("pose", sa)
        c = g.f32(np.round(g.rng.uniform(0.5, 1.5, const_shape), 1).astype(np.float32))
        y = g.op(op, [c, a])
        tail = np.broadcast_shapes((1, *sa), tuple(const_shape))[1:]
        return finish(g, y, int(np.prod(tail)))
    return build


def _custom(fn):
    return fn


def case_logic():
    g = G()
    a = g.op("Greater", [g.shaped("pose", [4]), g.f32(0.0)])
    b = g.op("Less", [g.shaped("pose", [4], 1), g.f32(0.3)])
    y = g.op("Or", [g.op("And", [a, b]), g.op("Not", [b])])
    return finish(g, y, 4, to_float=True)


def case_where():
    g = G()
    c = g.op("Greater", [g.shaped("pose", [3, 1]), g.f32(0.0)])
    y = g.op("Where", [c, g.shaped("pose", [3, 4], 1), g.f32(np.arange(4, dtype=np.float32))])
    return finish(g, y, 12)


def case_where_same():
    g = G()
    c = g.op("GreaterOrEqual", [g.shaped("pose", [5]), g.shaped("pose", [5], 2)])
    y = g.op("Where", [c, g.shaped("pose", [5], 1), g.shaped("pose", [5], 4)])
    return finish(g, y, 5)


def case_where_int():
    g = G()
    c = g.op("LessOrEqual", [g.shaped("pose", [3]), g.f32(0.1)])
    a = g.op("Cast", [g.op("Mul", [g.shaped("pose", [3], 1), g.f32(4.0)])], to=TensorProto.INT64)
    y = g.op("Where", [c, a, g.i64([7, -7, 1])])
    return finish(g, y, 3, to_float=True)


def case_cast():
    g = G()
    x = g.op("Mul", [g.shaped("pose", [6]), g.f32(2.5)])
    i = g.op("Cast", [x], to=TensorProto.INT64)
    bl = g.op("Cast", [i], to=TensorProto.BOOL)
    f1 = g.op("Cast", [bl], to=TensorProto.FLOAT)
    f2 = g.op("Cast", [i], to=TensorProto.FLOAT)
    b2 = g.op("Cast", [x], to=TensorProto.BOOL)
    i2 = g.op("Cast", [b2], to=TensorProto.INT64)
    f3 = g.op("Cast", [i2], to=TensorProto.FLOAT)
    f4 = g.op("Cast", [x], to=TensorProto.FLOAT)
    y = g.op("Concat", [f1, f2, f3, f4], axis=1)
    return finish(g, y, 24)


def case_int_arith():
    g = G()
    a = g.op("Cast", [g.op("Mul", [g.shaped("pose", [4]), g.f32(5.0)])], to=TensorProto.INT64)
    b = g.i64([3, -2, 1, 4])
    parts = [g.op(o, [a, b]) for o in ("Add", "Sub", "Mul", "Div", "Max", "Min")]
    parts += [g.op(o, [a, b]) for o in ("Equal", "Greater", "Less", "GreaterOrEqual", "LessOrEqual")]
    parts = [g.op("Cast", [p], to=TensorProto.FLOAT) for p in parts]
    parts += [g.op("Cast", [g.op("Abs", [a])], to=TensorProto.FLOAT),
              g.op("Cast", [g.op("Neg", [a])], to=TensorProto.FLOAT)]
    y = g.op("Concat", parts, axis=1)
    return finish(g, y, 4 * len(parts))


def case_minmax_variadic():
    g = G()
    a, b, c = g.shaped("pose", [3, 2]), g.shaped("pose", [1, 2], 1), g.shaped("pose", [3, 1], 2)
    y = g.op("Concat", [g.op("Max", [a, b, c]), g.op("Min", [a, b, c]), g.op("Max", [a])], axis=2)
    return finish(g, y, 18)


def case_gemm(transA=0, transB=0, c_shape=(5,), act=None, alpha=1.0, beta=1.0):
    def build():
        g = G(7)
        K, M = 6, 5
        a = g.shaped("pose", [K])
        if transA:
            # A^T for N rows: Gemm needs 2-D A; use [K, N] via Transpose.
            a = g.op("Transpose", [a], perm=[1, 0])
        w = g.rng.standard_normal((M, K) if transB else (K, M)).astype(np.float32)
        ins = [a, g.f32(w)]
        if c_shape is not None:
            ins.append(g.f32(g.rng.standard_normal(c_shape).astype(np.float32)))
        y = g.op("Gemm", ins, transA=transA, transB=transB, alpha=alpha, beta=beta)
        if act == "Clip":
            y = g.op("Clip", [y, g.f32(-0.5), g.f32(0.7)])
        elif act in ("radbas", "radbas_shared"):
            # exp(-(y * y)) as the exporter writes it; shared: y is read on as well, so the
            # three nodes cannot become the Gemm's activation
            r = g.op("Exp", [g.op("Neg", [g.op("Mul", [y, y])])])
            y = g.op("Add", [r, y]) if act == "radbas_shared" else r
        elif act:
            y = g.op(act, [y])
        return finish(g, y, M)
    return build


# These mix rows on purpose (runtime B / runtime gather indices over the batch): the
# loader refuses them, and with max_batch=1 they run pose by pose (cross_row_cases).
CROSS_ROW = {"gemm_runtime_b", "gather_runtime"}


def case_gemm_runtime_b():
    g = G()
    a = g.shaped("pose", [3])
    bmat = g.op("Reshape", [g.op("Slice", [g.shaped("pose", [6], 1), g.i64([0]), g.i64([6]),
                                          g.i64([1])]), g.i64([-1, 3])])
    # B = rows of the first pose only, as a runtime tensor [2,3]^T -> transB on runtime B
    b = g.op("Slice", [bmat, g.i64([0]), g.i64([2]), g.i64([0])])
    y = g.op("Gemm", [a, b], transB=1, alpha=0.5)
    return finish(g, y, 2)


def case_matmul(sa, sb, b_const=True):
    def build():
        g = G(5)
        a = g.shaped("pose", sa)
        if b_const:
            b = g.f32(g.rng.standard_normal(sb).astype(np.float32))
        else:
            b = g.shaped("pose", sb, 3)
        y = g.op("MatMul", [a, b])
        ta = (1, *sa)
        tb = tuple(sb) if b_const else (1, *sb)
        shp = np.matmul(np.zeros(ta), np.zeros(tb)).shape[1:]
        return finish(g, y, int(np.prod(shp)))
    return build


def case_reduce(op, axes, keepdims, as_input=True):
    def build():
        g = G()
        x = g.shaped("pose", [2, 3, 2])
        if as_input:
            y = g.op(op, [x, g.i64(axes)], keepdims=keepdims)
        else:
            y = g.op(op, [x], axes=axes, keepdims=keepdims)
        shp = np.zeros((1, 2, 3, 2)).sum(axis=tuple(axes), keepdims=bool(keepdims)).shape[1:]
        return finish(g, y, int(np.prod(shp)))
    return build


def case_argmax(axis, keepdims, last=0):
    def build():
        g = G()
        x = g.shaped("pose", [3, 4])
        if last:
            x = g.op("Max", [x, g.f32(0.2)])  # ties
        y = g.op("ArgMax", [x], axis=axis, keepdims=keepdims, select_last_index=last)
        shp = np.zeros((1, 3, 4)).argmax(axis=axis).shape[1:]
        return finish(g, y, int(np.prod(shp)), to_float=True)
    return build


def case_softmax(axis):
    def build():
        g = G()
        y = g.op("Softmax", [g.shaped("pose", [3, 4])], axis=axis)
        return finish(g, y, 12)
    return build


def case_slice(starts, ends, axes, steps):
    def build():
        g = G()
        x = g.shaped("pose", [4, 5])
        ins = [x, g.i64(starts), g.i64(ends)]
        if axes is not None:
            ins.append(g.i64(axes))
        if steps is not None:
            ins.append(g.i64(steps))
        y = g.op("Slice", ins)
        ref = np.zeros((1, 4, 5))
        sl = [slice(None)] * 3
        for k, (s, e) in enumerate(zip(starts, ends)):
            ax = axes[k] if axes is not None else k
            st = steps[k] if steps is not None else 1
            sl[ax] = slice(s, e, st)
        shp = ref[tuple(sl)].shape[1:]
        return finish(g, y, int(np.prod(shp)))
    return build


def case_gather(axis, idx):
    def build():
        g = G()
        x = g.shaped("pose", [3, 4])
        y = g.op("Gather", [x, g.i64(idx)], axis=axis)
        shp = np.take(np.zeros((1, 3, 4)), np.asarray(idx), axis=axis).shape[1:]
        return finish(g, y, int(np.prod(shp)))
    return build


def case_gather_runtime():
    g = G()
    x = g.shaped("pose", [3, 4])
    idx = g.op("ArgMax", [g.shaped("pose", [3], 1)], axis=1, keepdims=0)  # [N] runtime
    sel = g.op("Gather", [x, idx], axis=1)  # [N? ...] -> rank 3: [N, N, 4]
    y = g.op("ReduceSum", [sel, g.i64([1])], keepdims=0)
    return finish(g, y, 4)


def case_views():
    g = G()
    x = g.shaped("pose", [2, 3])
    u = g.op("Unsqueeze", [x, g.i64([1, -1])])           # [N,1,2,3,1]
    s = g.op("Squeeze", [u, g.i64([1])])                   # [N,2,3,1]
    s = g.op("Squeeze", [s, g.i64([-1])])                  # [N,2,3]
    t = g.op("Transpose", [s], perm=[0, 2, 1])             # [N,3,2]
    r = g.op("Reshape", [t, g.i64([-1, 6])])
    c = g.op("Constant", [], value=numpy_helper.from_array(np.arange(6, dtype=np.float32), "v"))
    cf = g.op("Constant", [], value_float=0.5)
    y = g.op("Add", [g.op("Mul", [g.op("Identity", [r]), cf]), c])
    return finish(g, y, 6)


def case_constant_forms():
    g = G()
    a = g.op("Constant", [], value_floats=[1.0, -2.0, 3.0])
    i = g.op("Constant", [], value_ints=[2, 0, 1])
    k = g.op("Constant", [], value_int=1)
    x = g.shaped("pose", [3])
    y1 = g.op("Mul", [x, a])
    y2 = g.op("Gather", [y1, i], axis=1)
    y3 = g.op("Gather", [y2, k], axis=1)
    y = g.op("Concat", [y2, g.op("Unsqueeze", [y3, g.i64([1])])], axis=1)
    return finish(g, y, 4)


def case_concat():
    g = G()
    a, b = g.shaped("pose", [2, 1]), g.shaped("pose", [2, 3], 1)
    y = g.op("Concat", [a, b, a], axis=-1)
    return finish(g, y, 10)


def case_concat_empty():
    """Inner sizes 2, 1 and 0 add up to the number of inputs, as three columns would: the
    columns kernel read the empty input's block for a column (past its end)."""
    g = G()
    t = g.shaped("pose", [2, 3])
    axis = g.i64([2])
    parts = [g.op("Slice", [t, g.i64([lo]), g.i64([hi]), axis]) for lo, hi in ((0, 2), (2, 3), (2, 2))]
    return finish(g, g.op("Concat", parts, axis=2), 6)


def case_folding():
    """A constant-only subgraph feeding the pose path (folded at load)."""
    g = G()
    w = g.f32(np.linspace(-1, 1, 6).astype(np.float32).reshape(2, 3))
    wf = g.op("Reshape", [g.op("Transpose", [g.op("Tanh", [g.op("Mul", [w, g.f32(2.0)])])],
                                             perm=[1, 0]), g.i64([6])])
    # Slice, Clip (padded operands) and ReduceSum (axes input) folded at load as well
    wf = g.op("Clip", [g.op("Slice", [wf, g.i64([0]), g.i64([6]), g.i64([0])]), g.f32(-0.9)])
    wf = g.op("Add", [wf, g.op("ReduceSum", [wf, g.i64([0])], keepdims=1)])
    y = g.op("Add", [g.shaped("pose", [6]), wf])
    return finish(g, y, 6)


UNARY = ["Abs", "Atan", "Cos", "Exp", "Neg", "Relu", "Sigmoid", "Sin", "Sqrt", "Tan", "Tanh"]
FBIN = ["Add", "Sub", "Mul", "Div", "Max", "Min"]
CMP = ["Equal", "Greater", "GreaterOrEqual", "Less", "LessOrEqual"]


def op_cases() -> dict:
    cases = {}
    for op in UNARY:
        cases[f"unary_{op}"] = _unary(op)
    for op in FBIN:
        cases[f"bin_{op}_same"] = _binary(op, [2, 3], [2, 3])
        cases[f"bin_{op}_bcast"] = _binary(op, [2, 3], [2, 1])
        cases[f"bin_{op}_const_row"] = _const_rhs(op, [2, 3], [3])
        cases[f"bin_{op}_const_scalar"] = _const_rhs(op, [5], [])
        cases[f"bin_{op}_outer"] = _const_rhs(op, [3, 1], [1, 4])
        # the broadcast operand on the left: scalar, column and row layouts of A
        cases[f"bin_{op}_const_scalar_lhs"] = _const_lhs(op, [5], [])
        cases[f"bin_{op}_bcast_lhs"] = _binary(op, [2, 1], [2, 3])
        cases[f"bin_{op}_const_row_lhs"] = _const_lhs(op, [2, 3], [3])
    for op in CMP:
        cases[f"cmp_{op}_same"] = _binary(op, [4], [4], out_bool=True)
        cases[f"cmp_{op}_const"] = _const_rhs(op, [2, 2], [2], out_bool=True)
    cases["clip"] = lambda: (lambda g: finish(g, g.op("Clip", [g.shaped("pose", [5]), g.f32(-0.3), g.f32(0.4)]), 5))(G())
    cases["clip_min_only"] = lambda: (lambda g: finish(g, g.op("Clip", [g.shaped("pose", [5]), g.f32(-0.3)]), 5))(G())
    cases["logic"] = case_logic
    cases["where_bcast"] = case_where
    cases["where_same"] = case_where_same
    cases["where_int"] = case_where_int
    cases["cast"] = case_cast
    cases["int_arith"] = case_int_arith
    cases["minmax_variadic"] = case_minmax_variadic
    cases["gemm_plain"] = case_gemm()
    cases["gemm_transB"] = case_gemm(transB=1)
    cases["gemm_transA"] = case_gemm(transA=1, c_shape=None)
    cases["gemm_alpha_beta"] = case_gemm(alpha=0.7, beta=-1.3, c_shape=(1, 5))
    cases["gemm_c_scalar"] = case_gemm(c_shape=())
    cases["gemm_no_c"] = case_gemm(c_shape=None, transB=1)
    # B transposed: not the MLP layer, so the one-pose plan expands it (radbas as its nodes)
    for act in ("Tanh", "Sigmoid", "Relu", "Clip", "radbas"):
        cases[f"gemm_fused_{act}"] = case_gemm(transB=1, act=act)
    # the MLP layer (B as [K, N], a bias row) with the activations it fuses
    for act in ("Tanh", "Sigmoid", "Relu", "Clip", "radbas"):
        cases[f"gemm_layer_{act}"] = case_gemm(act=act)
    cases["gemm_layer_radbas_shared"] = case_gemm(act="radbas_shared")
    cases["matmul_2d"] = case_matmul([4], [4, 3])
    cases["matmul_batched_constB"] = case_matmul([2, 3], [3, 4])
    cases["matmul_batched_runtimeB"] = case_matmul([2, 3], [3, 2], b_const=False)
    cases["matmul_vec"] = case_matmul([2, 3], [3])
    cases["matmul_bcast_batch"] = case_matmul([2, 1, 3], [2, 3, 2], b_const=False)
    for axes, kd in (([1], 1), ([1], 0), ([2, 3], 1), ([-1], 0), ([1, 3], 0)):
        cases[f"reducesum_{axes}_{kd}"] = case_reduce("ReduceSum", axes, kd)
        cases[f"reducemax_{axes}_{kd}"] = case_reduce("ReduceMax", axes, kd, as_input=False)
    for axis, kd in ((1, 1), (2, 0), (-1, 1)):
        cases[f"argmax_{axis}_{kd}"] = case_argmax(axis, kd)
    cases["argmax_last"] = case_argmax(2, 1, last=1)
    cases["softmax_last"] = case_softmax(-1)
    cases["softmax_mid"] = case_softmax(1)
    cases["slice_basic"] = case_slice([1], [3], [1], None)
    cases["slice_neg_step"] = case_slice([-1, 4], [-10, 0], [2, 1], [-2, -1])
    cases["slice_clamp"] = case_slice([0, -100], [100, 2], [1, 2], [2, 1])
    cases["slice_huge_steps"] = case_slice([1, -1], [4, -100], [1, 2], [2**62, -2**62])
    cases["slice_default_axes"] = case_slice([0, 1, 1], [1000, 3, 4], None, None)
    cases["gather_axis1_vec"] = case_gather(1, [2, 0, -1])
    cases["gather_axis2_scalar"] = case_gather(2, 3)
    cases["gather_axis1_matrix"] = case_gather(1, [[0, 1], [2, -3]])
    cases["views"] = case_views
    cases["constant_forms"] = case_constant_forms
    cases["concat"] = case_concat
    cases["concat_empty"] = case_concat_empty
    cases["folding"] = case_folding
    return cases


def cross_row_cases() -> dict:
    """Graphs whose row i reads row j (CROSS_ROW), kept apart from op_cases."""
    return {"gemm_runtime_b": case_gemm_runtime_b, "gather_runtime": case_gather_runtime}


# -- the realistic pose -> pose corrector ------------------------------------------------

def pose_model(seed: int = 0, hidden=(20, 20, 20, 20), metadata: dict | None = None) -> onnx.ModelProto:
    """quat -> R -> 6D (+ scaled position) -> tanh MLP -> Gram-Schmidt -> R -> quat."""
    g = G(seed)
    rng = g.rng
    x = "pose"
    col = lambda t, k: g.op("Slice", [t, g.i64([k]), g.i64([k + 1]), g.i64([1])])
    pos = g.op("Slice", [x, g.i64([0]), g.i64([3]), g.i64([1])])
    q = g.op("Slice", [x, g.i64([3]), g.i64([7]), g.i64([1])])
    qn = g.op("Div", [q, g.op("Sqrt", [g.op("ReduceSum", [g.op("Mul", [q, q]), g.i64([1])], keepdims=1)])])
    w, qx, qy, qz = (col(qn, k) for k in range(4))
    two = g.f32(2.0)
    one = g.f32(1.0)
    m = lambda a, b: g.op("Mul", [a, b])
    add = lambda a, b: g.op("Add", [a, b])
    sub = lambda a, b: g.op("Sub", [a, b])
    xx, yy, zz = m(qx, qx), m(qy, qy), m(qz, qz)
    xy, xz, yz = m(qx, qy), m(qx, qz), m(qy, qz)
    wx, wy, wz = m(w, qx), m(w, qy), m(w, qz)
    R = [[sub(one, m(two, add(yy, zz))), m(two, sub(xy, wz)), m(two, add(xz, wy))],
         [m(two, add(xy, wz)), sub(one, m(two, add(xx, zz))), m(two, sub(yz, wx))],
         [m(two, sub(xz, wy)), m(two, add(yz, wx)), sub(one, m(two, add(xx, yy)))]]
    six = g.op("Concat", [R[0][0], R[1][0], R[2][0], R[0][1], R[1][1], R[2][1]], axis=1)
    mean = rng.uniform(-0.5, 0.5, 3).astype(np.float32)
    scale = rng.uniform(0.2, 0.5, 3).astype(np.float32)
    ps = g.op("Div", [g.op("Sub", [pos, g.f32(mean)]), g.f32(scale)])
    h = g.op("Concat", [ps, six], axis=1)
    sizes = [9, *hidden, 9]
    for i in range(len(sizes) - 1):
        W = (rng.standard_normal((sizes[i + 1], sizes[i])) / np.sqrt(sizes[i])).astype(np.float32)
        b = (0.1 * rng.standard_normal(sizes[i + 1])).astype(np.float32)
        h = g.op("Gemm", [h, g.f32(W), g.f32(b)], transB=1)
        if i < len(sizes) - 2:
            h = g.op("Tanh", [h])
    dp = g.op("Slice", [h, g.i64([0]), g.i64([3]), g.i64([1])])
    d6 = g.op("Slice", [h, g.i64([3]), g.i64([9]), g.i64([1])])
    pos_out = g.op("Add", [pos, g.op("Mul", [dp, g.f32(np.float32(0.01))])])
    six2 = g.op("Add", [six, g.op("Mul", [d6, g.f32(np.float32(0.05))])])
    a1 = g.op("Slice", [six2, g.i64([0]), g.i64([3]), g.i64([1])])
    a2 = g.op("Slice", [six2, g.i64([3]), g.i64([6]), g.i64([1])])
    nrm = lambda v: g.op("Div", [v, g.op("Sqrt", [g.op("ReduceSum", [m(v, v), g.i64([1])], keepdims=1)])])
    b1 = nrm(a1)
    dot = g.op("ReduceSum", [m(b1, a2), g.i64([1])], keepdims=1)
    b2 = nrm(sub(a2, m(dot, b1)))
    c = lambda v, k: g.op("Gather", [v, g.i64([k])], axis=1)
    b1c, b2c = [c(b1, k) for k in range(3)], [c(b2, k) for k in range(3)]
    b3c = [sub(m(b1c[1], b2c[2]), m(b1c[2], b2c[1])),
           sub(m(b1c[2], b2c[0]), m(b1c[0], b2c[2])),
           sub(m(b1c[0], b2c[1]), m(b1c[1], b2c[0]))]
    r = [[b1c[i], b2c[i], b3c[i]] for i in range(3)]  # r[i][j] = R_ij
    tr = add(add(r[0][0], r[1][1]), r[2][2])
    eps = g.f32(1e-12)
    sq = lambda v: m(g.op("Sqrt", [g.op("Max", [add(one, v), eps])]), two)
    quarter = g.f32(0.25)
    d = lambda a, s: g.op("Div", [a, s])
    s0 = sq(tr)
    qa = g.op("Concat", [m(s0, quarter), d(sub(r[2][1], r[1][2]), s0), d(sub(r[0][2], r[2][0]), s0),
                         d(sub(r[1][0], r[0][1]), s0)], axis=1)
    s1 = sq(sub(sub(r[0][0], r[1][1]), r[2][2]))
    qb = g.op("Concat", [d(sub(r[2][1], r[1][2]), s1), m(s1, quarter), d(add(r[0][1], r[1][0]), s1),
                         d(add(r[0][2], r[2][0]), s1)], axis=1)
    s2 = sq(sub(sub(r[1][1], r[0][0]), r[2][2]))
    qc = g.op("Concat", [d(sub(r[0][2], r[2][0]), s2), d(add(r[0][1], r[1][0]), s2), m(s2, quarter),
                         d(add(r[1][2], r[2][1]), s2)], axis=1)
    s3 = sq(sub(sub(r[2][2], r[0][0]), r[1][1]))
    qd = g.op("Concat", [d(sub(r[1][0], r[0][1]), s3), d(add(r[0][2], r[2][0]), s3),
                         d(add(r[1][2], r[2][1]), s3), m(s3, quarter)], axis=1)
    piv = g.op("ArgMax", [g.op("Concat", [tr, r[0][0], r[1][1], r[2][2]], axis=1)], axis=1, keepdims=1)
    is_k = lambda k: g.op("Equal", [piv, g.i64([k])])
    qsel = g.op("Where", [is_k(0), qa, g.op("Where", [is_k(1), qb, g.op("Where", [is_k(2), qc, qd])])])
    qsel = g.op("Where", [g.op("Less", [col(qsel, 0), g.f32(0.0)]), g.op("Neg", [qsel]), qsel])
    qout = nrm(qsel)
    out = g.op("Concat", [pos_out, qout], axis=1)
    meta = {"posecorr_version": "0.1.0", "method": "mlp", "representation": "zhou"}
    meta.update(metadata or {})
    return g.model(out, metadata=meta)


def time_input(elem=TensorProto.FLOAT, shape=("N",), name: str = "t"):
    return helper.make_tensor_value_info(name, elem, list(shape))


def time_model(t_first: bool = False) -> onnx.ModelProto:
    """corrected = pose + t * rate (a drift linear in time; t float32 [N] as a second
    input, declared before `pose` when t_first)."""
    g = G()
    rate = g.f32(np.array([[1e-4, -2e-4, 3e-5, 0, 0, 0, 0]], np.float32))
    col = g.op("Unsqueeze", ["t", g.i64([1])])
    y = g.op("Add", ["pose", g.op("Mul", [col, rate])])
    vi = [time_input()]
    return g.model(y, **({"inputs_before": vi} if t_first else {"inputs_after": vi}))


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.6, 0.6, (n, 3))
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([p, q], axis=1).astype(np.float32)


def model_box(model) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) float32 of a model's metadata input_bounds (model: a path, bytes or a
    ModelProto); KeyError without it."""
    import json

    if not isinstance(model, onnx.ModelProto):
        model = onnx.load_from_string(model) if isinstance(model, bytes) else onnx.load(str(model))
    meta = {p.key: p.value for p in model.metadata_props}
    lo, hi = np.asarray(json.loads(meta["input_bounds"]), np.float32)
    return lo, hi


def poses_in_box(model, n: int, seed: int = 0) -> np.ndarray:
    """random_poses with positions uniform in the inner 90 % of the model's input_bounds:
    poses the runtimes correct rather than refuse."""
    lo, hi = model_box(model)
    x = random_poses(n, seed)
    u = np.random.default_rng(seed + 1).uniform(0.05, 0.95, (n, 3))
    x[:, :3] = (lo + (hi - lo) * u).astype(np.float32)
    return x


# Metadata a test graph needs to load without PC_LOAD_ALLOW_UNBOUNDED: a wide box and a
# reach no test graph exceeds.
BOUNDED = {"input_bounds": "[[-10, -10, -10], [10, 10, 10]]", "correction_reach": "[100, 4]"}


def signed(model, aligned: bool = False) -> bytes:
    """`model` (a ModelProto) serialised with a fresh model_digest, as a producer that signs
    its files writes it (the one it carried, if any, is replaced); `aligned`: through the
    exporter's serialize_aligned."""
    from posecorr.controller import digest

    m = onnx.ModelProto()
    m.CopyFrom(model)
    kept = [(e.key, e.value) for e in m.metadata_props if e.key != digest.KEY]
    del m.metadata_props[:]
    for key, value in kept + [(digest.KEY, digest.PLACEHOLDER)]:
        entry = m.metadata_props.add()
        entry.key, entry.value = key, value
    if aligned:
        from posecorr.export.aligned import serialize_aligned

        return digest.sign(serialize_aligned(m))
    return digest.sign(m.SerializeToString())


def offset_graph(model, dx: float = 5000.0):
    """`model` (a ModelProto, changed in place and returned) with a node adding dx to x
    after everything else: a graph gone wrong that still answers poses."""
    for node in model.graph.node:
        node.output[:] = ["before_offset" if o == "corrected" else o for o in node.output]
    shift = np.zeros((1, 7), np.float32)
    shift[0, 0] = dx
    model.graph.initializer.append(numpy_helper.from_array(shift, "offset"))
    model.graph.node.append(helper.make_node("Add", ["before_offset", "offset"], ["corrected"], name="offset"))
    return model


def without_metadata(model, *keys: str):
    """`model` (a ModelProto, changed in place and returned) without the metadata `keys`."""
    kept = [(e.key, e.value) for e in model.metadata_props if e.key not in keys]
    del model.metadata_props[:]
    for key, value in kept:
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    return model


def op_inputs(n: int, seed: int = 0) -> np.ndarray:
    """Poses for the operator cases: positions uniform in [-2, 2], unit quaternions (every
    runtime refuses another)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-2, 2, (n, 7))
    x[:, 3:] /= np.linalg.norm(x[:, 3:], axis=1, keepdims=True)
    return x.astype(np.float32)


# -- building the runtime for tests -------------------------------------------------------

@contextlib.contextmanager
def build_lock(build_dir):
    """Holds build_dir for one builder: the test suite runs its files in several processes
    (pytest-xdist), and two cmake builds in one folder overwrite each other's objects. The
    lock ends with the file's closing. Unlike posecorr.safeio.exclusive, it waits for the
    other builder, and it keeps its file: an unlinked lock file lets a third process hold a
    new one beside a process still waiting on the old."""
    import fcntl
    from pathlib import Path

    build_dir = Path(build_dir)
    build_dir.parent.mkdir(parents=True, exist_ok=True)
    with open(build_dir.parent / f".{build_dir.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def build_runtime(build_dir, *options: str, build_type: str = "Release"):
    """Configures and builds runtime_c into build_dir (incremental); returns the Path."""
    import shutil
    import subprocess
    from pathlib import Path

    src = Path(__file__).resolve().parents[1]
    build_dir = Path(build_dir)
    cmake = shutil.which("cmake")
    if cmake is None:
        raise RuntimeError("cmake is required to build runtime_c")
    with build_lock(build_dir):
        if not (build_dir / "CMakeCache.txt").exists():
            subprocess.run([cmake, "-S", str(src), "-B", str(build_dir),
                            f"-DCMAKE_BUILD_TYPE={build_type}", *options],
                           check=True, capture_output=True, text=True)
        r = subprocess.run([cmake, "--build", str(build_dir), "--parallel", "2"],
                           capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"building runtime_c failed:\n{r.stdout[-4000:]}\n{r.stderr[-4000:]}")
    return build_dir


def build_test_runtime():
    """The runtime with its C tests, in build/c-test: the one build the test modules share."""
    from pathlib import Path

    return build_runtime(Path(__file__).resolve().parents[2] / "build" / "c-test", "-DPC_BUILD_TESTS=ON")
