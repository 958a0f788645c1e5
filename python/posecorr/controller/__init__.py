"""The controller side: what a robot controller's PC needs to use an exported corrector.

- `runtime`: the ctypes shim over libposecorr and `Corrector` (C or onnxruntime back-end);
- `onnx_meta`: a model's metadata and structure without the onnx package (`posecorr info`);
- `apply`: batch correction of a pose table, streaming (`posecorr apply`).

Everything here runs on numpy alone (onnxruntime is imported only when that back-end is
asked for). Of the rest of posecorr it uses only the numpy-only core: `posecorr.data`,
`posecorr.metrics` (with `posecorr.rotations`) and `posecorr.safeio`;
tests/test_controller.py imports it with torch, scipy, scikit-learn, onnx and onnxruntime
made unimportable.
"""
from __future__ import annotations

from .apply import apply_file
from .onnx_meta import read_info
from .runtime import Corrector, PoseCorrError

__all__ = ["Corrector", "PoseCorrError", "apply_file", "read_info"]
