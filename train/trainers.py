"""The trainers: a registry of MATLAB training functions (paper table 1) and their steps.

``TRAINERS`` maps a name ("lm", "scg", ...) to a ``Trainer``: MATLAB's function name,
table 1's number and its ``Step`` class (one epoch of its rule), run by the shared loop
``iterate``. Adding a trainer = its Step class and one ``register`` line.

The shared loop minimises the mean squared error of r = (y - T) * escale (target units,
MATLAB's default), full batch, one step per epoch, and stops like MATLAB's ``train``: a step
that says it cannot go on (a line search that found no lower point: "Minimum step size
reached"; Levenberg-Marquardt's damping beyond mu_max: "Maximum MU reached"), ``epochs``,
``goal`` on the mse, ``min_grad`` on |gradient|, or ``max_fail`` consecutive validation
failures. It returns the network with the best validation error (the last one without
validation data). A Bayesian step (trainbr) only monitors the validation poses: no
validation stop, the last network. The first-order steps take their gradients from torch
autograd; ``lr`` is MATLAB's learning rate (paper: 0.01). The Levenberg-Marquardt steps
(``LM``, ``BR``) use the Gauss-Newton matrix of ``lm.py``.

| trainer | MATLAB | table 1 | rule (g = gradient of the mse) |
|---|---|---|---|
| lm    | trainlm  | 1  | (J'J + mu I) dx = -J'r, mu x0.1 on success, x10 and retry on failure, see ``LM`` |
| br    | trainbr  | 2  | LM on beta Ed + alpha Ew with MacKay's evidence updates of alpha and beta, see ``BR`` |
| gd    | traingd  | 6  | x -= lr g |
| gdm   | traingdm | 8  | dx = mc dx_prev - (1 - mc) lr g, mc = 0.9 |
| gda   | traingda | 7  | x -= lr g; a step raising the mse by > 4 % (max_perf_inc 1.04) is undone and lr *= 0.7; a step lowering it gives lr *= 1.05 |
| gdx   | traingdx | 9  | gdm's momentum step with gda's adaptive lr (momentum reset after an undone step) |
| rp    | trainrp  | 3  | per weight delta (delta0 0.07, x1.2 when the gradient keeps its sign, x0.5 when it flips, <= deltamax 50); dx = -delta sign(g); after a flip the next step waits (g_old = 0) |
| scg   | trainscg | 4  | Moller's scaled conjugate gradient (sigma 5e-5, lambda 5e-7), see ``SCG`` |
| bfg   | trainbfg | 5  | BFGS on the Hessian approximation H (H = I first), dx = -H \\ g, backtracking line search ``srchbac`` |
| cgb   | traincgb | 10 | conjugate gradient with Powell-Beale restarts, line search ``srchcha`` |
| cgf   | traincgf | 11 | Fletcher-Reeves conjugate gradient, line search ``srchcha`` |
| cgp   | traincgp | 12 | Polak-Ribiere conjugate gradient, line search ``srchcha`` |
| adam  | (none)   | -  | torch.optim.Adam(lr) full batch |
| lbfgs | (none)   | -  | torch.optim.LBFGS(lr=1, history 50, strong Wolfe line search), one iteration per epoch |

Line search parameters are MATLAB's defaults: alpha 0.001 (sufficient decrease), beta 0.1
(sufficient slope reduction), delta 0.01 (first step), gama 0.1, scale_tol 20, low_lim
0.1, up_lim 0.5, maxstep 100, minstep 1e-6.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from posecorr.registry import Registry

from .lm import Network


@dataclass
class TrainResult:
    coefs: list[np.ndarray]
    intercepts: list[np.ndarray]
    epochs: int
    stop_reason: str
    history: dict[str, list[float]]
    best_val: float | None
    train_loss: float
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Trainer:
    name: str
    matlab: str
    number: int | None                   # table 1's algorithm number (None: not in the paper)
    title: str
    train: Callable[..., TrainResult]    # (est, sizes, coefs, intercepts, Xn, Tn, escale, val)
    step: type                           # the Step class run by ``iterate``

    @property
    def bayesian(self) -> bool:
        """Bayesian regularisation (trainbr): no validation split and no early stop; validation
        poses may join the training rows; about twice plain LM's work per configuration."""
        return self.step.bayesian


TRAINERS: Registry = Registry("trainer")


def register(name: str, matlab: str, number: int | None, title: str) -> Callable:
    """Class decorator: a ``Step`` class becomes the trainer ``name``."""
    def add(step_class: type) -> type:
        TRAINERS.add(name, Trainer(name, matlab, number, title, iterate(step_class), step_class))
        return step_class
    return add


