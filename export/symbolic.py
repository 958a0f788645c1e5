"""Symbolic tensors: the third `posecorr._xp` namespace, which emits ONNX nodes.

A `Sym` stands for a tensor of a graph under construction. Code written against the
`_xp` interface (rotations, physical effects, the correctors' `forward`) runs unchanged on
it: every arithmetic operator and namespace call appends ONNX nodes (opset 17, default
domain, only operators of `export/operators.txt`) to the shared `Graph`.

Keeping graphs lean matters because the C runtime's single-pose latency grows with the
node count, so the builder
- folds constants: an operation whose inputs are all constants is computed at build time
  in float64 and becomes one float32 initializer,
- reuses identical constants and identical nodes (common-subexpression elimination),
- drops no-op nodes (x * 1, x + 0, x / 1, Reshape to the same shape, Where(c, a, a)),
- and `Graph.to_graph_proto` keeps only the nodes the outputs depend on.

Shapes are tuples with -1 for the dynamic batch dimension N. Floats in the graph are
float32; Python floats and numpy / torch arrays mixed into expressions become constants.
"""
from __future__ import annotations

import hashlib
import math
import sys
from typing import Any, Iterable, Sequence

import numpy as np

OPSET = 17

# ONNX TensorProto element types used here.
FLOAT, INT64, BOOL = 1, 7, 9


class ExportError(RuntimeError):
    """A forward pass that cannot be turned into an ONNX graph."""


def _elem_of(value: np.ndarray) -> int:
    if value.dtype == np.bool_:
        return BOOL
    if value.dtype.kind in "iu":
        return INT64
    if value.dtype.kind == "f":
        return FLOAT
    raise ExportError(f"unsupported constant dtype {value.dtype}")


def _to_numpy(value: Any) -> np.ndarray:
    """Python number, numpy array or torch tensor -> numpy array (float64 for floats)."""
    if hasattr(value, "detach"):  # torch tensor (parameters, buffers)
        value = value.detach().cpu().numpy()
    arr = np.asarray(value)
    if arr.dtype.kind in "fiu":
        # Ints in a float expression (2 * x, x * np.arange(3)) are float constants; index
        # constants are made by Graph.index().
        arr = arr.astype(np.float64)
    elif arr.dtype != np.bool_:
        raise ExportError(f"cannot use {type(value).__name__} of dtype {arr.dtype} in an exported graph")
    return arr


def broadcast_shapes(*shapes: Sequence[int]) -> tuple[int, ...]:
    """numpy broadcasting of shapes in which -1 is the (unknown, >= 1) batch size."""
    rank = max((len(s) for s in shapes), default=0)
    out: list[int] = []
    for axis in range(rank):
        dims = [s[len(s) - rank + axis] for s in shapes if len(s) - rank + axis >= 0]
        known = {d for d in dims if d not in (1, -1)}
        if len(known) > 1:
            raise ExportError(f"shapes {list(map(tuple, shapes))} do not broadcast")
        if known:
            out.append(known.pop())
        elif -1 in dims:
            out.append(-1)
        else:
            out.append(1)
    return tuple(out)


def _caller_scope() -> str:
    """Name of the first function outside this module on the stack: labels nodes so that
    an error about a node points at the formula that produced it. A list comprehension is a
    frame of its own, `<listcomp>`, up to Python 3.11 and part of its function from 3.12
    (PEP 709): the names, not the graph, differ across Pythons."""
    frame = sys._getframe(1)
    here = __file__
    while frame is not None and frame.f_code.co_filename == here:
        frame = frame.f_back
    return frame.f_code.co_name if frame is not None else "graph"


class Node:
    __slots__ = ("op_type", "inputs", "outputs", "attrs", "name")

    def __init__(self, op_type: str, inputs: list[str], outputs: list[str],
                 attrs: dict[str, Any], name: str) -> None:
        self.op_type, self.inputs, self.outputs, self.attrs, self.name = op_type, inputs, outputs, attrs, name


