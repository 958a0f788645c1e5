"""The data-driven cores by name: the one table that turns "pmc" or "mlp" into an estimator.

A model is described by a `spec.ModelSpec` (method, representation, network settings), which
builds its core through this table; `posecorr fit --method` offers the table's names. What
code needs to know about a method (does it build a core, is it a network, does it choose
among candidates) is a property of its entry here, never a comparison of its name. The
estimator classes are imported when first built: reading the table needs neither
scikit-learn nor torch.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, Mapping

from posecorr.registry import Registry


@dataclass(frozen=True)
class Method:
    """A core: `estimator` "module:Class" inside posecorr.train ("" for no core), the settings
    of a `ModelSpec` it takes (`settings`: hidden, activation, ...), the parameters `posecorr
    fit` gives it where they differ from the estimator's own defaults (`fit_params`), its
    label in the paper's tables (`title`, for a method that is not a network) and whether it
    stands for a choice among candidates rather than one core (`chooses`: fit's "auto")."""

    name: str
    estimator: str
    settings: tuple[str, ...] = ()
    fit_params: Mapping[str, Any] = field(default_factory=dict)
    title: str = ""
    chooses: bool = False

    @property
    def has_core(self) -> bool:
        return bool(self.estimator)

    @property
    def network(self) -> bool:
        """A network: it takes hidden layers (and is labelled by them in the paper's tables)."""
        return "hidden" in self.settings

    def make(self, representation: str, settings: Mapping[str, Any] | None = None, **params: Any) -> Any:
        """A fresh (unfitted) core, or None for a method without one: ``params``, and of the
        ``settings`` (hidden, activation, ...) the ones this method takes."""
        if not self.estimator:
            return None
        module, cls = self.estimator.split(":")
        taken = {name: settings[name] for name in self.settings if name in settings} if settings else {}
        return getattr(importlib.import_module(f".{module}", __package__), cls)(representation=representation,
                                                                               **taken, **params)


METHODS: Registry = Registry("method")


def register_method(method: Method) -> Method:
    return METHODS.add(method.name, method)


def get_method(name: str) -> Method:
    return METHODS.lookup(name)


register_method(Method("none", ""))
# `fit` picks the ridge penalty by cross-validation; the protocol keeps the paper's plain least squares.
register_method(Method("pmc", "pmc:PMC", fit_params={"alpha": "cv"}, title="PMC"))
# `fit`'s network follows the physics stage: it learns what the stage left (`MLP.residual`).
register_method(Method("mlp", "mlp:MLP", settings=("hidden", "activation", "trainer", "epochs", "random_state"),
                       fit_params={"residual": True}))
# `fit --method auto`: a nested cross-validated choice among `pipeline.auto_candidates`.
register_method(Method("auto", "", chooses=True))
