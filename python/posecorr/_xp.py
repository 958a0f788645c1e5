"""A minimal array namespace so that every formula is written once.

Rotation and effect formulas in posecorr are written against the small interface below
plus arithmetic operators (+ - * / unary -, with arrays or Python floats), comparisons
(< <= > >=) and last-axis indexing `x[..., i]`, `x[..., i:j]`, and a `.shape` whose
batch entries may be -1).

The interface (every namespace implements exactly these):
  sqrt sin cos tan exp tanh abs atan2 sigmoid        elementwise
  maximum(a, b) minimum(a, b) clip(x, lo, hi)         elementwise, b/lo/hi may be floats
  where(cond, a, b)                                   a, b arrays or floats
  stack(xs, axis=-1) concat(xs, axis=-1)              xs may mix arrays and floats (stack)
  sum(x, axis=-1, keepdims=False)
  reshape(x, shape) swap_last(x) matmul(a, b)
  linear(x, weight(in, out), bias(out))               one Gemm when exported
  softmax(x) step(x) compet(x)                        along the last axis (MLP activations)
  const(value, like)                                  a constant of like's float type The same code then runs on numpy arrays, on torch tensors
(differentiable) and on the symbolic tensors of `posecorr.export`, which turn each call
into ONNX nodes. That is how the simulator, the fit, the diagnosis and the exported graph
share one implementation of each formula.

torch is imported only when a torch tensor is passed in, so the controller-side install
(numpy only) never loads it.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np


# The longest last axis NumpyNamespace.sum adds term by term (numpy's own loop is pairwise
# from 8 terms on, so beyond 7 the written-out adds would change the bits).
_ADDS_WRITTEN_OUT = 7


class NumpyNamespace:
    name = "numpy"

    sqrt = staticmethod(np.sqrt)
    sin = staticmethod(np.sin)
    cos = staticmethod(np.cos)
    exp = staticmethod(np.exp)
    tanh = staticmethod(np.tanh)
    abs = staticmethod(np.abs)
    atan2 = staticmethod(np.arctan2)
    maximum = staticmethod(np.maximum)
    minimum = staticmethod(np.minimum)
    matmul = staticmethod(np.matmul)

    @staticmethod
    def where(cond: Any, a: Any, b: Any) -> Any:
        return np.where(cond, a, b)

    @staticmethod
    def stack(xs: Sequence[Any], axis: int = -1) -> Any:
        shape = getattr(xs[0], "shape", None)
        if all(isinstance(x, np.ndarray) and x.shape == shape for x in xs):
            return np.stack(xs, axis=axis)      # the usual case; broadcasting would cost as much again
        return np.stack(np.broadcast_arrays(*xs), axis=axis)

    @staticmethod
    def concat(xs: Sequence[Any], axis: int = -1) -> Any:
        return np.concatenate(xs, axis=axis)

    @staticmethod
    def sum(x: Any, axis: int = -1, keepdims: bool = False) -> Any:
        # numpy's reduction costs ten times the adds over a last axis of 3 or 4 (a vector, a
        # quaternion: nearly every sum here); under 8 terms numpy adds in order from +0.0, so
        # the adds written out, +0.0 last (a sum of -0.0s is +0.0 to numpy), give its bits.
        if axis in (-1, np.ndim(x) - 1) and getattr(x, "dtype", None) is not None and x.dtype.kind == "f" \
                and 1 < x.shape[-1] <= _ADDS_WRITTEN_OUT:
            total = x[..., 0] + x[..., 1]
            for i in range(2, x.shape[-1]):
                total += x[..., i]
            total += 0.0
            return total[..., None] if keepdims else total
        return np.sum(x, axis=axis, keepdims=keepdims)

    @staticmethod
    def reshape(x: Any, shape: Sequence[int]) -> Any:
        return np.reshape(x, shape)

    @staticmethod
    def swap_last(x: Any) -> Any:
        return np.swapaxes(x, -1, -2)

    @staticmethod
    def const(value: Any, like: Any) -> Any:
        dtype = like.dtype if isinstance(like, np.ndarray) and like.dtype.kind == "f" else np.float64
        return np.asarray(value, dtype=dtype)

    tan = staticmethod(np.tan)

    @staticmethod
    def sigmoid(x: Any) -> Any:
        return 0.5 * (1.0 + np.tanh(0.5 * x))

    @staticmethod
    def clip(x: Any, lo: float, hi: float) -> Any:
        return np.clip(x, lo, hi)

    @staticmethod
    def softmax(x: Any) -> Any:
        e = np.exp(x - np.max(x, axis=-1, keepdims=True))
        return e / np.sum(e, axis=-1, keepdims=True)

    @staticmethod
    def step(x: Any) -> Any:
        return np.where(x >= 0, 1.0, 0.0).astype(x.dtype)

    @staticmethod
    def compet(x: Any) -> Any:
        # MATLAB's compet: 1 at the first maximum of each row, 0 elsewhere.
        out = np.zeros_like(x)
        np.put_along_axis(out, np.argmax(x, axis=-1)[..., None], 1.0, axis=-1)
        return out

    @staticmethod
    def linear(x: Any, weight: Any, bias: Any) -> Any:
        """x @ weight + bias with weight (in, out): one Gemm in the exported graph."""
        return x @ weight + bias


class TorchNamespace:
    name = "torch"

    def __init__(self) -> None:
        import torch

        self.t = torch
        self.sqrt = torch.sqrt
        self.sin = torch.sin
        self.cos = torch.cos
        self.exp = torch.exp
        self.tanh = torch.tanh
        self.abs = torch.abs
        self.atan2 = torch.atan2
        self.matmul = torch.matmul

    def _tensor(self, x: Any, like: Any) -> Any:
        if isinstance(x, self.t.Tensor):
            return x
        return self.t.as_tensor(x, dtype=like.dtype, device=like.device)

    def where(self, cond: Any, a: Any, b: Any) -> Any:
        ref = a if isinstance(a, self.t.Tensor) else b
        return self.t.where(cond, self._tensor(a, ref), self._tensor(b, ref))

    def maximum(self, a: Any, b: Any) -> Any:
        ref = a if isinstance(a, self.t.Tensor) else b
        return self.t.maximum(self._tensor(a, ref), self._tensor(b, ref))

    def minimum(self, a: Any, b: Any) -> Any:
        ref = a if isinstance(a, self.t.Tensor) else b
        return self.t.minimum(self._tensor(a, ref), self._tensor(b, ref))

    def stack(self, xs: Sequence[Any], axis: int = -1) -> Any:
        ref = next(x for x in xs if isinstance(x, self.t.Tensor))
        xs = self.t.broadcast_tensors(*[self._tensor(x, ref) for x in xs])
        return self.t.stack(xs, dim=axis)

    def concat(self, xs: Sequence[Any], axis: int = -1) -> Any:
        return self.t.cat(list(xs), dim=axis)

    def sum(self, x: Any, axis: int = -1, keepdims: bool = False) -> Any:
        return self.t.sum(x, dim=axis, keepdim=keepdims)

    def reshape(self, x: Any, shape: Sequence[int]) -> Any:
        return self.t.reshape(x, tuple(shape))

    def swap_last(self, x: Any) -> Any:
        return self.t.transpose(x, -1, -2)

    def const(self, value: Any, like: Any) -> Any:
        return self.t.as_tensor(value, dtype=like.dtype, device=like.device)

    def tan(self, x: Any) -> Any:
        return self.t.tan(x)

    def sigmoid(self, x: Any) -> Any:
        return self.t.sigmoid(x)

    def clip(self, x: Any, lo: float, hi: float) -> Any:
        return self.t.clamp(x, lo, hi)

    def softmax(self, x: Any) -> Any:
        return self.t.softmax(x, dim=-1)

    def step(self, x: Any) -> Any:
        return (x >= 0).to(x.dtype)

    def compet(self, x: Any) -> Any:
        index = self.t.argmax(x, dim=-1, keepdim=True)
        return self.t.zeros_like(x).scatter(-1, index, 1.0)

    def linear(self, x: Any, weight: Any, bias: Any) -> Any:
        weight, bias = self._tensor(weight, x), self._tensor(bias, x)
        if x.dim() == 2:
            return self.t.addmm(bias, x, weight)    # one fused product-and-add, as the trainers always used
        return self.t.matmul(x, weight) + bias


_NUMPY = NumpyNamespace()
_TORCH: TorchNamespace | None = None


def namespace(*xs: Any) -> Any:
    """The namespace of the first argument that is not a plain number or numpy array."""
    global _TORCH
    for x in xs:
        ns = getattr(x, "pc_namespace", None)
        if ns is not None:
            return ns
        if type(x).__module__.startswith("torch"):
            if _TORCH is None:
                _TORCH = TorchNamespace()
            return _TORCH
    return _NUMPY