class Graph:
    """Nodes and initializers of one graph under construction."""

    def __init__(self) -> None:
        self.nodes: list[Node] = []
        self.initializers: dict[str, np.ndarray] = {}   # name -> value in its ONNX dtype
        self.inputs: list[tuple[str, int, tuple[int, ...]]] = []
        self._const_names: dict[bytes, str] = {}
        self._node_cache: dict[tuple, str] = {}
        self._producer: dict[str, Node] = {}
        self.shapes: dict[str, tuple[int, ...]] = {}   # tracked shape of every node output
        self._counter = 0
        self.ns = SymNamespace(self)

    # --- names --------------------------------------------------------------------------
    def _fresh(self, stem: str) -> str:
        self._counter += 1
        return f"{stem}_{self._counter}"

    # --- tensors ------------------------------------------------------------------------
    def input(self, name: str, shape: Sequence[int], elem: int = FLOAT) -> "Sym":
        self.inputs.append((name, elem, tuple(shape)))
        return Sym(self, name=name, shape=tuple(shape), elem=elem)

    def const(self, value: Any) -> "Sym":
        arr = _to_numpy(value)
        return Sym(self, value=arr, shape=arr.shape, elem=_elem_of(arr))

    def index(self, value: Any) -> "Sym":
        """An int64 constant (indices, axes, shapes)."""
        arr = np.asarray(value, dtype=np.int64)
        return Sym(self, value=arr, shape=arr.shape, elem=INT64)

    def lift(self, value: Any) -> "Sym":
        if isinstance(value, Sym):
            if value.graph is not self:
                raise ExportError("symbolic tensors of two different graphs were mixed")
            return value
        return self.const(value)

    def const_name(self, value: np.ndarray, elem: int) -> str:
        """The initializer holding `value` (float32 for floats), shared by equal constants."""
        onnx_value = np.array(value.astype({FLOAT: np.float32, INT64: np.int64, BOOL: np.bool_}[elem]))
        key = hashlib.sha1(str((elem, onnx_value.shape)).encode() + onnx_value.tobytes()).digest()
        name = self._const_names.get(key)
        if name is None:
            name = f"c{len(self._const_names)}"
            if onnx_value.ndim == 0 and elem == FLOAT:
                name += f"_{float(onnx_value):.4g}".replace("-", "m").replace(".", "p").replace("+", "")
            self._const_names[key] = name
            self.initializers[name] = onnx_value
        return name

    def name_of(self, x: "Sym") -> str:
        if x.name is None:
            x.name = self.const_name(x.value, x.elem)
        return x.name

    # --- nodes --------------------------------------------------------------------------
    def emit(self, op_type: str, inputs: Sequence["Sym | None"], shape: Sequence[int], elem: int = FLOAT,
             **attrs: Any) -> "Sym":
        """Append one node with a single output (or reuse an identical earlier node)."""
        names = [("" if x is None else self.name_of(x)) for x in inputs]
        key = (op_type, tuple(names), tuple(sorted((k, _hashable(v)) for k, v in attrs.items())))
        out = self._node_cache.get(key)
        if out is None:
            scope = _caller_scope()
            out = self._fresh(f"{scope}/{op_type}")
            node = Node(op_type, names, [out], dict(attrs), out)
            self.nodes.append(node)
            self._producer[out] = node
            self._node_cache[key] = out
            self.shapes[out] = tuple(shape)
        return Sym(self, name=out, shape=tuple(shape), elem=elem)

    def producer(self, x: "Sym") -> Node | None:
        return None if x.name is None else self._producer.get(x.name)


def _hashable(v: Any) -> Any:
    if isinstance(v, (list, tuple)):
        return tuple(_hashable(i) for i in v)
    if isinstance(v, np.ndarray):
        return (v.dtype.str, v.shape, v.tobytes())
    return v