class ValidationCheck:
    """MATLAB's validation stop: keep the best-validation weights, count the epochs in a
    row that made validation worse (trainlm and the gradient trainers stop at max_fail)."""

    def __init__(self, theta: Any) -> None:
        self.best = math.inf
        self.best_theta = theta.clone()
        self.fails = 0

    def update(self, val_mse: float, theta: Any) -> None:
        if val_mse < self.best:
            self.best, self.best_theta, self.fails = val_mse, theta.clone(), 0
        elif val_mse > self.best:
            self.fails += 1

    @property
    def best_or_none(self) -> float | None:
        return None if self.best == math.inf else self.best


def training_tensors(est: Any, sizes: Sequence[int], coefs: list[np.ndarray], intercepts: list[np.ndarray],
                     Xn: np.ndarray, Tn: np.ndarray, escale: np.ndarray,
                     val: tuple[np.ndarray, np.ndarray] | None) -> tuple[Any, ...]:
    """(net, packed weights, X, T, X_val or None, T_val or None) in float64: every trainer's start."""
    import torch

    net = Network(sizes, est.activation, escale)
    theta = net.pack(coefs, intercepts)
    X = torch.as_tensor(Xn, dtype=torch.float64)
    T = torch.as_tensor(Tn, dtype=torch.float64)
    Xv = Tv = None
    if val is not None:
        Xv = torch.as_tensor(val[0], dtype=torch.float64)
        Tv = torch.as_tensor(val[1], dtype=torch.float64)
    return net, theta, X, T, Xv, Tv


# --- the problem every step sees --------------------------------------------------------------

class Problem:
    """mse and gradient of the network's scaled residual on the training rows."""

    def __init__(self, net: Any, X: Any, T: Any) -> None:
        self.net, self.X, self.T = net, X, T
        self.N = T.numel()

    def loss(self, theta: Any) -> Any:
        r = self.net.residual(theta, self.X, self.T)
        return (r * r).sum() / self.N

    def mse(self, theta: Any) -> float:
        import torch

        with torch.no_grad():
            return self.net.sse(theta, self.X, self.T) / self.N

    def mse_grad(self, theta: Any) -> tuple[float, Any]:
        import torch

        th = theta.detach().requires_grad_(True)
        loss = self.loss(th)
        (grad,) = torch.autograd.grad(loss, th)
        return float(loss.detach()), grad


class Step:
    """One epoch of a trainer: ``step(epoch, theta, mse, g) -> (theta, mse, g)`` at the new point.

    ``g`` is the gradient the loop's ``min_grad`` rule measures (``start`` gives the first).
    A step that cannot go on sets ``stop_reason``; ``state()`` adds per-epoch values to the
    history, ``extra()`` to the result's ``extra``. ``bayesian``: the validation poses are only
    monitored (no validation stop, the last network is returned).
    """

    stop_reason: str | None = None
    bayesian = False

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        self.problem = problem
        self.lr = float(est.lr)

    def start(self, theta: Any) -> tuple[float, Any]:
        """(mse, g) at the initial weights."""
        return self.problem.mse_grad(theta)

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        raise NotImplementedError

    def moved(self, theta: Any) -> tuple[Any, float, Any]:
        return (theta, *self.problem.mse_grad(theta))

    def state(self) -> dict[str, float]:
        return {}

    def extra(self) -> dict[str, Any]:
        return {}


def iterate(step_class: type) -> Callable[..., TrainResult]:
    """The shared training loop of the Step trainers (see the module docstring)."""

    def train(est: Any, sizes: Sequence[int], coefs: list[np.ndarray], intercepts: list[np.ndarray],
              Xn: np.ndarray, Tn: np.ndarray, escale: np.ndarray, val: tuple[np.ndarray, np.ndarray] | None
              ) -> TrainResult:
        import torch

        net, theta, X, T, Xv, Tv = training_tensors(est, sizes, coefs, intercepts, Xn, Tn, escale, val)
        problem = Problem(net, X, T)
        step = step_class(problem, theta, est)
        mse, g = step.start(theta)
        early_stop = Xv is not None and not step.bayesian
        history: dict[str, list[float]] = {"mse": [], "val_mse": []}
        check = ValidationCheck(theta)
        stop = None
        t0 = time.perf_counter()
        epoch = 0
        for epoch in range(int(est.epochs) + 1):
            vmse = float("nan")
            if Xv is not None:
                with torch.no_grad():
                    vmse = net.sse(theta, Xv, Tv) / Tv.numel()
                check.update(vmse, theta)
            _record(history, step.state(), epoch, mse, vmse, est.verbose)
            stop = _stop_reason(step, est, epoch, mse, g, early_stop and check.fails >= int(est.max_fail))
            if stop:
                break
            theta, mse, g = step(epoch, theta, mse, g)

        final = check.best_theta if early_stop and check.best < math.inf else theta
        coefs_out, intercepts_out = net.to_numpy(final)
        seconds = time.perf_counter() - t0
        return TrainResult(coefs_out, intercepts_out, epoch, stop or "Maximum epoch reached", history, check.best_or_none,
                           problem.mse(final),
                           {"seconds": seconds, "seconds_per_epoch": seconds / max(epoch, 1), **step.extra()})

    train.__name__ = f"train_{step_class.__name__.lower()}"
    train.__doc__ = step_class.__doc__
    return train


