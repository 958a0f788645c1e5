"""The MLP's transfer functions (one table) and the feed-forward pass that applies them.

``ACTIVATIONS`` maps a name to an ``Activation``: its map written once against the
``posecorr._xp`` namespace (so the same formula runs on numpy for ``predict``, on torch for
training and on the exporter's symbolic tensors, which emit the ONNX nodes), its elementwise
derivative for the Levenberg-Marquardt Jacobian (``lm.Network.gauss_newton``), and the ranges
MATLAB's ``initnw`` needs. The CLI's ``--activation`` choices and the sweep presets derive
from it; ``register_activation`` adds one (tests do) with no other edit.

The eight MATLAB transfer functions of the paper's table 1 (``paper=True``): tansig = tanh,
logsig = 1/(1+exp(-n)), radbas = exp(-n^2), purelin = n, satlin = clip(n, 0, 1), softmax
(over the layer), hardlim = (n >= 0), compet = one-hot of the first maximum. hardlim and
compet have a zero derivative everywhere, as in MATLAB: only the linear output layer trains.

This module imports numpy only: the command line builds its choices from it without torch.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

from posecorr._xp import namespace
from posecorr.registry import Registry


@dataclass(frozen=True)
class Activation:
    """One transfer function.

    forward: n -> f(n) in any ``posecorr._xp`` namespace (numpy, torch, ONNX export).
    derivative: (z, a = f(z)) -> f'(z) elementwise on torch tensors, or None when the
        Jacobian is not diagonal (softmax: the Gauss-Newton pass has its own rule).
    active_range: the input range ``initnw`` spreads the Nguyen-Widrow weights over (None:
        unbounded or degenerate, so uniform [-1, 1] weights as ``initnw`` falls back to).
    output_range: the layer's output range (the next layer's input range for ``initnw``).
    paper: one of the eight transfer functions of the paper's table 1.
    """

    name: str
    forward: Callable[[Any], Any]
    derivative: Callable[[Any, Any], Any] | None
    active_range: tuple[float, float] | None
    output_range: tuple[float, float]
    paper: bool = False


ACTIVATIONS: Registry = Registry("activation")


def register_activation(activation: Activation) -> Activation:
    return ACTIVATIONS.add(activation.name, activation)


def get_activation(name: str) -> Activation:
    return ACTIVATIONS.lookup(name)


def _xp(method: str) -> Callable[[Any], Any]:
    return lambda n: getattr(namespace(n), method)(n)


for _activation in (
    Activation("compet", _xp("compet"), lambda z, a: z.new_zeros(z.shape), None, (0.0, 1.0), True),
    Activation("hardlim", _xp("step"), lambda z, a: z.new_zeros(z.shape), None, (0.0, 1.0), True),
    Activation("logsig", _xp("sigmoid"), lambda z, a: a * (1.0 - a), (-4.0, 4.0), (0.0, 1.0), True),
    Activation("purelin", lambda n: n, lambda z, a: z.new_ones(z.shape), None, (-1.0, 1.0), True),
    Activation("radbas", lambda n: namespace(n).exp(-(n * n)), lambda z, a: -2.0 * z * a, (-2.0, 2.0), (0.0, 1.0),
               True),
    Activation("satlin", lambda n: namespace(n).clip(n, 0.0, 1.0), lambda z, a: ((z > 0) & (z < 1)).to(z.dtype),
               (0.0, 1.0), (0.0, 1.0), True),
    Activation("softmax", _xp("softmax"), None, None, (0.0, 1.0), True),
    Activation("tansig", _xp("tanh"), lambda z, a: 1.0 - a * a, (-2.0, 2.0), (-1.0, 1.0), True),
):
    register_activation(_activation)

# The paper's eight, for the sweep presets of table 1 (fixed here: a test's registration stays out).
PAPER_ACTIVATIONS: tuple[str, ...] = tuple(name for name, a in ACTIVATIONS.items() if a.paper)


def mlp_forward(x: Any, layers: Sequence[tuple[Any, Any]], activation: str,
                inputs: list | None = None, pre: list | None = None) -> Any:
    """The feed-forward pass: ``layers`` [(weight (in, out), bias (out,)), ...], the activation
    after every hidden layer, a linear output layer; any ``posecorr._xp`` namespace.

    ``inputs`` / ``pre``, when given, receive each layer's input and pre-activation (what the
    Gauss-Newton pass needs)."""
    xp = namespace(x)
    act = get_activation(activation).forward
    h = x
    last = len(layers) - 1
    for i, (w, b) in enumerate(layers):
        if inputs is not None:
            inputs.append(h)
        z = xp.linear(h, w, b)
        if pre is not None:
            pre.append(z)
        h = z if i == last else act(z)
    return h