class Sym:
    """A symbolic tensor: a graph value (`name`) or a build-time constant (`value`)."""

    # numpy must hand mixed expressions (ndarray op Sym) to our reflected operators.
    __array_ufunc__ = None
    pc_namespace: "SymNamespace"

    def __init__(self, graph: Graph, *, name: str | None = None, value: np.ndarray | None = None,
                 shape: tuple[int, ...] = (), elem: int = FLOAT) -> None:
        self.graph = graph
        self.name = name
        self.value = value
        self.shape = tuple(int(d) for d in shape)
        self.elem = elem

    @property
    def pc_namespace(self) -> "SymNamespace":  # type: ignore[override]
        return self.graph.ns

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def dtype(self) -> Any:
        return {FLOAT: np.float32, INT64: np.int64, BOOL: np.bool_}[self.elem]

    @property
    def is_const(self) -> bool:
        return self.value is not None

    def __repr__(self) -> str:
        what = "const" if self.is_const else self.name
        return f"Sym({what}, shape={self.shape}, elem={self.elem})"

    # Data-dependent Python control flow cannot be exported: say so clearly.
    def __bool__(self) -> bool:
        raise ExportError("a symbolic tensor has no value at export time: forward() must not branch "
                          "in Python on tensor values (use xp.where)")

    def __float__(self) -> float:
        if self.is_const and self.value.size == 1:
            return float(self.value)
        raise ExportError("float() of a symbolic tensor: its value is only known at run time")

    def __iter__(self):
        raise ExportError("iterating over a symbolic tensor is not supported; index x[..., i] instead")

    def __len__(self) -> int:
        if not self.shape or self.shape[0] < 0:
            raise ExportError("len() of a symbolic tensor with a dynamic first dimension")
        return self.shape[0]

    # --- arithmetic ---------------------------------------------------------------------
    def __add__(self, other: Any) -> "Sym":
        return _binary("Add", self, other)

    def __radd__(self, other: Any) -> "Sym":
        return _binary("Add", other, self)

    def __sub__(self, other: Any) -> "Sym":
        return _binary("Sub", self, other)

    def __rsub__(self, other: Any) -> "Sym":
        return _binary("Sub", other, self)

    def __mul__(self, other: Any) -> "Sym":
        return _binary("Mul", self, other)

    def __rmul__(self, other: Any) -> "Sym":
        return _binary("Mul", other, self)

    def __truediv__(self, other: Any) -> "Sym":
        return _binary("Div", self, other)

    def __rtruediv__(self, other: Any) -> "Sym":
        return _binary("Div", other, self)

    def __neg__(self) -> "Sym":
        return _neg(self)

    def __pos__(self) -> "Sym":
        return self

    def __pow__(self, exponent: Any) -> "Sym":
        if exponent == 2:
            return self * self
        if exponent == 1:
            return self
        if exponent == 0.5:
            return self.graph.ns.sqrt(self)
        raise ExportError(f"x ** {exponent!r} is not exportable (only 0.5, 1 and 2)")

    def __matmul__(self, other: Any) -> "Sym":
        return self.graph.ns.matmul(self, other)

    def __rmatmul__(self, other: Any) -> "Sym":
        return self.graph.ns.matmul(other, self)

    # --- comparisons (bool tensors) and logic -------------------------------------------
    def __lt__(self, other: Any) -> "Sym":
        return _binary("Less", self, other)

    def __le__(self, other: Any) -> "Sym":
        return _binary("LessOrEqual", self, other)

    def __gt__(self, other: Any) -> "Sym":
        return _binary("Greater", self, other)

    def __ge__(self, other: Any) -> "Sym":
        return _binary("GreaterOrEqual", self, other)

    def __and__(self, other: Any) -> "Sym":
        return _binary("And", self, other)

    def __rand__(self, other: Any) -> "Sym":
        return _binary("And", other, self)

    def __or__(self, other: Any) -> "Sym":
        return _binary("Or", self, other)

    def __ror__(self, other: Any) -> "Sym":
        return _binary("Or", other, self)

    def __invert__(self) -> "Sym":
        if self.elem != BOOL:
            raise ExportError("~x is only defined for bool tensors")
        if self.is_const:
            return self.graph.const(~self.value)
        return self.graph.emit("Not", [self], self.shape, BOOL)

    __hash__ = object.__hash__  # keep Syms hashable despite the comparison overloads

    # --- indexing -----------------------------------------------------------------------
    def __getitem__(self, index: Any) -> "Sym":
        return _getitem(self, index)


# --- elementwise machinery -----------------------------------------------------------------

_NUMPY_BINARY = {
    "Add": np.add, "Sub": np.subtract, "Mul": np.multiply, "Div": np.divide,
    "Less": np.less, "LessOrEqual": np.less_equal, "Greater": np.greater,
    "GreaterOrEqual": np.greater_equal, "Equal": np.equal, "And": np.logical_and,
    "Or": np.logical_or, "Max": np.maximum, "Min": np.minimum,
}
_BOOL_RESULT = {"Less", "LessOrEqual", "Greater", "GreaterOrEqual", "Equal", "And", "Or"}


def _graph_of(*xs: Any) -> Graph:
    for x in xs:
        if isinstance(x, Sym):
            return x.graph
    raise ExportError("no symbolic tensor among the arguments")


def _is_scalar_const(x: Sym, v: float) -> bool:
    return x.is_const and x.value.dtype.kind == "f" and bool(np.all(x.value == v))


def _neg(x: Sym) -> Sym:
    if x.is_const:
        return x.graph.const(-x.value)
    producer = x.graph.producer(x)
    if producer is not None and producer.op_type == "Neg":   # -(-y) = y
        src = producer.inputs[0]
        return Sym(x.graph, name=src, shape=x.shape, elem=x.elem)
    return x.graph.emit("Neg", [x], x.shape)


