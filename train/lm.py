"""The Levenberg-Marquardt linear algebra of trainlm ("lm") and trainbr ("br").

The two trainers are steps of the shared training loop (``trainers.LM``, ``trainers.BR``);
this module holds what they need beyond it: the network over a flat parameter vector, its
Gauss-Newton matrix and the damped Cholesky solves. Everything is float64 torch on the CPU.

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

The damped systems (J^T J + mu I) and (beta J^T J + (alpha + mu) I) are solved by Cholesky
(``Normal``); trainbr's effective parameter count needs the trace of an inverse. A matrix that
is not positive definite gives None: the step counts as failed and mu grows. Where the error
terms are fewer than the weights (a session of a few dozen poses against a network of
1,649 weights), ``Network.linearise`` hands the same system over in error space (``Dual``:
J from the same sensitivities, one eigendecomposition of J J^T per epoch).
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from .activations import get_activation, mlp_forward


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
    def _sensitivities(self, theta: Any, X: Any, T: Any) -> tuple[list, list, Any]:
        """(each layer's augmented input (S, A_l), its sensitivities delta_l (S, m, n_l), r (S, m))."""
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
        return augmented, deltas, r

    def gauss_newton(self, theta: Any, X: Any, T: Any) -> tuple[Any, Any, Any]:
        """(J^T J (P x P), J^T r (P,), r (S, m)) of r = (y - T) * escale, J = dr/dtheta."""
        t = self.torch
        augmented, deltas, r = self._sensitivities(theta, X, T)
        S = X.shape[0]
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

    def jacobian_rows(self, theta: Any, X: Any, T: Any) -> tuple[Any, Any]:
        """(J ((S m) x P), r (S, m)): each row the Kronecker product a~_s (x) delta_{s,k}."""
        augmented, deltas, r = self._sensitivities(theta, X, T)
        rows = r.numel()
        J = self.torch.cat([self.torch.einsum("sa,skj->skaj", a, d).reshape(rows, -1)
                            for a, d in zip(augmented, deltas)], dim=1)
        return J, r

    def linearise(self, theta: Any, X: Any, T: Any) -> "Normal | Dual":
        """The damped system at theta: in weight space (P x P) where the error terms are at least
        the weights, else in error space ((S m) x (S m)): a session of a few dozen poses has
        hundreds of error terms against zhou 20-20-20-20's 1,649 weights."""
        if X.shape[0] * T.shape[1] >= self.n_params:
            return Normal(*self.gauss_newton(theta, X, T))
        return Dual(*self.jacobian_rows(theta, X, T))

    def jacobian(self, theta: Any, X: Any, T: Any) -> Any:
        """The full (S m) x P Jacobian of the residual by autograd (for tests and benchmarks)."""
        from torch.func import jacrev

        return jacrev(lambda th: self.residual(th, X, T).reshape(-1))(theta)


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


class Normal:
    """(beta J'J + c I) dx = -(beta J'r + alpha theta) in weight space, from `gauss_newton`."""

    def __init__(self, JJ: Any, g: Any, r: Any) -> None:
        self.JJ, self.g = JJ, g
        self.ed = float((r * r).sum())

    def _damped(self, beta: float, c: float) -> Any:
        A = beta * self.JJ
        A.diagonal().add_(c)
        return A

    def step(self, beta: float, c: float, alpha: float, theta: Any) -> Any | None:
        """dx, or None where the damped matrix is not positive definite."""
        return _cholesky_solve(self._damped(beta, c), -(beta * self.g + alpha * theta))

    def trace_inverse(self, beta: float, alpha: float) -> float | None:
        """trace((beta J'J + alpha I)^-1): trainbr's effective parameter count needs it."""
        return _trace_inverse(self._damped(beta, alpha))


class Dual:
    """The same system through J J' where the error terms N are fewer than the weights P.
    (beta J'J + c I)^-1 J' = J' (beta J J' + c I)^-1, and theta splits into its part in the
    row space of J and the rest, which the system only scales by 1 / c:

        dx = -J' (beta J J' + c I)^-1 (beta r - (alpha beta / c) J theta) - (alpha / c) theta

    One eigendecomposition J J' = U diag(lam) U' serves every damping c a step tries and the
    trace, trace((beta J'J + alpha I)^-1) = (P - N) / alpha + sum 1 / (beta lam + alpha): the
    cost of a step falls from P^3 to N^2 P."""

    def __init__(self, J: Any, r: Any) -> None:
        import torch

        self.J, self.r = J, r.reshape(-1)
        self.g = J.T @ self.r
        self.ed = float(self.r @ self.r)
        self.lam, self.U = torch.linalg.eigh(J @ J.T)

    def step(self, beta: float, c: float, alpha: float, theta: Any) -> Any | None:
        scale = beta * self.lam + c
        if not bool((scale > 0).all()):
            return None
        v = beta * self.r
        if alpha:
            v = v - (alpha * beta / c) * (self.J @ theta)
        dx = -(self.J.T @ (self.U @ ((self.U.T @ v) / scale)))
        return dx - (alpha / c) * theta if alpha else dx

    def trace_inverse(self, beta: float, alpha: float) -> float | None:
        scale = beta * self.lam + alpha
        if alpha <= 0 or not bool((scale > 0).all()):
            return None
        return (self.J.shape[1] - len(self.lam)) / alpha + float((1.0 / scale).sum())
