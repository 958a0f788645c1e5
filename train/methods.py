"""The data-driven cores by name: the one table that turns "pmc" or "mlp" into an estimator.

`posecorr fit --method`, the sweep's configurations (`protocol.Config`) and auto's candidates
(`pipeline.auto_candidates`) all build their cores through `make_estimator`; the command
line's choices are the table's names (and "auto", which chooses among candidates). The
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
    of `posecorr fit` it takes (`settings`: --hidden, --activation, ...) and the parameters
    `posecorr fit` gives it where they differ from the estimator's own defaults (`fit_params`)."""

    name: str
    estimator: str
    settings: tuple[str, ...] = ()
    fit_params: Mapping[str, Any] = field(default_factory=dict)

    def make(self, representation: str, settings: Mapping[str, Any] | None = None, **params: Any) -> Any:
        """A fresh (unfitted) core, or None for the method without one: ``params``, and of the
        ``settings`` (a command's options: hidden, activation, ...) the ones this method takes."""
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


def make_estimator(method: str, representation: str, **params: Any) -> Any:
    """`method`'s core on `representation` with `params` (None for "none")."""
    return get_method(method).make(representation, **params)


register_method(Method("none", ""))
# `fit` picks the ridge penalty by cross-validation; the protocol keeps the paper's plain least squares.
register_method(Method("pmc", "pmc:PMC", fit_params={"alpha": "cv"}))
register_method(Method("mlp", "mlp:MLP", settings=("hidden", "activation", "trainer", "epochs", "random_state")))
