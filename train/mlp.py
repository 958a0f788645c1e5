"""The multilayer perceptron corrector (paper section 2.4) with MATLAB semantics.

Network: input vector [x, y, z, params(rep)] -> ``mapminmax`` to [-1, 1] -> hidden layers
(``hidden``, e.g. 20-20-20-20) with one of the eight MATLAB transfer functions ->
linear (purelin) output layer -> reverse ``mapminmax`` -> decode to a pose. The 16
architectures of the paper's table 1 are ``spec.ARCHITECTURES``.

Transfer functions: the table ``activations.ACTIVATIONS`` (the eight of MATLAB and any
registered one), which also holds the forward pass (``mlp_forward``) that ``predict``, the
trainers and the ONNX export share. hardlim and compet have a zero derivative everywhere, as
in MATLAB: gradient and Jacobian based trainers cannot move the hidden weights, so they stay
at their initial values and only the (linear) output layer is trained. That is what MATLAB
does too, and why those rows of the paper's tables are poor.

Scaling (MATLAB ``mapminmax``): inputs AND targets are mapped to [-1, 1] with the training
set's min / max per row (a constant row maps to -1, gain 1, as in MATLAB). By default the
training error is measured in the targets' original units after reverse mapping
(MATLAB's ``performParam.normalization = 'none'``); ``normalization="standard"`` trains on
the [-1, 1] targets instead.

Initialisation (MATLAB ``initnw``-like, seeded by ``random_state``): Nguyen-Widrow for
hidden layers whose transfer function has a finite active input range (tansig and radbas
[-2, 2], logsig [-4, 4], satlin [0, 1]): weight rows of random direction and magnitude
0.7 S^(1/R), biases spread over linspace(-1, 1, S), both mapped to the active range and to
the previous layer's output range. Layers with an unbounded or degenerate active range
(purelin, softmax, hardlim, compet) and the output layer get ``rands`` (uniform [-1, 1]),
as ``initnw`` falls back to.

Trainers (``TRAINERS``): the registry of ``trainers.py`` (table 1's twelve MATLAB training
functions plus adam and lbfgs), every one a step of the shared training loop; "lm" (trainlm)
and "br" (trainbr) solve with the Gauss-Newton matrix of ``lm.py``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from posecorr._xp import namespace

from .activations import get_activation, mlp_forward
from .base import BaseCorrector, Rule, Validation, check_parameters, check_poses, encode_pose, vector_size
from .spec import DEFAULT_ACTIVATION, DEFAULT_EPOCHS, DEFAULT_HIDDEN, DEFAULT_TRAINER, parse_hidden
from .splits import validation_split
from .trainers import TRAINERS


def activation_xp(name: str, n: Any) -> Any:
    """Transfer function ``name`` (``activations.ACTIVATIONS``) in the xp namespace of n."""
    return get_activation(name).forward(n)


CONSTANT_STEPS = 4096


def mapminmax_settings(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MATLAB mapminmax to [-1, 1]: gain, offset with Xn = X * gain + offset.

    y = (ymax - ymin)(x - xmin)/(xmax - xmin) + ymin; a constant row gets gain 1, so it maps
    to ymin = -1 (MATLAB's behaviour). A row that varies by no more than CONSTANT_STEPS float32
    steps of its magnitude counts as constant: the exported model runs in float32, where it
    does not vary at all, and a gain of 2 / span would make its rounding the network's input
    (a session held at one orientation: the corrected rotation's diagonal spans 1e-8, and the
    graph's output moved by 2.5e-5 rad from predict's).
    """
    lo, hi = X.min(axis=0), X.max(axis=0)
    span = hi - lo
    resolution = CONSTANT_STEPS * np.spacing(np.maximum(np.abs(lo), np.abs(hi)).astype(np.float32))
    const = ~(span > resolution)
    gain = np.where(const, 1.0, 2.0 / np.where(const, 1.0, span))
    offset = -1.0 - lo * gain
    return gain, offset