def _record(history: dict[str, list[float]], state: dict[str, float], epoch: int, mse: float,
            vmse: float, verbose: Any) -> None:
    """One epoch's errors and step state into the history, printed every `verbose` epochs."""
    history["mse"].append(mse)
    history["val_mse"].append(vmse)
    for key, value in state.items():
        history.setdefault(key, []).append(value)
    if verbose and epoch % int(verbose) == 0:
        print(f"epoch {epoch:4d} mse {mse:.4g} val {vmse:.4g}"
              + "".join(f" {key} {value:.4g}" for key, value in state.items()), flush=True)


def _stop_reason(step: Step, est: Any, epoch: int, mse: float, g: Any, validation_failed: bool) -> str | None:
    """Why training stops after this epoch's record, None to take another step."""
    import torch

    # The step's own stop first: the point it could not leave is recorded, then the run ends.
    if step.stop_reason:
        return step.stop_reason
    if epoch >= int(est.epochs):
        return "Maximum epoch reached"
    if not math.isfinite(mse):
        return "Diverged"
    if mse <= est.goal:
        return "Performance goal met"
    if float(torch.linalg.vector_norm(g)) < est.min_grad:
        return "Minimum gradient reached"
    if validation_failed:
        return "Validation stop"
    return None


# --- Levenberg-Marquardt -------------------------------------------------------------------------

@register("lm", "trainlm", 1, "Levenberg-Marquardt backpropagation (LM)")
class LM(Step):
    """trainlm: each epoch solves (J'J + mu I) dx = -J'r (J'J and J'r of the sum of squared
    errors Ed, ``Network.linearise``, formed once per epoch) and takes the step when it
    lowers the objective: then mu *= mu_dec (0.1); else mu *= mu_inc (10) and the system is
    solved again with the new diagonal. mu starts at ``mu`` (trainlm 1e-3); beyond mu_max
    (1e10) the step gives up: "Maximum MU reached". The loop's gradient rule measures the
    gradient of Ed, 2 J'r, as MATLAB's does."""

    mu_start = 1e-3

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        super().__init__(problem, theta, est)
        self.net, self.N = problem.net, problem.N
        self.P = self.net.n_params
        self.mu = float(est.mu if est.mu is not None else self.mu_start)
        self.mu_dec, self.mu_inc, self.mu_max = float(est.mu_dec), float(est.mu_inc), float(est.mu_max)
        # trainbr's scales of the errors and of the weight penalty: plain LM weighs the errors alone
        self.beta, self.alpha = 1.0, 0.0
        self.t0 = time.perf_counter()
        if self.mu > self.mu_max:
            self.stop_reason = "Maximum MU reached"

    def start(self, theta: Any) -> tuple[float, Any]:
        self._linearise(theta)
        return self.ed / self.N, self.gradient(theta)

    def _linearise(self, theta: Any) -> None:
        """The damped system and Ed at theta: what the next step solves with."""
        self.system = self.net.linearise(theta, self.problem.X, self.problem.T)
        self.ed = self.system.ed

    def gradient(self, theta: Any) -> Any:
        """The gradient of the objective, for the loop's min_grad rule."""
        return 2.0 * (self.beta * self.system.g + self.alpha * theta)

    def objective(self, ed: float, theta: Any) -> float:
        return self.beta * ed + self.alpha * float(theta @ theta)

    def accepted(self, ed: float, theta: Any) -> None:
        """Hook after an accepted step (trainbr's evidence update)."""

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        perf = self.objective(self.ed, theta)
        while self.mu <= self.mu_max:
            # (beta J'J + (mu + alpha) I) dx = -(beta J'r + alpha theta)
            dx = self.system.step(self.beta, self.mu + self.alpha, self.alpha, theta)
            if dx is not None:
                trial = theta + dx
                ed = self.net.sse(trial, self.problem.X, self.problem.T)
                new = self.objective(ed, trial)
                if math.isfinite(new) and new < perf:
                    self.mu = max(self.mu * self.mu_dec, 1e-20)
                    self.accepted(ed, trial)
                    self._linearise(trial)
                    return trial, self.ed / self.N, self.gradient(trial)
            self.mu *= self.mu_inc
        self.stop_reason = "Maximum MU reached"
        return theta, mse, g

    def state(self) -> dict[str, float]:
        return {"mu": self.mu, "seconds": time.perf_counter() - self.t0}


