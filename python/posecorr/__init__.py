"""posecorr: learn and apply pose corrections for consumer VR trackers.

The controller-side import is light: this module pulls in numpy only. Fitting lives in
`posecorr.train` (torch), export in `posecorr.export` (onnx).
"""
from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__", "Corrector"]


def __getattr__(name: str):
    # Lazy so that `import posecorr` does not load ctypes or onnxruntime.
    if name == "Corrector":
        from .runtime import Corrector

        return Corrector
    if name in ("PMC", "MLP"):
        from . import train

        return getattr(train, name)
    raise AttributeError(f"module 'posecorr' has no attribute {name!r}")
