"""The Levenberg-Marquardt core shared by trainlm ("lm") and trainbr ("br").

Everything is float64 torch on the CPU.

The Gauss-Newton matrix without forming J
-----------------------------------------
For a network with m outputs, the Jacobian row of sample s, output k, for the weights of
layer l (augmented input a~ = [a, 1] of size A_l, n_l units) is the Kronecker product
a~_s (x) delta_{s,k} with delta_{s,k} = d y_k / d z_l (the back-propagated sensitivity of
output k). Hence, block (l, l') of J^T J is

    sum_s sum_k (a~_s a~'_s^T) (x) (delta_{s,k} delta'_{s,k}^T)
        = sum_s (a~_s a~'_s^T) (x) G_s,   G_s = delta_s^T delta'_s  (n_l x n_l', summed over k)

so the m output rows of a sample collapse into ONE Kronecker term before the big
contraction: the cost is 2 S P^2 flops (S samples, P parameters) instead of 2 S m P^2 for
J^T J from the (S m) x P Jacobian: m = 9 times fewer for zhou (6 + 3 outputs). Each block is
one GEMM of (S x A_l A_l') by (S x n_l n_l') matrices. The sensitivities for all m outputs
come from one batched back-propagation seeded with diag(escale) (the reverse mapminmax,
so the errors are in target units, MATLAB's default). J^T r is a_l^T (sum_k delta_k r_k).

The damped systems (J^T J + mu I) and (beta J^T J + (alpha + mu) I) are solved by Cholesky;
a failed step (higher objective or a non-positive-definite matrix) multiplies mu by mu_inc
and re-factorises: only the diagonal changes, J^T J is formed once per epoch.

MATLAB semantics
----------------
trainlm: mu = 1e-3, mu_dec 0.1 on success, mu_inc 10 and retry on failure, stop when
mu > mu_max (1e10), |grad| < min_grad (1e-7), mse <= goal, epochs (1000) done, or
max_fail (6) consecutive epochs without a new best validation error; returns the network
with the best validation error (the last one when there is no validation set).

trainbr: MacKay's evidence framework as in MATLAB's trainbr: F = beta Ed + alpha Ew
(Ed = sum of squared errors, Ew = sum of squared weights and biases); initially
gamma = P, beta = (N - gamma) / (2 Ed), alpha = gamma / (2 Ew); each epoch one LM step on F
with (beta J^T J + (alpha + mu) I), mu starting at 5e-3; after an accepted step
gamma = P - alpha trace((beta J^T J + alpha I)^-1) (J^T J of the epoch's start point, as
MATLAB), alpha = gamma / (2 Ew), beta = (N - gamma) / (2 Ed). No validation stop; returns the
LAST network (the validation error is only recorded). N = number of error terms (S m).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from .activations import get_activation, mlp_forward

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


class Network:
    """A functional MLP over a flat float64 parameter vector (layer blocks [W; b], row-major)."""

    def __init__(self, sizes: Sequence[int], activation: str, escale: np.ndarray) -> None:
        import torch

        self.torch = torch
        self.sizes = list(sizes)
        self.activation = get_activation(activation)
        self.n_layers = len(sizes) - 1
        self.blocks = [(sizes[i] + 1, sizes[i + 1]) for i in range(self.n_layers)]
        self.offsets = np.cumsum([0] + [a * n for a, n in self.blocks]).tolist()
        self.n_params = self.offsets[-1]
        self.escale = torch.as_tensor(np.asarray(escale, np.float64))

    def pack(self, coefs: Sequence[np.ndarray], intercepts: Sequence[np.ndarray]) -> Any:
        parts = [np.concatenate([w, b[None, :]], axis=0).ravel() for w, b in zip(coefs, intercepts)]
        return self.torch.as_tensor(np.concatenate(parts), dtype=self.torch.float64)

    def unpack(self, theta: Any) -> list[tuple[Any, Any]]:
        out = []
        for (a, n), off in zip(self.blocks, self.offsets):
            block = theta[off:off + a * n].reshape(a, n)
            out.append((block[:-1], block[-1]))
        return out

    def to_numpy(self, theta: Any) -> tuple[list[np.ndarray], list[np.ndarray]]:
        layers = self.unpack(theta.detach())
        return ([w.numpy().copy() for w, _ in layers], [b.numpy().copy() for _, b in layers])

    # --- forward -----------------------------------------------------------------------
    def outputs(self, theta: Any, X: Any, inputs: list | None = None, pre: list | None = None) -> Any:
        """Network output in the scaled target space (S, m); differentiable in theta.
        ``inputs`` / ``pre`` receive each layer's input and pre-activation (``mlp_forward``)."""
        return mlp_forward(X, self.unpack(theta), self.activation.name, inputs, pre)

    def residual(self, theta: Any, X: Any, T: Any) -> Any:
        return (self.outputs(theta, X) - T) * self.escale

    def sse(self, theta: Any, X: Any, T: Any) -> float:
        r = self.residual(theta, X, T)
        return float(self.torch.sum(r * r))

    # --- Gauss-Newton pieces ---------------------------------------------------------------
    def gauss_newton(self, theta: Any, X: Any, T: Any) -> tuple[Any, Any, Any]:
        """(J^T J (P x P), J^T r (P,), r (S, m)) of r = (y - T) * escale, J = dr/dtheta."""
        t = self.torch
        S = X.shape[0]
        layers = self.unpack(theta)
        inputs: list = []
        zs: list = []
        h = self.outputs(theta, X, inputs, zs)
        ones = t.ones((S, 1), dtype=X.dtype)
        augmented = [t.cat([a, ones], dim=1) for a in inputs]
        acts = inputs[1:]                                 # a hidden layer's output is the next one's input
        r = (h - T) * self.escale
        m = T.shape[1]
        # sensitivities delta_l (S, m, n_l) of the scaled outputs (x escale), top down
        delta = t.diag(self.escale).expand(S, m, m)
        deltas = [delta]
        for i in range(self.n_layers - 2, -1, -1):
            w_up = layers[i + 1][0]                       # (n_i, n_{i+1})
            u = t.matmul(delta, w_up.T)                   # (S, m, n_i)
            d = None if self.activation.derivative is None else self.activation.derivative(zs[i], acts[i])
            if d is None:                                 # a Jacobian that is not diagonal: softmax
                s = acts[i][:, None, :]
                us = u * s
                delta = us - us.sum(-1, keepdim=True) * s
            else:
                delta = u * d[:, None, :]
            deltas.append(delta)
        deltas.reverse()
        P = self.n_params
        JJ = t.empty((P, P), dtype=X.dtype)
        g = t.empty(P, dtype=X.dtype)
        for l in range(self.n_layers):
            Al, nl = self.blocks[l]
            ol = self.offsets[l]
            g[ol:ol + Al * nl] = (augmented[l].T @ t.einsum("skj,sk->sj", deltas[l], r)).reshape(-1)
            for k in range(l, self.n_layers):
                Ak, nk = self.blocks[k]
                ok = self.offsets[k]
                G = t.bmm(deltas[l].transpose(1, 2), deltas[k]).reshape(S, nl * nk)
                Pm = (augmented[l][:, :, None] * augmented[k][:, None, :]).reshape(S, Al * Ak)
                block = (Pm.T @ G).reshape(Al, Ak, nl, nk).permute(0, 2, 1, 3).reshape(Al * nl, Ak * nk)
                JJ[ol:ol + Al * nl, ok:ok + Ak * nk] = block
                if k != l:
                    JJ[ok:ok + Ak * nk, ol:ol + Al * nl] = block.T
        return JJ, g, r

    def jacobian(self, theta: Any, X: Any, T: Any) -> Any:
        """The full (S m) x P Jacobian of the residual by autograd (for tests and benchmarks)."""
        from torch.func import jacrev

        return jacrev(lambda th: self.residual(th, X, T).reshape(-1))(theta)


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