@register("br", "trainbr", 2, "Bayesian regularization (BR)")
class BR(LM):
    """trainbr, MacKay's evidence framework as in MATLAB: the LM step on F = beta Ed + alpha Ew
    (Ew = sum of squared weights and biases), (beta J'J + (alpha + mu) I) dx = -(beta J'r +
    alpha w), mu starting at 5e-3. Initially gamma = P (the parameter count), beta = (N -
    gamma) / (2 Ed), alpha = gamma / (2 Ew) (N = number of error terms, S m); after an accepted
    step gamma = P - alpha trace((beta J'J + alpha I)^-1) (J'J of the epoch's start point, as
    MATLAB), alpha = gamma / (2 Ew), beta = (N - gamma) / (2 Ed). The validation poses are only
    monitored; the last network is returned.

    One departure: where P > N / 2, gamma starts at N / 2. MATLAB's start there leaves beta
    near zero or, from P = N on, sets it to 1 whatever the errors' scale, and the weights'
    penalty drowns the data: a 183-weight network on 40 poses (120 numbers) fell to 1.6
    effective weights and left 3.3 mm of a 4.6 mm field held out, 1.5 mm from N / 2
    (`tests/test_mlp.py`)."""

    bayesian = True
    mu_start = 5e-3

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        super().__init__(problem, theta, est)
        ed = self.net.sse(theta, problem.X, problem.T)
        ew = float(theta @ theta)
        self.gamma = float(min(self.P, self.N / 2.0))
        self.beta = 1.0 if ed == 0 else (self.N - self.gamma) / (2.0 * ed)
        self.alpha = self.gamma / (2.0 * ew) if ew > 0 else 1.0

    def accepted(self, ed: float, theta: Any) -> None:
        trace = self.system.trace_inverse(self.beta, self.alpha)
        if trace is not None:
            ew = float(theta @ theta)
            self.gamma = self.P - self.alpha * trace
            self.alpha = 1.0 if ew == 0 else self.gamma / (2.0 * ew)
            self.beta = 1.0 if ed == 0 else (self.N - self.gamma) / (2.0 * ed)

    def state(self) -> dict[str, float]:
        return {**super().state(), "gamma": self.gamma, "alpha": self.alpha, "beta": self.beta}

    def extra(self) -> dict[str, Any]:
        return {"gamma": self.gamma, "alpha": self.alpha, "beta": self.beta, "n_errors": self.N}


# --- gradient descent family ---------------------------------------------------------------------

MOMENTUM, LR_INC, LR_DEC, MAX_PERF_INC = 0.9, 1.05, 0.7, 1.04


@register("gd", "traingd", 6, "Gradient descent backpropagation (GD)")
class GD(Step):
    """traingd: x -= lr g."""

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        return self.moved(theta - self.lr * g)


@register("gdm", "traingdm", 8, "Gradient descent with momentum backpropagation (GDM)")
class GDM(Step):
    """traingdm: dx = mc dx_prev - (1 - mc) lr g."""

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        super().__init__(problem, theta, est)
        self.dx = theta.new_zeros(theta.shape)

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        self.dx = MOMENTUM * self.dx - (1.0 - MOMENTUM) * self.lr * g
        return self.moved(theta + self.dx)


@register("gda", "traingda", 7, "Gradient descent with adaptive learning rule backpropagation (GDA)")
class GDA(Step):
    """traingda: a step raising the mse by more than max_perf_inc is undone and lr *= lr_dec;
    a step lowering it gives lr *= lr_inc."""

    momentum = False

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        super().__init__(problem, theta, est)
        self.dx = theta.new_zeros(theta.shape)

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        dx = MOMENTUM * self.dx - (1.0 - MOMENTUM) * self.lr * g if self.momentum else -self.lr * g
        trial = theta + dx
        new = self.problem.mse(trial)
        if not math.isfinite(new) or new > mse * MAX_PERF_INC:
            self.lr *= LR_DEC
            self.dx = theta.new_zeros(theta.shape)
            return theta, mse, g
        if new < mse:
            self.lr *= LR_INC
        self.dx = dx
        return self.moved(trial)

    def extra(self) -> dict[str, Any]:
        return {"final_lr": self.lr}


