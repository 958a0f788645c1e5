"""posecorr: learn and apply pose corrections for consumer VR trackers.

`import posecorr` loads nothing else; `posecorr.Corrector` loads the controller side
(`posecorr.controller`: the shim, `info`, `apply`; numpy only). Fitting lives in
`posecorr.train` (torch), export in `posecorr.export` (onnx), diagnosis, features, the
ledger and the report in `posecorr.analysis`.
"""
from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__", "Corrector", "PoseCorrError"]


def __getattr__(name: str):
    # Lazy so that `import posecorr` does not load ctypes or onnxruntime.
    if name in ("Corrector", "PoseCorrError"):
        from .controller import runtime

        return getattr(runtime, name)
    if name in ("PMC", "MLP"):
        from . import train

        return getattr(train, name)
    raise AttributeError(f"module 'posecorr' has no attribute {name!r}")