def _binary(op: str, a: Any, b: Any) -> Sym:
    g = _graph_of(a, b)
    a, b = g.lift(a), g.lift(b)
    if op in ("And", "Or"):
        if a.elem != BOOL or b.elem != BOOL:
            raise ExportError(f"{op} needs bool tensors")
    elif a.elem == BOOL or b.elem == BOOL:
        raise ExportError(f"arithmetic/comparison {op} on a bool tensor; use xp.where")
    shape = broadcast_shapes(a.shape, b.shape)
    elem = BOOL if op in _BOOL_RESULT else FLOAT
    if a.is_const and b.is_const:
        with np.errstate(all="ignore"):
            return g.const(_NUMPY_BINARY[op](a.value, b.value))
    # No-op elimination: only when the constant does not change the shape by broadcasting.
    if shape == b.shape and a.is_const and a.ndim <= b.ndim:
        if (op == "Add" and _is_scalar_const(a, 0.0)) or (op == "Mul" and _is_scalar_const(a, 1.0)):
            return b
        if op == "Mul" and _is_scalar_const(a, -1.0) or op == "Sub" and _is_scalar_const(a, 0.0):
            return _neg(b)
    if shape == a.shape and b.is_const and b.ndim <= a.ndim:
        if (op in ("Add", "Sub") and _is_scalar_const(b, 0.0)) or (op in ("Mul", "Div") and _is_scalar_const(b, 1.0)):
            return a
        if op in ("Mul", "Div") and _is_scalar_const(b, -1.0):
            return _neg(a)
    # a + (-y) -> a - y and a - (-y) -> a + y: one node instead of two (the Neg is pruned
    # if nothing else uses it).
    if op in ("Add", "Sub") and not b.is_const:
        producer = g.producer(b)
        if producer is not None and producer.op_type == "Neg":
            src = Sym(g, name=producer.inputs[0], shape=b.shape, elem=b.elem)
            return g.emit("Sub" if op == "Add" else "Add", [a, src], shape, elem)
    if op in ("Add", "Mul", "Max", "Min", "Equal", "And", "Or") and a.is_const and not b.is_const:
        a, b = b, a   # canonical order: more CSE hits
    return g.emit(op, [a, b], shape, elem)


def _unary(op: str, fn: Any, x: Any) -> Sym:
    if not isinstance(x, Sym):
        raise ExportError(f"{op} of a non-symbolic value")
    if x.elem != FLOAT:
        raise ExportError(f"{op} needs a float tensor")
    if x.is_const:
        with np.errstate(all="ignore"):
            return x.graph.const(fn(x.value))
    return x.graph.emit(op, [x], x.shape)


# --- indexing ---------------------------------------------------------------------------

def _getitem(x: Sym, index: Any) -> Sym:
    """Basic indexing: ints (Gather, the axis disappears), slices (Slice), `...`,
    and integer lists / arrays (Gather with a vector of indices)."""
    if not isinstance(index, tuple):
        index = (index,)
    n_real = sum(1 for i in index if i is not Ellipsis)
    if n_real > x.ndim or sum(1 for i in index if i is Ellipsis) > 1:
        raise ExportError(f"index {index!r} does not fit shape {x.shape}")
    per_axis: list[Any] = []
    for i in index:
        if i is Ellipsis:
            per_axis.extend([slice(None)] * (x.ndim - n_real))
        else:
            per_axis.append(i)
    per_axis.extend([slice(None)] * (x.ndim - len(per_axis)))
    out = x
    # Last axis first, so the axis numbers of the remaining entries stay valid.
    for axis in range(x.ndim - 1, -1, -1):
        out = _index_axis(out, axis, per_axis[axis])
    return out


