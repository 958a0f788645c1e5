"""First-order trainers with MATLAB semantics (full batch, one step per epoch).

All minimise the mean squared error of r = (y - T) * escale (the same error as the LM
core) with gradients from torch autograd, stop like MATLAB's ``train`` (``epochs``,
``goal`` on the mse, ``min_grad`` on |gradient|, ``max_fail`` consecutive validation
failures) and return the network with the best validation error (the last one without
validation data). ``lr`` is MATLAB's learning rate (paper: 0.01).

| trainer | MATLAB | rule (g = gradient of the mse) |
|---|---|---|
| gd    | traingd  | x -= lr g |
| gdm   | traingdm | dx = mc dx_prev - (1 - mc) lr g, mc = 0.9 |
| gda   | traingda | x -= lr g; a step raising the mse by > 4 % (max_perf_inc 1.04) is undone and lr *= 0.7; a step lowering it gives lr *= 1.05 |
| gdx   | traingdx | gdm's momentum step with gda's adaptive lr (momentum reset after an undone step) |
| rp    | trainrp  | per weight delta (delta0 0.07, x1.2 when the gradient keeps its sign, x0.5 when it flips, <= deltamax 50); dx = -delta sign(g); after a flip the next step waits (g_old = 0) |
| adam  | (none)   | torch.optim.Adam(lr) full batch |
| lbfgs | (none)   | torch.optim.LBFGS(lr=1, history 50, strong Wolfe line search), one iteration per epoch |
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable, Sequence

import numpy as np

from .lm import TrainResult, ValidationCheck, training_tensors


def train_first_order(est: Any, sizes: Sequence[int], coefs: list[np.ndarray], intercepts: list[np.ndarray],
                      Xn: np.ndarray, Tn: np.ndarray, escale: np.ndarray,
                      val: tuple[np.ndarray, np.ndarray] | None, callback: Callable | None = None) -> TrainResult:
    import torch

    net, theta, X, T, Xv, Tv = training_tensors(est, sizes, coefs, intercepts, Xn, Tn, escale, val)
    N = T.numel()

    def loss_grad(th: Any) -> tuple[float, Any]:
        th = th.detach().requires_grad_(True)
        r = net.residual(th, X, T)
        loss = torch.sum(r * r) / N
        (grad,) = torch.autograd.grad(loss, th)
        return float(loss.detach()), grad

    def mse_of(th: Any) -> float:
        with torch.no_grad():
            return net.sse(th, X, T) / N

    kind = est.trainer
    lr = float(est.lr)
    mc, lr_inc, lr_dec, max_perf_inc = 0.9, 1.05, 0.7, 1.04
    delta = torch.full_like(theta, 0.07)
    g_old = torch.zeros_like(theta)
    dx_prev = torch.zeros_like(theta)
    param = None
    opt = None
    if kind in ("adam", "lbfgs"):
        param = theta.clone().requires_grad_(True)
        if kind == "adam":
            opt = torch.optim.Adam([param], lr=lr)
        else:
            opt = torch.optim.LBFGS([param], lr=1.0, max_iter=1, history_size=50, line_search_fn="strong_wolfe",
                                    tolerance_grad=1e-15, tolerance_change=1e-20)

    history: dict[str, list[float]] = {"mse": [], "val_mse": [], "lr": []}
    check = ValidationCheck(theta)
    stop = "Maximum epoch reached"
    t0 = time.perf_counter()
    epoch = 0
    for epoch in range(int(est.epochs) + 1):
        current = param.detach() if param is not None else theta
        mse, g = loss_grad(current)
        vmse = float("nan")
        if Xv is not None:
            with torch.no_grad():
                vmse = net.sse(current, Xv, Tv) / Tv.numel()
            check.update(vmse, current)
        history["mse"].append(mse)
        history["val_mse"].append(vmse)
        history["lr"].append(lr)
        if callback is not None:
            callback(epoch, history)
        if est.verbose and epoch % int(est.verbose) == 0:
            print(f"epoch {epoch:4d} mse {mse:.4g} val {vmse:.4g} lr {lr:.3g}", flush=True)
        if epoch >= int(est.epochs):
            break
        if not math.isfinite(mse):
            stop = "Diverged"
            break
        if mse <= est.goal:
            stop = "Performance goal met"
            break
        if float(torch.linalg.vector_norm(g)) < est.min_grad:
            stop = "Minimum gradient reached"
            break
        if Xv is not None and check.fails >= int(est.max_fail):
            stop = "Validation stop"
            break

        if kind == "gd":
            theta = theta - lr * g
        elif kind == "gdm":
            dx_prev = mc * dx_prev - (1.0 - mc) * lr * g
            theta = theta + dx_prev
        elif kind in ("gda", "gdx"):
            if kind == "gdx":
                dx = mc * dx_prev - (1.0 - mc) * lr * g
            else:
                dx = -lr * g
            trial = theta + dx
            new = mse_of(trial)
            if not math.isfinite(new) or new > mse * max_perf_inc:
                lr *= lr_dec
                dx_prev = torch.zeros_like(theta)
            else:
                if new < mse:
                    lr *= lr_inc
                theta, dx_prev = trial, dx
        elif kind == "rp":
            gg = g * g_old
            delta = torch.where(gg > 0, delta * 1.2, torch.where(gg < 0, delta * 0.5, delta))
            delta = torch.clamp(delta, max=50.0)
            theta = theta - delta * torch.sign(g)
            g_old = torch.where(gg < 0, torch.zeros_like(g), g)
        elif kind in ("adam", "lbfgs"):
            def closure() -> Any:
                opt.zero_grad()
                r = net.residual(param, X, T)
                loss = torch.sum(r * r) / N
                loss.backward()
                return loss

            opt.step(closure)
        else:
            raise ValueError(f"unknown first-order trainer {kind!r}")

    final = param.detach() if param is not None else theta
    if Xv is not None and check.best < math.inf:
        final = check.best_theta
    coefs_out, intercepts_out = net.to_numpy(final)
    seconds = time.perf_counter() - t0
    return TrainResult(coefs_out, intercepts_out, epoch, stop, history,
                       check.best_or_none, mse_of(final),
                       {"seconds": seconds, "seconds_per_epoch": seconds / max(epoch, 1), "final_lr": lr})