@register("gdx", "traingdx", 9, "Gradient descent with momentum and adaptive learning rule backpropagation (GDMA)")
class GDX(GDA):
    """traingdx: traingdm's momentum step with traingda's adaptive lr."""

    momentum = True


@register("rp", "trainrp", 3, "Resilient backpropagation (RP)")
class RP(Step):
    """trainrp: per weight step sizes (delta0 0.07, x1.2 / x0.5, <= 50), dx = -delta sign(g)."""

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        super().__init__(problem, theta, est)
        self.delta = theta.new_full(theta.shape, 0.07)
        self.g_old = theta.new_zeros(theta.shape)

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        import torch

        gg = g * self.g_old
        self.delta = torch.clamp(torch.where(gg > 0, self.delta * 1.2, torch.where(gg < 0, self.delta * 0.5,
                                                                                   self.delta)), max=50.0)
        self.g_old = torch.where(gg < 0, torch.zeros_like(g), g)
        return self.moved(theta - self.delta * torch.sign(g))


@register("adam", "(none)", None, "Adam, full batch")
class Adam(Step):
    """torch.optim.Adam(lr) on the full batch."""

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        import torch

        super().__init__(problem, theta, est)
        self.param = theta.clone().requires_grad_(True)
        self.opt = torch.optim.Adam([self.param], lr=self.lr)

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        self.param.grad = g.clone()      # the gradient at theta, which the parameter holds
        self.opt.step()
        return self.moved(self.param.detach().clone())


@register("lbfgs", "(none)", None, "L-BFGS with strong Wolfe line search")
class LBFGS(Step):
    """torch.optim.LBFGS(lr=1, history 50, strong Wolfe), one iteration per epoch."""

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        import torch

        super().__init__(problem, theta, est)
        self.param = theta.clone().requires_grad_(True)
        self.opt = torch.optim.LBFGS([self.param], lr=1.0, max_iter=1, history_size=50,
                                     line_search_fn="strong_wolfe", tolerance_grad=1e-15, tolerance_change=1e-20)

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        def closure() -> Any:
            self.opt.zero_grad()
            loss = self.problem.loss(self.param)
            loss.backward()
            return loss

        self.opt.step(closure)
        return self.moved(self.param.detach().clone())


# --- scaled conjugate gradient -------------------------------------------------------------------

@register("scg", "trainscg", 4, "Scaled conjugate gradient backpropagation (SCG)")
class SCG(Step):
    """trainscg (Moller, Neural Networks 6, 1993, 525-533), MATLAB's update order.

    With direction d and r = -g: when the last step succeeded, the curvature along d is
    estimated by a finite difference of gradients, s = (g(x + sigma_k d) - g(x)) / sigma_k,
    sigma_k = sigma / |d|, delta = d's. The scale lambda makes it positive definite:
    delta += (lambda - lambda_bar) |d|^2; if delta <= 0: lambda_bar = 2 (lambda - delta /
    |d|^2), delta = -delta + lambda |d|^2, lambda = lambda_bar. Step alpha = mu / delta with
    mu = -d'g; comparison Delta = 2 delta (E(x) - E(x + alpha d)) / mu^2. Delta >= 0: accept,
    new direction -g + beta d with beta = (|g|^2 - g'g_old) / mu (restart with -g every P
    epochs, P = number of weights), lambda_bar = 0, and Delta >= 0.75 gives lambda /= 4.
    Delta < 0: reject, lambda_bar = lambda. Delta < 0.25 gives lambda += delta (1 - Delta) / |d|^2.
    """

    sigma, lambda0 = 5.0e-5, 5.0e-7

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        super().__init__(problem, theta, est)
        self.d: Any = None
        self.success = True
        self.lam, self.lam_bar = self.lambda0, 0.0
        self.delta = 0.0
        self.n_weights = theta.numel()

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        if self.d is None:
            self.d = -g
        d = self.d
        d2 = float(d @ d)
        if self.success:  # curvature along d by a finite difference of gradients
            sigma_k = self.sigma / math.sqrt(d2)
            _, g_sigma = self.problem.mse_grad(theta + sigma_k * d)
            self.delta = float(d @ ((g_sigma - g) / sigma_k))
        delta = self.delta + (self.lam - self.lam_bar) * d2
        if delta <= 0:
            self.lam_bar = 2.0 * (self.lam - delta / d2)
            delta = -delta + self.lam * d2
            self.lam = self.lam_bar
        mu = -float(d @ g)
        alpha = mu / delta
        trial = theta + alpha * d
        mse_trial = self.problem.mse(trial)
        # a non-finite trial or a direction without slope counts as a failed step
        comparison = 2.0 * delta * (mse - mse_trial) / (mu * mu) if math.isfinite(mse_trial) and mu else -math.inf
        self.delta = delta
        if comparison >= 0:
            mse_new, g_new = self.problem.mse_grad(trial)
            if epoch % self.n_weights == 0:
                self.d = -g_new
            else:
                beta = (float(g_new @ g_new) - float(g_new @ g)) / mu
                self.d = -g_new + beta * d
            self.lam_bar, self.success = 0.0, True
            if comparison >= 0.75:
                self.lam *= 0.25
            theta, mse, g = trial, mse_new, g_new
        else:
            self.lam_bar, self.success = self.lam, False
        if comparison < 0.25:
            self.lam += delta * (1.0 - comparison) / float(self.d @ self.d)
        return theta, mse, g

    def extra(self) -> dict[str, Any]:
        return {"final_lambda": self.lam}