def _index_axis(x: Sym, axis: int, idx: Any) -> Sym:
    g = x.graph
    dim = x.shape[axis]
    if isinstance(idx, slice):
        if idx == slice(None):
            return x
        if idx.step not in (None, 1):
            raise ExportError("slices with a step are not exportable")
        if dim < 0 and ((idx.start or 0) < 0 or (idx.stop is not None and idx.stop < 0)):
            raise ExportError("negative slice bounds on the dynamic axis")
        start, stop, _ = idx.indices(dim if dim >= 0 else 2**62)
        new_dim = max(stop - start, 0) if dim >= 0 or idx.stop is not None else -1
        if x.is_const:
            sl = [slice(None)] * x.ndim
            sl[axis] = idx
            return g.const(x.value[tuple(sl)])
        if dim >= 0 and start == 0 and stop == dim:
            return x
        shape = x.shape[:axis] + (new_dim,) + x.shape[axis + 1:]
        return g.emit("Slice", [x, g.index(np.array([start], np.int64)), g.index(np.array([stop], np.int64)),
                                g.index(np.array([axis], np.int64))], shape, x.elem)
    if isinstance(idx, (int, np.integer)):
        i = int(idx)
        if dim >= 0:
            if not -dim <= i < dim:
                raise ExportError(f"index {i} out of range for axis of size {dim}")
            i %= dim
        if x.is_const:
            return g.const(np.take(x.value, i, axis=axis))
        shape = x.shape[:axis] + x.shape[axis + 1:]
        return g.emit("Gather", [x, g.index(np.array(i, np.int64))], shape, x.elem, axis=axis)
    arr = np.asarray(idx)
    if arr.dtype.kind in "iu" and arr.ndim == 1:
        if dim >= 0:
            arr = arr % dim
        if x.is_const:
            return g.const(np.take(x.value, arr, axis=axis))
        shape = x.shape[:axis] + (len(arr),) + x.shape[axis + 1:]
        return g.emit("Gather", [x, g.index(arr)], shape, x.elem, axis=axis)
    raise ExportError(f"unsupported index {idx!r} (ints, slices, ... and integer lists only)")


def _norm_axis(axis: int, rank: int) -> int:
    if not -rank <= axis < rank:
        raise ExportError(f"axis {axis} out of range for rank {rank}")
    return axis % rank


# --- the namespace ----------------------------------------------------------------------

