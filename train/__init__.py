"""posecorr.train: fitting of the correctors and the paper's protocol.

``PMC`` (polynomial model correction, paper 2.3) and ``MLP`` (MATLAB-style networks,
paper 2.4) are scikit-learn estimators (see ``base.py`` for the contract), each described
and built by a ``ModelSpec`` (``spec.py``); ``splits`` holds the fixed split and the
cross-validation plans, ``protocol`` runs the 30-repeat sweep, ``stats`` the Friedman /
Dunn-Sidak analysis and ``tables`` prints tables 2-5.

Every name here is imported when first used: the command line reads the registries
(``trainers``, ``activations``, ``methods``) to build its choices, and its controller-side
verbs must not load scikit-learn or torch by doing so.
"""
from __future__ import annotations

import importlib
from typing import Any

# name -> the module (relative to this package) that defines it.
_EXPORTS = {
    "PMC": "pmc", "MLP": "mlp", "BaseCorrector": "base", "Validation": "base",
    "encode_pose": "base", "decode_pose": "base", "ACTIVATIONS": "activations", "ARCHITECTURES": "spec",
    "TRAINERS": "trainers", "ModelSpec": "spec", "fit_one": "protocol", "run_sweep": "protocol",
    "build_grid": "protocol", "SweepResult": "protocol",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module 'posecorr.train' has no attribute {name!r}")