def init_weights(sizes: Sequence[int], activation: str, rng: np.random.Generator
                 ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """MATLAB initnw-like initial weights (in, out) and biases (out,) for all layers."""
    coefs, intercepts = [], []
    in_range = (-1.0, 1.0)  # inputs after mapminmax
    n_layers = len(sizes) - 1
    for layer in range(n_layers):
        R, S = sizes[layer], sizes[layer + 1]
        hidden_layer = layer < n_layers - 1
        active = get_activation(activation).active_range if hidden_layer else None
        if active is None:
            w = rng.uniform(-1.0, 1.0, size=(S, R))
            b = rng.uniform(-1.0, 1.0, size=S)
        else:
            mag = 0.7 * S ** (1.0 / R)
            direction = rng.standard_normal((S, R))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            w = mag * direction
            b = mag * np.linspace(-1.0, 1.0, S) * np.sign(w[:, 0]) if S > 1 else np.zeros(1)
            x, y = 0.5 * (active[1] - active[0]), 0.5 * (active[1] + active[0])
            w, b = x * w, x * b + y
            # map from the previous layer's output range [pmin, pmax] to [-1, 1]
            xs = 2.0 / (in_range[1] - in_range[0])
            ys = 1.0 - in_range[1] * xs
            b = w @ np.full(R, ys) + b
            w = w * xs
        coefs.append(np.ascontiguousarray(w.T))
        intercepts.append(b.copy())
        if hidden_layer:
            in_range = get_activation(activation).output_range
    return coefs, intercepts


# The numeric parameters' ranges (`check_parameters`): a damping of 0 or a growth factor of 1
# never reached mu_max, and the training never ended.
PARAMETER_RULES = {
    "goal": Rule(lambda v: v >= 0, ">= 0"),
    "min_grad": Rule(lambda v: v >= 0, ">= 0"),
    "max_fail": Rule(lambda v: v >= 1, ">= 1", whole=True),
    "mu": Rule(lambda v: v > 0, "> 0", none=True),
    "mu_dec": Rule(lambda v: 0 < v <= 1, "in (0, 1] (1: held)"),
    "mu_inc": Rule(lambda v: v > 1, "> 1"),
    "mu_max": Rule(lambda v: v > 0, "> 0"),
    "lr": Rule(lambda v: v > 0, "> 0"),
    "verbose": Rule(lambda v: v >= 0, ">= 0 (0: silent)", whole=True),
    "num_threads": Rule(lambda v: v >= 1, ">= 1", whole=True, none=True),
    "epochs": Rule(lambda v: v >= 0, ">= 0 (0: the initial network)", whole=True),
    "validation_fraction": Rule(lambda v: 0 <= v < 1, "in [0, 1) (the share of the poses held for early stopping)"),
}


@dataclass(repr=False, eq=False)
class MLP(BaseCorrector):
    """Feed-forward network corrector, trained like MATLAB's ``train`` with ``trainFcn``.

    Parameters
    ----------
    representation : "pos" | "eaa" | "quat" | "R" | "zhou"
    hidden : hidden layer sizes, e.g. (10, 10) (default ``spec.DEFAULT_HIDDEN``, table 1's
        architecture 16)
    activation : one of ``ACTIVATIONS`` for every hidden layer; the output layer is purelin
    trainer : one of ``TRAINERS``
    epochs : maximum epochs (MATLAB default 1000)
    goal : stop when the training mse (in the units training uses) <= goal (MATLAB 0;
        the paper's "RMSE 1e-3" would be goal=1e-6)
    max_fail : validation failures before stopping (MATLAB 6; ignored by "br")
    min_grad : stop when |gradient| < min_grad (MATLAB 1e-7 for lm; 1e-7 for br)
    mu, mu_dec, mu_inc, mu_max : Levenberg-Marquardt damping (None = trainer default:
        trainlm 1e-3, trainbr 5e-3; 0.1, 10, 1e10)
    lr : learning rate of the gradient trainers (paper: 0.01)
    normalization : "none" (errors in target units, MATLAB default) or "standard"
    validation_fraction : when ``fit`` gets no ``validation=`` data, the share of the
        training rows held out for early stopping (MATLAB divides 70/15/15 itself; trainbr
        does not use validation for stopping).
    merge_validation : "br" only: train on train + validation (default False: the
        validation rows are only monitored, MATLAB's default)
    residual : learn the reference's vector minus the input's and add the input back (default
        False: the paper's network maps the pose itself). `posecorr fit` sets it for a core
        after the physics stage: there trainbr, on a session's few poses, drives every weight
        towards zero, which makes an absolute network a constant pose (hundreds of mm held
        out) and a residual one the physics stage it follows.
    random_state : seed for the initial weights and the internal split
    num_threads : torch threads during fit (None = leave as is)
    verbose : print one line per ``verbose`` epochs (0 = silent)

    ``fit(measured, reference, validation=Validation(measured_val, reference_val))``.
    """

    representation: str = "zhou"
    hidden: Any = DEFAULT_HIDDEN
    activation: str = DEFAULT_ACTIVATION
    trainer: str = DEFAULT_TRAINER
    epochs: int = DEFAULT_EPOCHS
    goal: float = 0.0
    max_fail: int = 6
    min_grad: float = 1e-7
    mu: float | None = None
    mu_dec: float = 0.1
    mu_inc: float = 10.0
    mu_max: float = 1e10
    lr: float = 0.01
    normalization: str = "none"
    validation_fraction: float = 0.15
    merge_validation: bool = False
    residual: bool = False
    random_state: int = 0
    num_threads: int | None = None
    verbose: int = 0

    method = "mlp"
    uses_validation = True
    shaping = ("representation", "hidden", "activation", "normalization", "residual")

    def _check_parameters(self) -> None:
        check_parameters(self, PARAMETER_RULES, flags=("merge_validation", "residual"))
        if self.mu is not None and self.mu > self.mu_max:
            raise ValueError(f"mu must be at most mu_max ({self.mu_max!r}), got {self.mu!r}")

    # --- fit ----------------------------------------------------------------------------
    def min_rows(self) -> int:
        return 4

    def n_weights(self) -> int:
        d = vector_size(self.representation)
        sizes = [d, *parse_hidden(self.hidden), d]
        return sum((a + 1) * b for a, b in zip(sizes, sizes[1:]))

    def _fit_vectors(self, X: np.ndarray, Y: np.ndarray, validation: Validation | None) -> None:
        import torch

        get_activation(self.activation)   # refuses an unknown name before any work
        trainer = TRAINERS.lookup(self.trainer)   # refuses an unknown name before any work
        if self.normalization not in ("none", "standard"):
            raise ValueError("normalization must be 'none' or 'standard'")
        hidden = parse_hidden(self.hidden)
        rng = np.random.default_rng(self.random_state)
        if self.residual:
            Y = Y - X
        if validation is not None:
            mv = check_poses(validation.measured, "validation measured")
            rv = check_poses(validation.reference, "validation reference", len(mv))
            Xv = np.asarray(encode_pose(mv, self.representation), np.float64)
            Yv = np.asarray(encode_pose(rv, self.representation), np.float64) - (Xv if self.residual else 0.0)
        elif not trainer.bayesian and self.validation_fraction > 0 and len(X) >= 10:
            train, held = validation_split(len(X), self.validation_fraction, rng)
            Xv, Yv = X[held], Y[held]
            X, Y = X[train], Y[train]
        else:
            Xv = Yv = None
        if trainer.bayesian and self.merge_validation and Xv is not None:
            X, Y = np.concatenate([X, Xv]), np.concatenate([Y, Yv])

        d_in, d_out = X.shape[1], Y.shape[1]
        sizes = [d_in, *hidden, d_out]
        self.x_gain_, self.x_offset_ = mapminmax_settings(X)
        self.y_gain_, self.y_offset_ = mapminmax_settings(Y)
        coefs, intercepts = init_weights(sizes, self.activation, rng)

        Xn = X * self.x_gain_ + self.x_offset_
        Tn = Y * self.y_gain_ + self.y_offset_
        escale = 1.0 / self.y_gain_ if self.normalization == "none" else np.ones(d_out)
        val = None if Xv is None else (Xv * self.x_gain_ + self.x_offset_, Yv * self.y_gain_ + self.y_offset_)

        old_threads = torch.get_num_threads()
        if self.num_threads:
            torch.set_num_threads(int(self.num_threads))
        try:
            result = trainer.train(self, sizes, coefs, intercepts, Xn, Tn, escale, val)
        finally:
            if self.num_threads:
                torch.set_num_threads(old_threads)
        self.coefs_ = [np.asarray(w, np.float64) for w in result.coefs]
        self.intercepts_ = [np.asarray(b, np.float64) for b in result.intercepts]
        # The trainer's result as fitted attributes.
        for attribute, field in (("n_epochs_", "epochs"), ("stop_reason_", "stop_reason"), ("history_", "history"),
                                 ("best_val_loss_", "best_val"), ("train_loss_", "train_loss"), ("extra_", "extra")):
            setattr(self, attribute, getattr(result, field))
        self.sizes_ = sizes
        self.n_parameters_ = int(sum(w.size + b.size for w, b in zip(self.coefs_, self.intercepts_)))

    # --- inference ------------------------------------------------------------------------
    def _core(self, x: Any) -> Any:
        xp = namespace(x)
        h = x * xp.const(self.x_gain_, x) + xp.const(self.x_offset_, x)
        h = mlp_forward(h, list(zip(self.coefs_, self.intercepts_)), self.activation)
        y = h * xp.const(1.0 / self.y_gain_, h) + xp.const(-self.y_offset_ / self.y_gain_, h)
        return x + y if self.residual else y

    def export_info(self) -> dict[str, str]:
        self._check_fitted()
        info = {"method": "mlp", "representation": self.representation,
                "architecture": "-".join(str(h) for h in parse_hidden(self.hidden)) or "linear",
                "layers": "-".join(str(s) for s in self.sizes_),
                "activation": self.activation, "output_activation": "purelin",
                "trainer": self.trainer, "epochs": str(self.n_epochs_), "stop_reason": self.stop_reason_,
                "n_parameters": str(self.n_parameters_), "normalization": self.normalization,
                "scaling": "mapminmax[-1,1] inputs and targets",
                "output": "input + network" if self.residual else "network",
                "train_loss_mse": f"{self.train_loss_:.6g}", "random_state": str(self.random_state)}
        if self.best_val_loss_ is not None:
            info["best_validation_mse"] = f"{self.best_val_loss_:.6g}"
        for key, value in self.extra_.items():
            info[key] = f"{value:.6g}" if isinstance(value, float) else str(value)
        return info
