"""Training benchmark: ``python -m bench.train [out.json]`` (or ``make bench``).

1. Seconds per Levenberg-Marquardt epoch of the paper's best Exp III network
   (zhou: 9-20-20-20-20-9 tansig, 1649 parameters) on 2360 samples (70 % of Exp III),
   posecorr's core (factored J^T J, Cholesky) side by side with the
   ``torch-levenberg-marquardt`` PyPI package (vmap(jacrev) Jacobian, J^T J, Cholesky
   solve) on the same network, data and initial weights, both float64; plus the loss each
   reaches after the same number of epochs and the time each needs to reach the worse of
   the two final losses ("at equal loss").
   The package is optional: install it for measuring only with
   ``pip install --no-deps torch-levenberg-marquardt`` (its own dependencies
   pytorch-lightning / torchmetrics are NOT needed for ``LevenbergMarquardtModule``: the
   benchmark puts empty stand-ins for them into ``sys.modules`` when they are missing,
   because the package's ``__init__`` imports its Lightning helpers). If it cannot be
   imported the entry is null with the reason.
2. The wall time of ``repeats`` (30) runs of the protocol with the best Exp III
   configuration (zhou, tansig, 20-20-20-20, br) on the simulated Exp III, ``workers``
   local processes, with the test-set summary.
"""
from __future__ import annotations

import json
import os
import platform
import sys
import time
import types
from pathlib import Path
from typing import Any

import numpy as np


