"""posecorr.train: fitting of the correctors and the paper's protocol.

``PMC`` (polynomial model correction, paper 2.3) and ``MLP`` (MATLAB-style networks,
paper 2.4) are scikit-learn-style estimators (see ``base.py`` for the contract);
``protocol`` runs the 30-repeat sweep, ``stats`` the Friedman / Dunn-Sidak analysis and
``tables`` prints tables 2-5. torch is imported lazily (only when an MLP is fitted).
"""
from __future__ import annotations

from .base import REPRESENTATIONS, BaseCorrector, decode_pose, encode_pose
from .mlp import ACTIVATIONS, ARCHITECTURES, MLP, TRAINERS
from .pmc import PMC

__all__ = ["PMC", "MLP", "BaseCorrector", "REPRESENTATIONS", "ACTIVATIONS", "ARCHITECTURES", "TRAINERS",
           "encode_pose", "decode_pose", "fit_one", "run_sweep", "build_grid"]


def __getattr__(name: str):
    if name in ("fit_one", "run_sweep", "build_grid", "SweepResult", "Config"):
        from . import protocol

        return getattr(protocol, name)
    raise AttributeError(f"module 'posecorr.train' has no attribute {name!r}")