def _cholesky_solve(A: Any, b: Any) -> Any | None:
    import torch

    L, info = torch.linalg.cholesky_ex(A)
    if int(info) != 0:
        return None
    return torch.cholesky_solve(b[:, None], L)[:, 0]


def _trace_inverse(A: Any) -> float | None:
    import torch

    L, info = torch.linalg.cholesky_ex(A)
    if int(info) != 0:
        return None
    # LAPACK potri: A^-1 from its Cholesky factor (cheaper than a triangular solve with I)
    return float(torch.diagonal(torch.cholesky_inverse(L)).sum())


def train_lm(est: Any, sizes: Sequence[int], coefs: list[np.ndarray], intercepts: list[np.ndarray],
             Xn: np.ndarray, Tn: np.ndarray, escale: np.ndarray,
             val: tuple[np.ndarray, np.ndarray] | None, bayesian: bool = False) -> TrainResult:
    """trainlm, or trainbr (bayesian), on scaled inputs Xn and targets Tn (see the module
    docstring)."""
    import torch

    net, theta, X, T, Xv, Tv = training_tensors(est, sizes, coefs, intercepts, Xn, Tn, escale, val)
    P = net.n_params
    N = T.numel()
    eye = torch.eye(P, dtype=torch.float64)
    mu = float(est.mu if est.mu is not None else (5e-3 if bayesian else 1e-3))
    mu_dec, mu_inc, mu_max = float(est.mu_dec), float(est.mu_inc), float(est.mu_max)
    history: dict[str, list[float]] = {"mse": [], "val_mse": [], "mu": [], "seconds": []}
    if bayesian:
        history.update({"gamma": [], "alpha": [], "beta": []})

    ed = net.sse(theta, X, T)
    ew = float(theta @ theta)
    gamma = float(P)
    alpha = beta = 0.0
    if bayesian:
        beta = 1.0 if ed == 0 else (N - gamma) / (2.0 * ed)
        if beta <= 0:
            beta = 1.0
        alpha = gamma / (2.0 * ew) if ew > 0 else 1.0

    check = ValidationCheck(theta)
    stop = "Maximum epoch reached"
    epoch = 0
    t0 = time.perf_counter()
    for epoch in range(int(est.epochs) + 1):
        JJ, g, r = net.gauss_newton(theta, X, T)
        ed = float(torch.sum(r * r))
        mse = ed / N
        vmse = float("nan")
        if Xv is not None:
            vmse = net.sse(theta, Xv, Tv) / Tv.numel()
            check.update(vmse, theta)
        history["mse"].append(mse)
        history["val_mse"].append(vmse)
        history["mu"].append(mu)
        history["seconds"].append(time.perf_counter() - t0)
        if bayesian:
            history["gamma"].append(gamma)
            history["alpha"].append(alpha)
            history["beta"].append(beta)
        if est.verbose and epoch % int(est.verbose) == 0:
            print(f"epoch {epoch:4d} mse {mse:.4g} val {vmse:.4g} mu {mu:.2g}"
                  + (f" gamma {gamma:.1f}" if bayesian else ""), flush=True)
        grad = 2.0 * float(torch.linalg.vector_norm(g if not bayesian else beta * g + alpha * theta))
        if epoch >= int(est.epochs):
            stop = "Maximum epoch reached"
            break
        if mse <= est.goal:
            stop = "Performance goal met"
            break
        if grad < est.min_grad:
            stop = "Minimum gradient reached"
            break
        if mu > mu_max:
            stop = "Maximum MU reached"
            break
        if not bayesian and Xv is not None and check.fails >= int(est.max_fail):
            stop = "Validation stop"
            break

        # --- one Levenberg-Marquardt step: raise mu until the objective falls ---------------
        if bayesian:
            ew = float(theta @ theta)
            perf = beta * ed + alpha * ew
            H = beta * JJ
            rhs = -(beta * g + alpha * theta)
        else:
            perf = ed
            H = JJ
            rhs = -g
        accepted = False
        while mu <= mu_max:
            step = _cholesky_solve(H + (mu + alpha) * eye, rhs)
            if step is not None:
                trial = theta + step
                ed2 = net.sse(trial, X, T)
                ew2 = float(trial @ trial)
                perf2 = beta * ed2 + alpha * ew2 if bayesian else ed2
                if math.isfinite(perf2) and perf2 < perf:
                    theta, ed, ew = trial, ed2, ew2
                    mu = max(mu * mu_dec, 1e-20)
                    accepted = True
                    break
            mu *= mu_inc
        if bayesian and accepted:
            tr = _trace_inverse(H + alpha * eye)
            if tr is not None:
                gamma = P - alpha * tr
                alpha = 1.0 if ew == 0 else gamma / (2.0 * ew)
                beta = 1.0 if ed == 0 else (N - gamma) / (2.0 * ed)
        if not accepted:
            stop = "Maximum MU reached"
            epoch += 1
            history["mse"].append(ed / N)
            history["val_mse"].append(float("nan") if Xv is None else net.sse(theta, Xv, Tv) / Tv.numel())
            break

    final = theta
    if not bayesian and Xv is not None and check.best < math.inf:
        final = check.best_theta
    coefs_out, intercepts_out = net.to_numpy(final)
    extra: dict[str, Any] = {"seconds": time.perf_counter() - t0,
                             "seconds_per_epoch": (time.perf_counter() - t0) / max(epoch, 1)}
    if bayesian:
        extra.update({"gamma": gamma, "alpha": alpha, "beta": beta, "n_errors": N})
    train_loss = net.sse(final, X, T) / N
    return TrainResult(coefs_out, intercepts_out, epoch, stop, history,
                       check.best_or_none, train_loss, extra)
