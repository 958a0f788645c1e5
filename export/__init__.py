"""ONNX export of posecorr correctors (`posecorr.export`).

- `to_onnx(estimator, path, measured=..., **metadata)`: trace `estimator.forward` on
  symbolic tensors, check operators / onnx.checker / shape inference, verify parity with
  onnxruntime, write metadata, save.
- `symbolic`: the `_xp` namespace that emits ONNX nodes (`Sym`, `Graph`).
- `parity`: onnxruntime vs float64 predict; `run_onnx` applies any model.
- `metadata`: `data_digest` and the encoding of `metadata_props`.

The shipped models/ are written by the build harness `tools/models.py` (`make models`),
which is not part of the installed package.
"""
from __future__ import annotations

from .metadata import data_digest, encode_metadata
from .onnx_export import (OperatorNotSupported, ParityError, build_model, check_model, check_operators,
                          load_operator_list, op_counts, to_onnx)
from .parity import Parity, check_parity, run_onnx
from .symbolic import ExportError, Graph, Sym, custom_op

__all__ = ["to_onnx", "build_model", "check_model", "check_operators", "load_operator_list", "op_counts",
           "OperatorNotSupported", "ParityError", "ExportError", "data_digest", "encode_metadata",
           "Parity", "check_parity", "run_onnx", "Graph", "Sym", "custom_op"]