# --- line searches -----------------------------------------------------------------------------

ALPHA, BETA, GAMA, SCALE_TOL, DELTA0 = 0.001, 0.1, 0.1, 20.0, 0.01
LOW_LIM, UP_LIM, MAXSTEP, MINSTEP = 0.1, 0.5, 100.0, 1.0e-6
_MAX_EVALS = 60  # a guard only: both searches end long before on any sane function


@dataclass
class LineResult:
    a: float
    mse: float
    g: Any


def srchcha(problem: Problem, theta: Any, d: Any, mse: float, g: Any, slope: float, delta: float,
            tol: float, ch_perf: float) -> tuple[LineResult, float, float]:
    """MATLAB's srchcha (Charalambous, IEE Proc. G 139(3), 1992): bracket and cubic interpolation.

    First step max(delta, -2 ch_perf / slope); while the interval [a, b] is wider than tol
    and the better end fails sufficient decrease (alpha) or the slope condition
    (|slope| <= beta |slope_0|): a negative slope at b moves the trial point a + delta with
    delta x 3 (b lower than a) or / 3 (higher); a positive slope at b places it at the
    minimum of the cubic through a and b, kept within [gama, 1 - gama] of the interval. The
    trial point replaces b when it lies beyond b, or when its slope is positive or it is
    higher than a; else it replaces a. Returns the better end, the next first step (the step
    taken, at least 0.01) and tol = min(tol, delta / scale_tol).
    """
    def probe(step: float) -> tuple[float, Any, float]:
        f, grad = problem.mse_grad(theta + step * d)
        return f, grad, float(grad @ d)

    a, fa, ga, sa = 0.0, mse, g, slope
    delta = max(delta, -2.0 * ch_perf / slope)
    b = delta
    fb, gb, sb = probe(b)
    best = (a, fa, ga, sa) if fa < fb else (b, fb, gb, sb)
    evals = 1
    while (b - a > tol and (best[1] > mse + ALPHA * best[0] * slope or abs(best[3]) > abs(BETA * slope))
           and evals < _MAX_EVALS):
        width = b - a
        if sb < 0:
            delta = delta / 3.0 if fb > fa else delta * 3.0
        else:
            w = 3.0 * (fa - fb) / width + sa + sb
            v = math.sqrt(max(w * w - sa * sb, 0.0))
            star = width * (1.0 - (sb + v - w) / (sb - sa + 2.0 * v))
            if not math.isfinite(star):
                star = (1.0 - GAMA) * width
            delta = max(GAMA * width, min(star, (1.0 - GAMA) * width))
        t = a + delta
        ft, gt, st = probe(t)
        evals += 1
        if not math.isfinite(ft):
            b, fb, gb, sb = t, math.inf, gt, 1.0
        elif t > b:
            a, fa, ga, sa = b, fb, gb, sb
            b, fb, gb, sb = t, ft, gt, st
        elif st > 0 or ft > fa:
            b, fb, gb, sb = t, ft, gt, st
        else:
            a, fa, ga, sa = t, ft, gt, st
        best = (a, fa, ga, sa) if fa < fb else (b, fb, gb, sb)
    step, f, grad, _ = best
    next_delta = max(step, DELTA0)
    return LineResult(step, f, grad), next_delta, min(tol, next_delta / SCALE_TOL)