def _data(n: int = 2360, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    from posecorr.simulate import simulate

    from posecorr.train.base import encode_pose
    from posecorr.train.mlp import mapminmax_settings
    from posecorr.train.protocol import split_indices

    table = simulate(3, seed=seed).table
    train, _, _ = split_indices(table.n, seed, 0)
    train = train[:n]
    X = np.asarray(encode_pose(table.measured[train], "zhou"))
    Y = np.asarray(encode_pose(table.reference[train], "zhou"))
    gx, ox = mapminmax_settings(X)
    gy, oy = mapminmax_settings(Y)
    return X * gx + ox, Y * gy + oy


def _ours(Xn: np.ndarray, Tn: np.ndarray, theta0: Any, sizes: list[int], epochs: int) -> dict[str, Any]:
    import torch

    from posecorr.train.lm import Network, _cholesky_solve

    net = Network(sizes, "tansig", np.ones(sizes[-1]))
    X, T = torch.as_tensor(Xn), torch.as_tensor(Tn)
    theta = theta0.clone()
    eye = torch.eye(net.n_params, dtype=torch.float64)
    mu = 1e-3
    losses, times = [net.sse(theta, X, T) / T.numel()], [0.0]
    gn_seconds = []
    t0 = time.perf_counter()
    for _ in range(epochs):
        t1 = time.perf_counter()
        JJ, g, r = net.gauss_newton(theta, X, T)
        gn_seconds.append(time.perf_counter() - t1)
        ed = float(torch.sum(r * r))
        while mu <= 1e10:
            step = _cholesky_solve(JJ + mu * eye, -g)
            if step is not None:
                trial = theta + step
                ed2 = net.sse(trial, X, T)
                if ed2 < ed:
                    theta, mu = trial, max(mu * 0.1, 1e-20)
                    break
            mu *= 10.0
        losses.append(net.sse(theta, X, T) / T.numel())
        times.append(time.perf_counter() - t0)
    return {"seconds_per_epoch": times[-1] / epochs, "gauss_newton_seconds": float(np.median(gn_seconds)),
            "losses": losses, "times": times}


def _import_tlm() -> tuple[Any, str | None]:
    """The torch_levenberg_marquardt.training module, or (None, reason)."""
    stubs = []
    for name, attrs in (("pytorch_lightning", ("LightningModule", "Trainer", "Callback")),
                        ("torchmetrics", ("Metric",))):
        try:
            __import__(name)
        except ImportError:
            mod = types.ModuleType(name)
            for a in attrs:
                setattr(mod, a, type(a, (), {}))
            sys.modules[name] = mod
            stubs.append(name)
    try:
        import torch_levenberg_marquardt.training as training  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any failure is reported, not raised
        return None, f"{type(exc).__name__}: {exc}"
    return training, (f"stand-ins used for {', '.join(stubs)}" if stubs else None)


def _theirs(Xn: np.ndarray, Tn: np.ndarray, theta0: Any, sizes: list[int], epochs: int) -> dict[str, Any]:
    import torch

    training, note = _import_tlm()
    if training is None:
        return {"seconds_per_epoch": None, "reason": note}
    from posecorr.train.lm import Network

    layers: list[Any] = []
    for i in range(len(sizes) - 1):
        layers.append(torch.nn.Linear(sizes[i], sizes[i + 1]).double())
        if i < len(sizes) - 2:
            layers.append(torch.nn.Tanh())
    model = torch.nn.Sequential(*layers)
    # same initial weights: our blocks are [W (in, out); b], torch Linear holds W^T
    net = Network(sizes, "tansig", np.ones(sizes[-1]))
    linears = [m for m in model if isinstance(m, torch.nn.Linear)]
    with torch.no_grad():
        for lin, (w, b) in zip(linears, net.unpack(theta0)):
            lin.weight.copy_(w.T)
            lin.bias.copy_(b)
    module = training.LevenbergMarquardtModule(model, solve_method="cholesky", use_vmap=True)
    X, T = torch.as_tensor(Xn), torch.as_tensor(Tn)
    with torch.no_grad():
        losses, times = [float(torch.mean((model(X) - T) ** 2))], [0.0]
    t0 = time.perf_counter()
    for _ in range(epochs):
        module.training_step(X, T)
        with torch.no_grad():
            losses.append(float(torch.mean((model(X) - T) ** 2)))
        times.append(time.perf_counter() - t0)
    import importlib.metadata as md

    out = {"seconds_per_epoch": times[-1] / epochs, "losses": losses, "times": times,
           "version": md.version("torch-levenberg-marquardt"), "solve_method": "cholesky", "use_vmap": True}
    if note:
        out["note"] = note
    return out


def _time_to(losses: list[float], times: list[float], target: float) -> float | None:
    for loss, t in zip(losses, times):
        if loss <= target:
            return t
    return None


def lm_epoch_benchmark(epochs: int = 10, threads: int | None = None) -> dict[str, Any]:
    import torch

    if threads:
        torch.set_num_threads(threads)
    Xn, Tn = _data()
    sizes = [9, 20, 20, 20, 20, 9]
    from posecorr.train.lm import Network
    from posecorr.train.mlp import init_weights

    coefs, biases = init_weights(sizes, "tansig", np.random.default_rng(0))
    theta0 = Network(sizes, "tansig", np.ones(9)).pack(coefs, biases)
    ours = _ours(Xn, Tn, theta0, sizes, epochs)
    theirs = _theirs(Xn, Tn, theta0, sizes, epochs)
    out: dict[str, Any] = {"network": "9-20-20-20-20-9 tansig", "n_parameters": int(theta0.numel()),
                           "samples": int(len(Xn)), "residual_rows": int(Tn.size), "epochs": epochs,
                           "torch_threads": torch.get_num_threads(), "posecorr": ours,
                           "torch_levenberg_marquardt": theirs}
    if theirs.get("seconds_per_epoch"):
        out["speedup_per_epoch"] = theirs["seconds_per_epoch"] / ours["seconds_per_epoch"]
        target = max(ours["losses"][-1], theirs["losses"][-1])
        a, b = _time_to(ours["losses"], ours["times"], target), _time_to(theirs["losses"], theirs["times"], target)
        out["equal_loss"] = {"target_mse": target, "posecorr_seconds": a, "tlm_seconds": b,
                             "speedup": (b / a) if a and b else None}
    return out


def small_session_benchmark(poses: tuple[int, ...] = (12, 50), threads: int = 1) -> dict[str, Any]:
    """A small session's fit (``python -m bench --only train_small``): what `posecorr fit
    --method mlp --hidden 20-20-20-20 --effects station,mount` fits, the paper's network (zhou
    20-20-20-20, trainbr, residual) after the physics stage, on 12 and 50 poses of a simulated
    robot session (a network nobody named is smaller there, `spec.session_network`); the network's
    damped system solved in error space (J J', the trainers' choice where the error terms are
    fewer than the weights) and forced into weight space (J'J, P x P) in the same run: wall
    time, epochs, stop reason and training error of each."""
    import torch

    from posecorr.simulate import simulate_session
    from posecorr.train import lm
    from posecorr.train.mlp import MLP
    from posecorr.train.pipeline import CorrectionPipeline

    torch.set_num_threads(threads)
    weight_space = lambda self, theta, X, T: lm.Normal(*self.gauss_newton(theta, X, T))  # noqa: E731
    rows = []
    for n in poses:
        table = simulate_session(0, n=n, robot="ur5e").table
        row: dict[str, Any] = {"poses": n, "error_terms": 9 * n}
        for label in ("error_space", "weight_space"):
            saved = lm.Network.linearise
            if label == "weight_space":
                lm.Network.linearise = weight_space
            try:
                t0 = time.perf_counter()
                network = MLP("zhou", (20, 20, 20, 20), "tansig", "br", residual=True, random_state=0)
                model = CorrectionPipeline(("station", "mount"), network).fit(table.measured, table.reference)
                seconds = time.perf_counter() - t0
                est = model.core_
            finally:
                lm.Network.linearise = saved
            row[label] = {"seconds": seconds, "epochs": est.n_epochs_, "stop_reason": est.stop_reason_,
                          "training_rmse_total": -model.score(table.measured, table.reference)}
        row["speedup"] = row["weight_space"]["seconds"] / row["error_space"]["seconds"]
        rows.append(row)
    return {"network": "zhou 9-20-20-20-20-9 tansig, trainbr (1,649 weights)", "torch_threads": threads,
            "sessions": rows}


def run_small(out_path: str | os.PathLike = "bench/results/train_small.json") -> dict[str, Any]:
    load = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    result = {"load_average_before": load, **small_session_benchmark(),
              "load_average_after": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}
    Path(out_path).write_text(json.dumps(result, indent=2))
    return result


def repeats_benchmark(repeats: int = 30, workers: int = 2, epochs: int = 100, store: str | None = None
                      ) -> dict[str, Any]:
    from posecorr.simulate import simulate

    from posecorr.train.protocol import run_sweep
    from posecorr.train.spec import ModelSpec

    sim = simulate(3, seed=0)
    cfg = ModelSpec("mlp", "zhou", epochs=epochs)          # the spec's default network: the paper's 16/2
    t0 = time.perf_counter()
    res = run_sweep(sim.table, [cfg], repeats=repeats, store=store, workers=workers, progress=True)
    wall = time.perf_counter() - t0
    s = res.summary()[0]
    return {"config": cfg.key, "repeats": repeats, "workers": workers, "epochs": epochs,
            "wall_seconds": wall, "raw": res.raw, "noise_floor": sim.noise_floor,
            "rmse_total": s["rmse_total"], "rmse_pos": s["rmse_pos"], "rmse_rot": s["rmse_rot"],
            "improvement_total": s["improvement_total"],
            "seconds_per_run_avg": s["seconds_avg"]}


def run(out_path: str | os.PathLike = "bench/results/train.json", epochs: int = 10, repeats: int = 30,
        workers: int = 2, br_epochs: int = 100, skip_repeats: bool = False, threads: int = 1) -> dict[str, Any]:
    """Both benchmarks into ``out_path`` (JSON). ``threads``: torch threads for the per-epoch
    comparison (1 by default: on a shared 2-core machine the many short parallel regions of
    a 2-thread run are at the mercy of other processes; both libraries get the same)."""
    result: dict[str, Any] = {"machine": f"{platform.machine()} {platform.processor() or ''} "
                                         f"{os.cpu_count()} cpus, python {platform.python_version()}",
                              "load_average_before": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}
    result["lm_epoch"] = lm_epoch_benchmark(epochs, threads)
    if not skip_repeats:
        result["exp3_best_30_repeats"] = repeats_benchmark(repeats, workers, br_epochs)
    result["load_average_after"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default="bench/results/train.json")
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--br-epochs", type=int, default=100)
    ap.add_argument("--skip-repeats", action="store_true")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    r = run(a.out, a.epochs, a.repeats, a.workers, a.br_epochs, a.skip_repeats, a.threads)
    print(json.dumps({k: v for k, v in r["lm_epoch"].items() if k not in ("posecorr", "torch_levenberg_marquardt")},
                     indent=2))
    print("posecorr s/epoch", r["lm_epoch"]["posecorr"]["seconds_per_epoch"],
          "tlm s/epoch", r["lm_epoch"]["torch_levenberg_marquardt"].get("seconds_per_epoch"))
    if "exp3_best_30_repeats" in r:
        print(json.dumps(r["exp3_best_30_repeats"], indent=2))