class SymNamespace:
    """The `_xp` interface on symbolic tensors: every call appends ONNX nodes."""

    name = "onnx"

    def __init__(self, graph: Graph) -> None:
        self.g = graph

    # elementwise ---------------------------------------------------------------------------
    def sqrt(self, x: Sym) -> Sym:
        return _unary("Sqrt", np.sqrt, x)

    def sin(self, x: Sym) -> Sym:
        return _unary("Sin", np.sin, x)

    def cos(self, x: Sym) -> Sym:
        return _unary("Cos", np.cos, x)

    def tan(self, x: Sym) -> Sym:
        return _unary("Tan", np.tan, x)

    def exp(self, x: Sym) -> Sym:
        return _unary("Exp", np.exp, x)

    def tanh(self, x: Sym) -> Sym:
        return _unary("Tanh", np.tanh, x)

    def abs(self, x: Sym) -> Sym:
        return _unary("Abs", np.abs, x)

    def sigmoid(self, x: Sym) -> Sym:
        return _unary("Sigmoid", lambda v: 0.5 * (1.0 + np.tanh(0.5 * v)), x)

    def atan2(self, y: Any, x: Any) -> Sym:
        """Quadrant-correct atan2 from Atan (ONNX has none), 9 nodes.

        atan(y / x) is right for x > 0; for x < 0 add pi (y >= 0) or -pi (y < 0). Where
        x == 0 the divisor is replaced by a tiny positive number, so y / x is +-huge (atan
        -> +-pi/2) or 0 / tiny = 0 for the (0, 0) case (atan2(0, 0) = 0 as in numpy).
        Signed zeros are not distinguished: atan2(0, -0.0) gives 0 where numpy gives pi.
        """
        g = self.g
        y, x = g.lift(y), g.lift(x)
        if y.is_const and x.is_const:
            return g.const(np.arctan2(y.value, x.value))
        x_is_zero = _binary("Equal", x, 0.0)
        x_safe = self.where(x_is_zero, 1e-30, x)
        angle = _unary("Atan", np.arctan, y / x_safe)
        half_turn = self.where(y < 0.0, -math.pi, math.pi)
        return self.where(x < 0.0, angle + half_turn, angle)

    def maximum(self, a: Any, b: Any) -> Sym:
        return _binary("Max", a, b)

    def minimum(self, a: Any, b: Any) -> Sym:
        return _binary("Min", a, b)

    def clip(self, x: Any, lo: float | None, hi: float | None) -> Sym:
        g = self.g
        x = g.lift(x)
        if x.is_const:
            return g.const(np.clip(x.value, lo, hi))
        lo_s = None if lo is None else g.const(np.float64(lo))
        hi_s = None if hi is None else g.const(np.float64(hi))
        if lo_s is None and hi_s is None:
            return x
        return g.emit("Clip", [x, lo_s, hi_s] if hi_s is not None else [x, lo_s], x.shape)

    def where(self, cond: Any, a: Any, b: Any) -> Sym:
        g = self.g
        cond, a, b = g.lift(cond), g.lift(a), g.lift(b)
        if cond.elem != BOOL:
            raise ExportError("where() needs a bool condition (a comparison)")
        shape = broadcast_shapes(cond.shape, a.shape, b.shape)
        if cond.is_const and a.is_const and b.is_const:
            return g.const(np.where(cond.value, a.value, b.value))
        if cond.is_const and bool(np.all(cond.value)) and shape == a.shape:
            return a
        if cond.is_const and not bool(np.any(cond.value)) and shape == b.shape:
            return b
        if a is b or (a.name is not None and a.name == b.name) or (
                a.is_const and b.is_const and a.value.shape == b.value.shape and np.array_equal(a.value, b.value)):
            if shape == a.shape:
                return a
        return g.emit("Where", [cond, a, b], shape, a.elem)

    # shape ------------------------------------------------------------------------------
    def _unsqueeze(self, x: Sym, axis: int) -> Sym:
        shape = x.shape[:axis] + (1,) + x.shape[axis:]
        if x.is_const:
            return self.g.const(np.expand_dims(x.value, axis))
        return self.g.emit("Unsqueeze", [x, self.g.index(np.array([axis], np.int64))], shape, x.elem)

    def _zeros_like(self, x: Sym) -> Sym:
        """0 with x's (dynamic) shape: Expand is not in the operator list, x * 0 is one node."""
        if x.is_const:
            return self.g.const(np.zeros(x.shape))
        return self.g.emit("Mul", [x, self.g.const(np.float64(0.0))], x.shape)

    def stack(self, xs: Sequence[Any], axis: int = -1) -> Sym:
        """Unsqueeze + one Concat; float entries are filled in by one Add of a constant row."""
        g = self.g
        items = [g.lift(x) for x in xs]
        if not items:
            raise ExportError("stack of nothing")
        shape = broadcast_shapes(*[i.shape for i in items])
        out_rank = len(shape) + 1
        ax = _norm_axis(axis, out_rank)
        if all(i.is_const for i in items):
            return g.const(np.stack(np.broadcast_arrays(*[i.value for i in items]), axis=ax))
        if ax == out_rank - 1:
            vectorised = self._stack_gathers(items, shape)
            if vectorised is not None:
                return vectorised
        ref = next(i for i in items if not i.is_const)
        tensors = [i for i in items if not i.is_const]
        zero = None
        if any(i.shape != shape for i in tensors) or any(i.is_const for i in items):
            # One zero tensor of the full broadcast shape (from the first tensor that has it,
            # else the sum of zeros of all tensors, which broadcasts to it).
            full = next((i for i in tensors if i.shape == shape), None)
            zero = self._zeros_like(full) if full is not None else None
            if zero is None:
                zero = self._zeros_like(tensors[0])
                for t in tensors[1:]:
                    zero = _binary("Add", zero, self._zeros_like(t))
        parts: list[Sym] = []
        row = np.zeros(len(items))
        for k, item in enumerate(items):
            if item.is_const:
                if item.value.shape not in ((), (1,)) and item.shape != shape:
                    # A constant array entry of its own shape: broadcast it through the zero.
                    parts.append(self._unsqueeze(_binary("Add", zero, item), ax))
                    continue
                row[k] = float(np.reshape(item.value, ()))
                parts.append(self._unsqueeze(zero, ax))
            else:
                t = item if item.shape == shape else _binary("Add", item, zero)
                parts.append(self._unsqueeze(t, ax))
        out_shape = shape[:ax] + (len(items),) + shape[ax:]
        out = parts[0] if len(parts) == 1 else g.emit("Concat", parts, out_shape, ref.elem, axis=ax)
        if np.any(row != 0.0):
            trailing = out_rank - ax - 1
            out = _binary("Add", out, g.const(np.reshape(row, (len(items),) + (1,) * trailing)))
        return out

    def _shape_of(self, name: str) -> tuple[int, ...]:
        if name in self.g.shapes:
            return self.g.shapes[name]
        return next(shape for n, _, shape in self.g.inputs if n == name)

    def _scalar_gather(self, x: Sym) -> tuple[str, int] | None:
        """(source, index) when x = source[..., index] (a last-axis Gather of one index)."""
        node = self.g.producer(x)
        if node is None or node.op_type != "Gather":
            return None
        try:
            src_shape = self._shape_of(node.inputs[0])
        except StopIteration:
            return None
        index = self.g.initializers.get(node.inputs[1])
        if src_shape is None or index is None or index.ndim != 0 or node.attrs.get("axis") != len(src_shape) - 1:
            return None
        return node.inputs[0], int(index)

    def _stack_gathers(self, items: list[Sym], shape: tuple[int, ...]) -> Sym | None:
        """Peephole for stacks along the last axis (fewer nodes, same values):

        stack([s[..., i], s[..., j], ...])                 -> Gather(s, [i, j, ...])
        stack([s[..., i] * t[..., j], ...]) (any one binary op) -> op(Gather(s, I), Gather(t, J))

        The first is matrix_to_zhou and friends, the second PMC's quadratic features: k
        Unsqueeze + Concat (+ k products) become one Gather (+ one Gather and one product).
        """
        if any(i.is_const or i.shape != shape for i in items) or len(items) < 2:
            return None
        g = self.g
        direct = [self._scalar_gather(i) for i in items]
        if all(d is not None for d in direct) and len({d[0] for d in direct}) == 1:
            src = direct[0][0]
            source = Sym(g, name=src, shape=self._shape_of(src), elem=items[0].elem)
            return g.emit("Gather", [source, g.index([d[1] for d in direct])], shape + (len(items),),
                          items[0].elem, axis=len(shape))
        nodes = [g.producer(i) for i in items]
        if any(n is None for n in nodes) or len({n.op_type for n in nodes}) != 1:
            return None
        op = nodes[0].op_type
        if op not in ("Mul", "Add", "Sub", "Div") or any(len(n.inputs) != 2 for n in nodes):
            return None
        operands = []
        for k in range(2):
            parts = [self._scalar_gather(Sym(g, name=n.inputs[k], shape=shape)) for n in nodes]
            if any(p is None for p in parts) or len({p[0] for p in parts}) != 1:
                return None
            src = Sym(g, name=parts[0][0], shape=self._shape_of(parts[0][0]))
            operands.append(g.emit("Gather", [src, g.index([p[1] for p in parts])], shape + (len(items),),
                                   axis=len(shape)))
        return g.emit(op, operands, shape + (len(items),))

    def concat(self, xs: Sequence[Any], axis: int = -1) -> Sym:
        g = self.g
        items = [g.lift(x) for x in xs]
        rank = items[0].ndim
        ax = _norm_axis(axis, rank)
        if all(i.is_const for i in items):
            return g.const(np.concatenate([i.value for i in items], axis=ax))
        items = [i for i in items if i.shape[ax] != 0]
        if len(items) == 1:
            return items[0]
        dims = [i.shape[ax] for i in items]
        total = -1 if any(d < 0 for d in dims) else sum(dims)
        others = broadcast_shapes(*[i.shape[:ax] + (1,) + i.shape[ax + 1:] for i in items])
        shape = others[:ax] + (total,) + others[ax + 1:]
        return g.emit("Concat", items, shape, items[0].elem, axis=ax)

    def sum(self, x: Sym, axis: int = -1, keepdims: bool = False) -> Sym:
        g = self.g
        x = g.lift(x)
        ax = _norm_axis(axis, x.ndim)
        if x.is_const:
            return g.const(np.sum(x.value, axis=ax, keepdims=keepdims))
        shape = x.shape[:ax] + ((1,) if keepdims else ()) + x.shape[ax + 1:]
        if x.shape[ax] == 1:
            return x if keepdims else self.reshape(x, shape)
        return g.emit("ReduceSum", [x, g.index(np.array([ax], np.int64))], shape, x.elem,
                      keepdims=int(bool(keepdims)))

    def reshape(self, x: Sym, shape: Sequence[int]) -> Sym:
        g = self.g
        x = g.lift(x)
        shape = tuple(int(d) for d in shape)
        if x.is_const:
            return g.const(np.reshape(x.value, shape))
        if shape == x.shape:
            return x
        if 0 in shape:
            raise ExportError("reshape to a shape with a 0 dimension")
        if shape.count(-1) > 1:
            raise ExportError(f"reshape to {shape}: more than one unknown dimension")
        known_in = [d for d in x.shape if d >= 0]
        if -1 not in x.shape and -1 in shape:
            size = int(np.prod(known_in))
            rest = int(np.prod([d for d in shape if d >= 0]))
            shape = tuple(size // rest if d == -1 else d for d in shape)
        return g.emit("Reshape", [x, g.index(np.array(shape, np.int64))], shape, x.elem)

    def swap_last(self, x: Sym) -> Sym:
        g = self.g
        x = g.lift(x)
        if x.is_const:
            return g.const(np.swapaxes(x.value, -1, -2))
        perm = list(range(x.ndim))
        perm[-1], perm[-2] = perm[-2], perm[-1]
        shape = x.shape[:-2] + (x.shape[-1], x.shape[-2])
        return g.emit("Transpose", [x], shape, x.elem, perm=perm)

    def matmul(self, a: Any, b: Any) -> Sym:
        g = _graph_of(a, b) if isinstance(a, Sym) or isinstance(b, Sym) else self.g
        a, b = g.lift(a), g.lift(b)
        if a.is_const and b.is_const:
            return g.const(np.matmul(a.value, b.value))
        sa, sb = a.shape, b.shape
        if len(sa) == 1 and len(sb) == 1:
            shape: tuple[int, ...] = ()
        elif len(sa) == 1:
            shape = sb[:-2] + (sb[-1],)
        elif len(sb) == 1:
            shape = sa[:-1]
        else:
            shape = broadcast_shapes(sa[:-2], sb[:-2]) + (sa[-2], sb[-1])
        return g.emit("MatMul", [a, b], shape)

    def linear(self, x: Any, weight: Any, bias: Any) -> Sym:
        """x @ weight + bias, weight (in, out): one Gemm for a 2-D x."""
        g = self.g
        x, w = g.lift(x), g.lift(weight)
        b = None if bias is None else g.lift(bias)
        if x.is_const and w.is_const and (b is None or b.is_const):
            return g.const(x.value @ w.value + (0.0 if b is None else b.value))
        if x.ndim == 2 and w.ndim == 2 and (b is None or b.ndim <= 1):
            shape = (x.shape[0], w.shape[1])
            inputs = [x, w] + ([] if b is None else [b])
            return g.emit("Gemm", inputs, shape)
        out = self.matmul(x, w)
        return out if b is None else out + b

    def const(self, value: Any, like: Any = None) -> Sym:
        return self.g.const(value)

    # MLP activations along the last axis ----------------------------------------------------
    def softmax(self, x: Sym) -> Sym:
        x = self.g.lift(x)
        if x.is_const:
            e = np.exp(x.value - np.max(x.value, axis=-1, keepdims=True))
            return self.g.const(e / np.sum(e, axis=-1, keepdims=True))
        return self.g.emit("Softmax", [x], x.shape, axis=x.ndim - 1)

    def step(self, x: Sym) -> Sym:
        """hardlim: 1 where x >= 0 else 0 (GreaterOrEqual + Cast)."""
        x = self.g.lift(x)
        if x.is_const:
            return self.g.const((x.value >= 0).astype(np.float64))
        return self.g.emit("Cast", [x >= 0.0], x.shape, FLOAT, to=FLOAT)

    def compet(self, x: Sym) -> Sym:
        """MATLAB compet: 1 at the FIRST maximum of the last axis (ArgMax + Equal + Cast)."""
        g = self.g
        x = g.lift(x)
        if x.is_const:
            out = np.zeros_like(x.value)
            np.put_along_axis(out, np.argmax(x.value, axis=-1)[..., None], 1.0, axis=-1)
            return g.const(out)
        k = x.shape[-1]
        if k < 0:
            raise ExportError("compet along a dynamic axis")
        arg = g.emit("ArgMax", [x], x.shape[:-1] + (1,), INT64, axis=x.ndim - 1, keepdims=1, select_last_index=0)
        hot = g.emit("Equal", [arg, g.index(np.arange(k, dtype=np.int64))], x.shape, BOOL)
        return g.emit("Cast", [hot], x.shape, FLOAT, to=FLOAT)


def custom_op(op_type: str, *inputs: Any, shape: Sequence[int] | None = None, **attrs: Any) -> Sym:
    """Emit an arbitrary ONNX node (an escape hatch; the exporter still checks the operator
    against `export/operators.txt`, so this is how a refused graph is produced in tests)."""
    g = _graph_of(*inputs)
    xs = [g.lift(i) for i in inputs]
    return g.emit(op_type, xs, tuple(shape) if shape is not None else xs[0].shape, **attrs)


def all_nodes(graph: Graph) -> Iterable[Node]:
    return iter(graph.nodes)