def srchbac(problem: Problem, theta: Any, d: Any, mse: float, g: Any, slope: float) -> LineResult:
    """MATLAB's srchbac (Dennis & Schnabel's backtracking) from the full step lambda = 1.

    Sufficient decrease: E(lambda) <= E(0) + alpha lambda slope. While it fails, lambda goes
    to the minimum of the quadratic (first backtrack) or cubic (later) interpolation of E,
    kept within [low_lim, up_lim] of the last lambda; below minstep / |d| the search gives
    up (no step). When the full step already decreases enough but the slope is still steep
    (slope(lambda) < beta slope), lambda doubles (up to maxstep / |d|) while both stay so;
    an extension that loses sufficient decrease keeps the last step that had it (where
    srchbac would interpolate between the two).
    """
    def value(step: float) -> float:
        f = problem.mse(theta + step * d)
        return f if math.isfinite(f) else math.inf

    norm_d = float(d.norm())
    lam_min, lam_max = MINSTEP / norm_d, MAXSTEP / norm_d
    lam = min(1.0, lam_max)
    f = value(lam)
    lam_old = f_old = None
    evals = 1
    while f > mse + ALPHA * lam * slope:
        if lam < lam_min or evals >= _MAX_EVALS:
            return LineResult(0.0, mse, g)
        if lam_old is None or not math.isfinite(f) or not math.isfinite(f_old):
            new = -slope * lam * lam / (2.0 * (f - mse - slope * lam)) if math.isfinite(f) else LOW_LIM * lam
        else:
            r1 = f - mse - slope * lam
            r2 = f_old - mse - slope * lam_old
            c3 = (r1 / lam ** 2 - r2 / lam_old ** 2) / (lam - lam_old)
            c2 = (-lam_old * r1 / lam ** 2 + lam * r2 / lam_old ** 2) / (lam - lam_old)
            if c3 == 0:
                new = -slope / (2.0 * c2)
            else:
                new = (-c2 + math.sqrt(max(c2 * c2 - 3.0 * c3 * slope, 0.0))) / (3.0 * c3)
        lam_old, f_old = lam, f
        lam = min(max(new, LOW_LIM * lam), UP_LIM * lam) if math.isfinite(new) else LOW_LIM * lam
        f = value(lam)
        evals += 1
    f, grad = problem.mse_grad(theta + lam * d)
    if lam_old is None:  # the first step decreased enough: extend while the slope stays steep
        while float(grad @ d) < BETA * slope and lam < lam_max and evals < _MAX_EVALS:
            longer = min(2.0 * lam, lam_max)
            f2, g2 = problem.mse_grad(theta + longer * d)
            evals += 1
            if not (math.isfinite(f2) and f2 <= mse + ALPHA * longer * slope):
                break
            lam, f, grad = longer, f2, g2
    return LineResult(lam, f, grad)


def _ratio(num: float, den: float) -> float:
    """num / den, 0 for den = 0: where MATLAB's division by zero would leave a NaN or
    infinite direction, the term drops out (and the descent checks restart with -g)."""
    return num / den if den else 0.0


# --- quasi-Newton and conjugate gradients ----------------------------------------------------------

@register("bfg", "trainbfg", 5, "BFGS quasi-Newton backpropagation (BFG)")
class BFG(Step):
    """trainbfg (Gill, Murray & Wright 1981): H = I, dx = -g first; then the BFGS update of
    the Hessian approximation H += g_old g_old' / (g_old' d) + y y' / (y' s) (y = change of
    gradient, s = the step taken), dx = -H \\ g, reset to H = I, dx = -g when that is not a
    descent direction; step length by ``srchbac``. Stops with "Minimum step size reached"
    when the search finds no lower point, "Precision problems in matrix inversion" when the
    direction is not finite."""

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        import torch

        super().__init__(problem, theta, est)
        self.eye = torch.eye(theta.numel(), dtype=theta.dtype)
        self.H = self.eye.clone()
        self.d: Any = None
        self.s: Any = None
        self.g_old: Any = None

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        import torch

        if self.d is None:
            d = -g
        else:
            y = g - self.g_old
            self.H = (self.H + _ratio(1.0, float(self.g_old @ self.d)) * torch.outer(self.g_old, self.g_old)
                      + _ratio(1.0, float(y @ self.s)) * torch.outer(y, y))
            d = -torch.linalg.solve(self.H, g) if bool(torch.isfinite(self.H).all()) else g * math.nan
            if float(g @ d) > 0:
                self.H, d = self.eye.clone(), -g
        if not bool(torch.isfinite(d).all()):
            self.stop_reason = "Precision problems in matrix inversion"
            return theta, mse, g
        found = srchbac(self.problem, theta, d, mse, g, float(g @ d))
        if found.a == 0:
            self.stop_reason = "Minimum step size reached"
            return theta, mse, g
        self.d, self.g_old, self.s = d, g, found.a * d
        return theta + self.s, found.mse, found.g


class ConjugateGradient(Step):
    """The traincgf / traincgp frame: first direction -g / |g|; then d = -g + Z d_old with the
    variant's Z (Z = 0 every P epochs, P = number of weights), normalised; a direction whose
    slope g'd is not below -0.001 |g| is replaced by -g / |g|. Step length by ``srchcha``
    (first step 0.01, then the last step taken; ch_perf = the last change of the mse). Stops
    with "Minimum step size reached" when the search finds no lower point."""

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        super().__init__(problem, theta, est)
        self.n_weights = theta.numel()
        self.d_old: Any = None
        self.g_old: Any = None
        self.mse_old: float | None = None
        self.delta, self.tol = DELTA0, DELTA0 / SCALE_TOL

    def z(self, g: Any) -> float:
        raise NotImplementedError

    def direction(self, epoch: int, g: Any, gnorm: float) -> Any:
        z = 0.0 if epoch % self.n_weights == 0 else self.z(g)
        return -g + z * self.d_old

    def __call__(self, epoch: int, theta: Any, mse: float, g: Any) -> tuple[Any, float, Any]:
        gnorm = float(g.norm())
        if self.d_old is None:
            d, ch_perf = -g / gnorm, mse
            self.d_old = -g
        else:
            raw = self.direction(epoch, g, gnorm)
            ch_perf = mse - self.mse_old
            self.d_old = raw
            d = raw / float(raw.norm())
            if float(g @ d) >= -0.001 * gnorm:
                d = -g / gnorm
                self.d_old = -g
                self.restarted(epoch)
        self.g_old, self.mse_old = g, mse
        found, self.delta, self.tol = srchcha(self.problem, theta, d, mse, g, float(g @ d), self.delta,
                                              self.tol, ch_perf)
        if found.a == 0:
            self.stop_reason = "Minimum step size reached"
            return theta, mse, g
        return theta + found.a * d, found.mse, found.g

    def restarted(self, epoch: int) -> None:
        """Hook for variants that keep restart state."""


@register("cgf", "traincgf", 11, "Fletcher-Powell conjugate gradient backpropagation (FP)")
class CGF(ConjugateGradient):
    """traincgf, Fletcher-Reeves: Z = |g|^2 / |g_old|^2."""

    def z(self, g: Any) -> float:
        return _ratio(float(g @ g), float(self.g_old @ self.g_old))


@register("cgp", "traincgp", 12, "Polak-Ribiere conjugate gradient backpropagation (PR)")
class CGP(ConjugateGradient):
    """traincgp, Polak-Ribiere: Z = (g - g_old)'g / |g_old|^2."""

    def z(self, g: Any) -> float:
        return _ratio(float((g - self.g_old) @ g), float(self.g_old @ self.g_old))


@register("cgb", "traincgb", 10, "Powell-Beale conjugate gradient backpropagation (PB)")
class CGB(ConjugateGradient):
    """traincgb (Powell, Math. Programming 12, 1977, 241-254): restart (t = this epoch - 1,
    keep d_t = d_old and y_t = g - g_old) when |g_old'g| >= 0.2 |g|^2 or P epochs have passed
    since the last restart; d = -g + Z1 d_old + Z2 d_t with Z1 = g'y / d_old'y (y = g - g_old)
    and Z2 = g'y_t / d_t'y_t (0 right after the restart)."""

    def __init__(self, problem: Problem, theta: Any, est: Any) -> None:
        super().__init__(problem, theta, est)
        self.t = 1
        self.d_t: Any = None
        self.y_t: Any = None
        self.dy_t = 1.0

    def direction(self, epoch: int, g: Any, gnorm: float) -> Any:
        if abs(float(self.g_old @ g)) >= 0.2 * gnorm * gnorm or epoch - self.t >= self.n_weights:
            self.t = epoch - 1
            self.y_t, self.d_t = g - self.g_old, self.d_old
            self.dy_t = float(self.d_t @ self.y_t)
        y = g - self.g_old
        d = -g + _ratio(float(g @ y), float(self.d_old @ y)) * self.d_old
        if epoch != self.t + 1 and self.d_t is not None:
            d = d + _ratio(float(g @ self.y_t), self.dy_t) * self.d_t
        return d

    def restarted(self, epoch: int) -> None:
        self.t, self.d_t, self.y_t, self.dy_t = epoch, None, None, 1.0
