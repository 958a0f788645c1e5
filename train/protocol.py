"""The paper's evaluation protocol (section 2.4) as a resumable sweep.

* A fixed test set: 15 % of the rows, drawn once with ``seed`` (``splits.split_indices``).
* ``repeats`` (30) runs per configuration; run r draws a fresh random 70 / 15 split of
  the remaining rows into training and validation (seeded by (seed, r), so every
  configuration of a sweep sees the same splits in run r: the Friedman blocks).
* MLPs train on the training rows with the validation rows for early stopping (trainlm
  and the gradient trainers; trainbr only monitors them). PMC fits the training rows.
* Per run the corrector is evaluated on the fixed test set: rmse_pos, rmse_rot,
  rmse_total; a configuration's summary is min / avg / max over runs and the improvement
  raw / min (tables 2-4).
* The paper's reduction (``SweepResult.methods``): per representation the PMC and, per
  activation, the network (architecture and algorithm) with the lowest test rmse_total
  over the repeats: 16 methods in Exp III (table 4), 36 in Exp II (table 3), 9 in Exp I
  (table 2).
* Friedman test + Dunn-Sidak comparison of mean ranks of rmse_total on those methods +
  tier list (``stats``; tables 5 and A1), printed by ``tables``.
* Grids (``GRID_PRESETS``) are table 1's: 1536 / 384 / 96 networks per representation for
  Exp I / II / III, each configuration a ``spec.ModelSpec`` labelled as in the paper ("tansig
  16/2" = architecture 16 trained by algorithm 2; an architecture outside table 1 in
  parentheses, "(16)/1").

Results go to a JSON-lines store, one object per finished run keyed by (config key,
repeat) together with a fingerprint of the data and the seed; an interrupted sweep started
again with the same store skips the runs it already has. Runs are spread over local
processes (``concurrent.futures.ProcessPoolExecutor``, torch limited to
cores // workers threads each) or over a Ray cluster with ``ray_address`` (when ray is
installed). A tqdm bar shows runs done, ETA and the best test rmse_total so far (on a terminal;
written to a log, a line every 30 s and the last).
"""
from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from posecorr.metrics import METRIC_KEYS, frames_unregistered, improvement, metric_block, pose_metrics, summarize
from posecorr.rotations import POSITION_ONLY, REPRESENTATIONS
from posecorr.safeio import append_line, open_sidecar, sigterm_as_interrupt, warn
from posecorr.textui import counted, first_few

from .activations import PAPER_ACTIVATIONS
from .base import Validation
from .spec import ARCHITECTURES, TRAINER_NUMBERS, ModelSpec, parse_hidden, parse_network
from .splits import FixedSplit, split_indices
from .trainers import TRAINERS


# --- configurations ---------------------------------------------------------------------

# The paper's four orientation representations (a representation a test registers stays out
# of the paper's grids).
PAPER_REPRESENTATIONS = tuple(name for name, rep in REPRESENTATIONS.items() if rep.paper and rep.orientation)
# Table 1's twelve learning algorithms in its numbering (1 = lm ... 12 = cgp).
PAPER_TRAINERS = tuple(sorted(TRAINER_NUMBERS, key=TRAINER_NUMBERS.get))

GRID_PRESETS = {
    # paper Exp I: position only, 12 trainers x 8 activations x 16 architectures = 1536 networks
    "paper-exp1": dict(representations=(POSITION_ONLY,), activations=PAPER_ACTIVATIONS, trainers=PAPER_TRAINERS,
                       architectures=ARCHITECTURES),
    # paper Exp II: per representation 3 trainers x 8 activations x 16 architectures = 384 networks
    "paper-exp2": dict(representations=PAPER_REPRESENTATIONS, activations=PAPER_ACTIVATIONS,
                       trainers=("lm", "br", "rp"), architectures=ARCHITECTURES),
    # paper Exp III: per representation 2 trainers x 3 activations x 16 architectures = 96 networks
    "paper-exp3": dict(representations=PAPER_REPRESENTATIONS, activations=("logsig", "radbas", "tansig"),
                       trainers=("lm", "br"), architectures=ARCHITECTURES),
    # a reduced Exp III grid that runs in minutes on two cores: the 4 PMCs and, per
    # representation, tansig with two small architectures (10 and 5-5) trained by lm for at
    # most 100 epochs (12 configurations)
    "reduced": dict(representations=PAPER_REPRESENTATIONS, activations=("tansig",),
                    trainers=("lm",), architectures=((10,), (5, 5)), epochs=100),
}
# The paper's table that a preset's reduced results correspond to (tables 2-4).
PRESET_TABLES = {"paper-exp1": 2, "paper-exp2": 3, "paper-exp3": 4}


def build_grid(preset: str | None = None, *, representations: Sequence[str] | None = None,
               activations: Sequence[str] | None = None, trainers: Sequence[str] | None = None,
               architectures: Sequence[Any] | None = None, networks: Sequence[Any] | None = None,
               include_pmc: bool = True, include_mlp: bool = True,
               options: Mapping[str, Any] | None = None) -> list[ModelSpec]:
    """The configuration grid: the cross product of the given axes, per representation
    the PMC first (``include_pmc``) then the MLPs.

    ``preset``: "paper-exp1", "paper-exp2", "paper-exp3" (the paper's grids, see
    ``GRID_PRESETS``) or "reduced" (per representation: PMC + tansig 10 and 5-5 trained
    by lm for at most 100 epochs, 12 configurations); explicit axes override the preset's.
    Architectures may be tuples, "20-20" strings or table-1 numbers as "#16".
    ``networks``: the paper's "architecture/algorithm" labels ("16/2", "(8-8)/adam") or
    (hidden, trainer) pairs; they replace the architectures x trainers product.
    ``options`` are extra MLP parameters (e.g. {"epochs": 200}: the epoch cap, or any other
    estimator parameter) added to every MLP configuration.
    """
    if preset and preset not in GRID_PRESETS:
        raise ValueError(f"unknown preset {preset!r}; expected one of {', '.join(GRID_PRESETS)}")
    base = dict(GRID_PRESETS[preset]) if preset else dict(GRID_PRESETS["paper-exp3"])
    if representations is not None:
        base["representations"] = tuple(representations)
    if activations is not None:
        base["activations"] = tuple(activations)
    if trainers is not None:
        base["trainers"] = tuple(trainers)
    if architectures is not None:
        base["architectures"] = tuple(parse_hidden(a) for a in architectures)
    if networks is not None:
        pairs = [parse_network(n) if isinstance(n, str) else (parse_hidden(n[0]), n[1]) for n in networks]
    else:
        pairs = [(tuple(arch), tr) for arch in base["architectures"] for tr in base["trainers"]]
    if options is None:
        options = {"epochs": base["epochs"]} if "epochs" in base else {}
    options = dict(options)
    epochs = options.pop("epochs", None)
    grid: list[ModelSpec] = []
    for rep in base["representations"]:
        if include_pmc:
            grid.append(ModelSpec("pmc", rep))
        if include_mlp:
            for act in base["activations"]:
                for arch, tr in pairs:
                    grid.append(ModelSpec("mlp", rep, arch, act, tr, epochs, options))
    return grid


def table_fingerprint(table: Any) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(table.measured).tobytes())
    h.update(np.ascontiguousarray(table.reference).tobytes())
    return h.hexdigest()[:16]


# --- one fit --------------------------------------------------------------------------------

@dataclass
class FitResult:
    estimator: Any
    raw: dict[str, float | None]
    test: dict[str, float | None]          # metric_block: corrected metrics + improvements
    train_index: np.ndarray
    val_index: np.ndarray
    test_index: np.ndarray
    seconds: float


def fit_one(table: Any, spec: ModelSpec, seed: int = 0, repeat: int = 0, split: FixedSplit = FixedSplit()
            ) -> FitResult:
    """Fit `spec`'s corrector on the protocol's split of ``table`` and evaluate it on the test set.

    For a position-only table the spec's representation must be position only ("pos").
    A split with ``test_fraction=0`` fits on all rows but the validation rows (``raw``/``test``
    are then measured on the training rows and say so only through ``test_index`` being empty).
    """
    if not table.has_orientation and spec.with_rotation:
        raise ValueError(f"this table is position-only (no ref_q columns): use representation={POSITION_ONLY!r}")
    from posecorr.data import require_rows

    from .pipeline import check_outliers

    require_rows(table, 10, "fit with a train/validation/test split", outliers=check_outliers)
    tr, va, te = split.indices(table.n, seed, repeat)
    M, R = table.measured, table.reference
    est = spec.make(seed=seed * 1000 + repeat)
    t0 = time.perf_counter()
    est.fit(M[tr], R[tr], validation=Validation(M[va], R[va]) if len(va) else None)
    seconds = time.perf_counter() - t0
    rows = te if len(te) else tr
    with_rot = spec.with_rotation
    raw = pose_metrics(R[rows], M[rows], with_rot)
    corrected = pose_metrics(R[rows], est.predict(M[rows]), with_rot)
    return FitResult(est, raw, metric_block(raw, corrected), tr, va, te, seconds)


def run_one(table: Any, config: ModelSpec, repeat: int, seed: int = 0, threads: int | None = None) -> dict[str, Any]:
    """One run of the protocol; the store's row."""
    if threads:
        try:
            import torch

            torch.set_num_threads(int(threads))
        except ImportError:
            pass
    res = fit_one(table, config, seed=seed, repeat=repeat)
    est = res.estimator
    row: dict[str, Any] = {"key": config.key, "repeat": int(repeat), "seed": int(seed),
                           "config": asdict(config), "seconds": res.seconds,
                           **{k: res.test[k] for k in METRIC_KEYS}}
    if config.is_network:
        row.update({"epochs": int(est.n_epochs_), "stop": est.stop_reason_, "best_val": est.best_val_loss_})
    return row


# --- the sweep -------------------------------------------------------------------------------

@dataclass
class SweepResult:
    configs: list[ModelSpec]
    rows: list[dict[str, Any]]
    raw: dict[str, float | None]
    repeats: int
    seconds: float = 0.0
    store: str | None = None
    # The best rigid fit on the test poses (`best_rigid_on_test`): {"name", rmse_pos, ...}.
    rigid: dict[str, Any] | None = None
    _by_key: dict[str, list[dict[str, Any]]] = field(default_factory=dict, repr=False)

    def runs(self, config: ModelSpec) -> list[dict[str, Any]]:
        if sum(map(len, self._by_key.values())) != len(self.rows):  # index the rows once (Exp I: 46,080 runs)
            self._by_key.clear()
            for r in sorted(self.rows, key=lambda r: r["repeat"]):
                self._by_key.setdefault(r["key"], []).append(r)
        return self._by_key.get(config.key, [])

    def summary(self, configs: Sequence[ModelSpec] | None = None) -> list[dict[str, Any]]:
        """Per configuration (default: all): min/avg/max of the three RMSEs and improvement = raw / min."""
        out = []
        for cfg in self.configs if configs is None else configs:
            runs = self.runs(cfg)
            if not runs:
                continue
            row: dict[str, Any] = {"key": cfg.key, "label": cfg.label, "name": cfg.name,
                                   "representation": cfg.representation, "runs": len(runs),
                                   "seconds_avg": float(np.mean([r["seconds"] for r in runs]))}
            best: dict[str, float | None] = {}
            for key in METRIC_KEYS:
                vals = [r[key] for r in runs if r.get(key) is not None]
                row[key] = summarize(vals) if vals else None
                best[key] = row[key]["min"] if vals else None
            row.update(improvement(self.raw, best))
            out.append(row)
        return out

    def methods(self) -> list[ModelSpec]:
        """The paper's methods (section 3, tables 2-5): per representation the PMC and, per
        activation, the one network (architecture and algorithm) with the lowest test
        rmse_total over the repeats ("best ... based on the minimum value of the total RMSE
        found for all runs"); ties go to the lower average, then to the earlier in the grid.
        Exp III's preset gives 4 x (1 + 3) = 16 methods."""
        best: dict[tuple[str, str, str], tuple[tuple[float, float], ModelSpec]] = {}
        for cfg in self.configs:
            vals = [r["rmse_total"] for r in self.runs(cfg)
                    if r.get("rmse_total") is not None and math.isfinite(r["rmse_total"])]
            if not vals:
                continue
            score = (min(vals), float(np.mean(vals)))
            group = (cfg.representation, cfg.method, cfg.activation)
            if group not in best or score < best[group][0]:
                best[group] = (score, cfg)
        chosen = {cfg for _, cfg in best.values()}
        return [c for c in self.configs if c in chosen]

    def complete_matrix(self, configs: Sequence[ModelSpec] | None = None) -> tuple[list[ModelSpec], np.ndarray]:
        """(configs, (n runs, k configs) rmse_total) over the repeats every config has."""
        have = [c for c in (self.configs if configs is None else configs) if self.runs(c)]
        common = None
        for c in have:
            reps = {r["repeat"] for r in self.runs(c)}
            common = reps if common is None else common & reps
        reps_sorted = sorted(common or [])
        data = np.array([[next(r["rmse_total"] for r in self.runs(c) if r["repeat"] == i) for c in have]
                         for i in reps_sorted], dtype=float)
        return have, data.reshape(len(reps_sorted), len(have))

    def statistics(self, alpha: float = 0.05, configs: Sequence[ModelSpec] | None = None) -> dict[str, Any]:
        """Friedman + Dunn-Sidak + tiers on rmse_total of ``configs`` (default: the paper's
        ``methods()``); needs >= 2 methods and >= 2 runs."""
        from . import stats

        cfgs, data = self.complete_matrix(self.methods() if configs is None else configs)
        if data.shape[0] < 2 or data.shape[1] < 2:
            return {}
        fr = stats.friedman(data)
        comps = stats.multcompare(fr, alpha)
        tiers = stats.tier_list(fr.mean_ranks, comps)
        return {"configs": cfgs, "friedman": fr, "comparisons": comps, "tiers": tiers}

    @property
    def frames_unregistered(self) -> bool:
        """Whether raw measures the frames' offset rather than the tracker (`metrics.RULE`)."""
        return self.rigid is not None and frames_unregistered(self.raw, self.rigid)

    def to_json(self) -> dict[str, Any]:
        st = self.statistics()
        out: dict[str, Any] = {"raw": self.raw, "rigid": self.rigid, "frames_unregistered": self.frames_unregistered,
                               "repeats": self.repeats, "seconds": self.seconds,
                               "store": self.store, "summary": self.summary(),
                               "methods": self.summary(self.methods())}
        if st:
            names = [c.name for c in st["configs"]]
            fr = st["friedman"]
            out["friedman"] = {"statistic": fr.statistic, "p_value": fr.p_value, "df": fr.df, "n": fr.n,
                               "k": fr.k, "mean_ranks": dict(zip(names, map(float, fr.mean_ranks)))}
            out["comparisons"] = [{"method1": names[c.i], "method2": names[c.j], "lower": c.lower,
                                   "diff": c.diff, "upper": c.upper, "p_value": c.p_value}
                                  for c in st["comparisons"]]
            out["tiers"] = [[names[i] for i in t] for t in st["tiers"].tiers]
        return out

    def format(self, comparisons: bool = False, table: int | None = None, all_configs: bool = False) -> str:
        """The paper's reduction: the methods table (tables 2-4 layout; ``table`` is the
        paper's number for the title), the Friedman line, the tier list (table 5) and with
        ``comparisons`` table A1. ``all_configs`` first lists every configuration."""
        from . import tables

        text = []
        if all_configs:
            text.append(tables.format_results(self.raw, self.summary(),
                                              f"Every configuration over {self.repeats} runs (imp = raw / min)") + "\n")
        methods = self.methods()
        number = f"Table {table}" if table else "Methods"
        text.append(tables.format_results(
            self.raw, self.summary(methods),
            f"{number}: per representation the PMC and the best network per activation, {len(methods)} methods, "
            f"over {self.repeats} runs (imp = raw / min)"))
        if self.rigid is not None and self.frames_unregistered:
            text.append(self._unregistered_note(methods, self.rigid))
        st = self.statistics()
        if st:
            names = [c.name for c in st["configs"]]
            fr = st["friedman"]
            text.append(f"\nFriedman: chi2({fr.df}) = {fr.statistic:.3f}, p = {fr.p_value:.3g}, "
                        f"n = {fr.n} runs, k = {fr.k} methods")
            ov = [(names[a], names[b]) for a, b in st["tiers"].overlaps]
            text.append("\n" + ("Table 5: " if table == 4 else "") + "Dunn-Sidak tier list\n"
                        + tables.format_tiers([[names[i] for i in t] for t in st["tiers"].tiers], ov))
            if comparisons:
                text.append("\n" + ("Table A1: " if table == 4 else "") + "Dunn-Sidak multiple comparison "
                            f"(alpha 0.05, {len(st['comparisons'])} pairs)\n"
                            + tables.format_comparisons(names, st["comparisons"]))
        else:
            _, data = self.complete_matrix(methods)
            text.append(f"\nNo Friedman test{', tier list or comparisons' if comparisons else ' or tier list'}: they rank "
                        f"at least 2 methods over at least 2 runs each method has, and there "
                        f"{'is' if data.shape[1] == 1 else 'are'} {counted(data.shape[1], 'method')} over "
                        f"{counted(data.shape[0], 'such run')}")
        return "\n".join(text)

    def _unregistered_note(self, methods: Sequence[ModelSpec], rigid: Mapping[str, Any]) -> str:
        line = (f"\nThe frames are unregistered: raw rmse_pos {1e3 * self.raw['rmse_pos']:.4g} mm against "
                f"{1e3 * rigid['rmse_pos']:.4g} mm for the best rigid fit ({rigid['name']}) on the same test "
                "poses, so imp measures their offset, not the tracker.")
        scored = [row for row in self.summary(methods) if row.get("rmse_total")]
        if scored:
            best = min(scored, key=lambda row: row["rmse_total"]["min"])
            ratio = rigid["rmse_total"] / best["rmse_total"]["min"]
            than = f"{ratio:.3g}x lower" if ratio >= 1 else f"{1 / ratio:.3g}x higher"
            line += (f" The best method, {best['name']}, reaches rmse_total {best['rmse_total']['min']:.4g}: {than} "
                     f"than the rigid fit's {rigid['rmse_total']:.4g}.")
        return line


def best_rigid_on_test(table: Any, seed: int = 0, with_rotation: bool = True) -> dict[str, Any]:
    """The best of the rigid fits `fit` scores as its floor, fitted as `fit` fits them
    (`pipeline.out_of_fold`) on the poses the protocol's split does not test and scored on its
    test poses: {"name", "rmse_pos", "rmse_rot", "rmse_total"}. Where raw measures
    unregistered frames, this is what a correction must beat."""
    from .pipeline import _best, _priors, out_of_fold, rigid_candidates, session_setup

    train, val, test = split_indices(table.n, seed, 0)
    fitted_on = np.union1d(train, val)
    floor = rigid_candidates(table)
    arrays, setup = (table.measured, table.reference, table.time()), session_setup(table)
    with_rot = setup.with_rotation
    predicted = out_of_fold(floor, np.arange(table.n), arrays, setup, [(fitted_on, test)],
                            _priors(floor, fitted_on, arrays, setup))
    metrics = {c.name: pose_metrics(table.reference[test], predicted[c.name][test], with_rotation and with_rot)
               for c in floor}
    best = _best(floor, {name: m["rmse_total"] for name, m in metrics.items()})
    return {"name": best.name, **metrics[best.name]}


def _load_store(path: Path, fingerprint: str, seed: int) -> dict[tuple[str, int], dict[str, Any]]:
    done: dict[tuple[str, int], dict[str, Any]] = {}
    handle = open_sidecar(path)
    if handle is None:
        return done
    unread: list[int] = []
    others = 0          # runs of another table or seed: kept, not resumed
    with handle:
        for number, raw in enumerate(handle, 1):
            line = raw.decode("utf-8", errors="replace").strip()
            if not line:
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                row = None
            if not (isinstance(row, dict) and "key" in row and "repeat" in row):
                # the last line torn by an interruption is moved aside at the next append;
                # any other is said, and stays as it is
                if raw.endswith(b"\n"):
                    unread.append(number)
                continue
            if row.get("data") == fingerprint and row.get("seed") == seed:
                done[(row["key"], int(row["repeat"]))] = row
            else:
                others += 1
    if unread:
        warn(f"{path}: {'line' if len(unread) == 1 else 'lines'} {first_few(unread, 5)} {'is' if len(unread) == 1 else 'are'} "
             "no sweep result (not a JSON row with a key and a repeat): left as they are and not read; a run "
             "they held is done again")
    if others:
        warn(f"{path}: holds {others} {'run' if others == 1 else 'runs'} of another table or seed: kept as they are, "
             "not resumed; this sweep's runs are added beside them")
    return done


def _worker_init(threads: int, parent: int) -> None:
    """Pool worker set-up: its torch threads, and no life of its own.

    Ctrl-C reaches the whole process group; the parent alone decides (it stops the pool),
    so workers ignore SIGINT and take SIGTERM's default. A worker whose parent died, even
    by kill -9, exits: Linux delivers SIGKILL on the parent's death (PR_SET_PDEATHSIG),
    elsewhere a thread watches the parent id.
    """
    import signal
    import threading

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if not _die_with_parent():
        def watch() -> None:
            while os.getppid() == parent:
                time.sleep(0.5)
            os._exit(1)

        threading.Thread(target=watch, daemon=True).start()
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)
    try:
        import torch

        torch.set_num_threads(threads)
    except ImportError:
        pass


def _die_with_parent() -> bool:
    import ctypes
    import signal
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(1, int(signal.SIGKILL), 0, 0, 0) == 0  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return False


def _run_in_worker(table: Any, config: ModelSpec, repeat: int, seed: int, threads: int) -> dict[str, Any]:
    """`run_one` in a pool worker; an exception that cannot be pickled would break the whole
    pool, so it crosses as a RuntimeError with the same message instead."""
    import pickle

    try:
        return run_one(table, config, repeat, seed, threads)
    except Exception as exc:
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:
            raise RuntimeError(f"{config.key}, repeat {repeat}: {type(exc).__name__}: {exc}") from None
        raise


def _stop_pool(pool: Any) -> None:
    """Cancel what has not started and end the workers now (a run in progress is lost,
    the finished ones are already in the store)."""
    # The executor has no public way to stop busy workers; its process table (emptied by
    # shutdown, so read first) is the only handle.
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes:
        if proc.is_alive():
            proc.terminate()
    for proc in processes:
        proc.join(timeout=5)
        if proc.is_alive():
            proc.kill()


def run_sweep(table: Any, configs: Sequence[ModelSpec], repeats: int = 30, store: str | os.PathLike | None = None,
              workers: int = 2, ray_address: str | None = None, seed: int = 0, progress: bool = True,
              threads: int | None = None) -> SweepResult:
    """Run every configuration ``repeats`` times (see the module docstring).

    ``store``: JSON-lines file; rows already in it (same data fingerprint and seed) are
    reused, new ones appended as they finish. ``workers``: local processes (1 = in this
    process). ``ray_address``: run on a Ray cluster instead (its head's "host:port", "auto" for
    the cluster this machine belongs to, "ray://host:port" through Ray Client, or "local").
    ``threads``: torch / BLAS threads per worker process (default ``default_threads(workers)``).
    """
    configs = list(configs)
    ray = _check_sweep(table, configs, ray_address)
    fingerprint = table_fingerprint(table)
    store_path, done = _open_store(store, fingerprint, seed)
    todo = [(c, r) for c in configs for r in range(repeats) if (c.key, r) not in done]
    rows = [done[(c.key, r)] for c in configs for r in range(repeats) if (c.key, r) in done]
    _, _, test = split_indices(table.n, seed, 0)
    with_rot = all(c.with_rotation for c in configs) and table.has_orientation
    raw = pose_metrics(table.reference[test], table.measured[test], with_rot)
    rigid = best_rigid_on_test(table, seed, with_rot)

    record = _Recorder(rows, fingerprint, store_path,
                       _progress_bar(len(configs) * repeats, len(rows)) if progress else None)
    t0 = time.perf_counter()
    # longest jobs first keeps the pool busy at the end
    todo.sort(key=lambda cr: -_cost(cr[0]))
    if ray_address is not None and todo:
        _sweep_on_ray(ray, ray_address, table, todo, seed, record)
    elif workers <= 1 or len(todo) <= 1:
        for c, r in todo:
            record(run_one(table, c, r, seed))
    else:
        _sweep_on_pool(table, todo, seed, workers, threads, record)
    record.close()
    order = {c.key: i for i, c in enumerate(configs)}
    rows.sort(key=lambda r: (order.get(r["key"], 1 << 30), r["repeat"]))
    return SweepResult(configs, rows, raw, repeats, time.perf_counter() - t0,
                       str(store_path) if store_path else None, rigid)


def _check_sweep(table: Any, configs: list[ModelSpec], ray_address: str | None) -> Any:
    """Refuse a grid or table the sweep cannot run; return the ray module when Ray is asked for."""
    keys = [c.key for c in configs]
    if len(set(keys)) != len(keys):
        raise ValueError("duplicate configurations in the grid")
    from posecorr.data import require_rows

    from .pipeline import check_outliers

    require_rows(table, 10, "the sweep's train/validation/test split", outliers=check_outliers)
    ray = None
    if ray_address is not None:
        try:
            import ray  # optional dependency
        except ImportError:
            raise ModuleNotFoundError("--ray needs the ray package (pip install 'posecorr[ray]')",
                                      name="ray") from None
        _probe_ray_head(ray_address)
    _require_training_rows(table.n, configs)
    return ray


# Seconds a head's port has to accept a connection: Ray's own client retries for minutes,
# printing only its log, where nothing listens.
RAY_PROBE_S = 5.0


def _probe_ray_head(address: str) -> None:
    """ConnectionError in one line where HOST:PORT (or ray://HOST:PORT) accepts no connection
    or "auto" finds no cluster; other addresses ("local") are Ray's to resolve."""
    import re
    import socket

    given = address
    if address == "auto":
        address = _find_ray_cluster() or address
    found = re.fullmatch(r"(?:ray://)?\[?([^\[\]/]+?)\]?:(\d+)", address)
    if found is None:
        return
    host, port = found.group(1), int(found.group(2))
    try:
        socket.create_connection((host, port), timeout=RAY_PROBE_S).close()
    except OSError as exc:
        reason = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or type(exc).__name__)
        raise ConnectionError(f"--ray {given}: nothing answers at {host}:{port} ({reason}): start the head there "
                              f"(ray start --head --port {port}) or give its address") from None


def _find_ray_cluster() -> str | None:
    """The address `--ray auto` resolves to, to be probed as HOST:PORT is (a stale address a
    dead head left is found but does not answer); ConnectionError in one line where it finds
    no cluster: Ray's own error names an --address flag posecorr does not have. Looked up as
    ray.init will (RAY_ADDRESS, the address the last `ray start` left, a GCS among the
    processes) by the function it calls, which is Ray's private one: where a Ray release
    moves it, None, and Ray resolves "auto" itself."""
    try:
        from ray._private.services import canonicalize_bootstrap_address
    except ImportError:
        return None
    try:
        return canonicalize_bootstrap_address("auto")
    except ConnectionError:
        raise ConnectionError("--ray auto: no Ray cluster is running on this machine and RAY_ADDRESS is unset: "
                              "start one (ray start --head) or give its head's address (--ray HOST:PORT)") from None


def _require_training_rows(n: int, configs: Sequence[ModelSpec]) -> None:
    """ValueError, before any run, where the protocol's split leaves a configuration fewer
    training poses than it takes, naming them and the rows they would need."""
    def training(rows: int) -> int:
        return len(split_indices(rows)[0])

    needs = {c.key: c.make(seed=0).min_rows() for c in configs}
    short = {key: k for key, k in needs.items() if k > training(n)}
    if not short:
        return
    most = max(short.values())
    rows = next(m for m in itertools.count(n + 1) if training(m) >= most)
    named = first_few([f"{key} {k}" for key, k in sorted(short.items(), key=lambda kv: (-kv[1], kv[0]))], 4)
    raise ValueError(f"{n} rows: the sweep's split trains on {training(n)} of them, and {len(short)} of its "
                     f"{len(configs)} configurations need more ({named} poses): at least {rows} rows, or a "
                     "grid without them; on a session this size `posecorr fit --cv loo` scores a model on every pose")


def _open_store(store: str | os.PathLike | None, fingerprint: str,
                seed: int) -> tuple[Path | None, dict[tuple[str, int], dict[str, Any]]]:
    """Return the store's path and the rows it already holds for this data and seed."""
    store_path = Path(store) if store is not None else None
    done = _load_store(store_path, fingerprint, seed) if store_path else {}
    if store_path:
        store_path.parent.mkdir(parents=True, exist_ok=True)
        # Open it for appending now: an unwritable store fails before hours of training, not after.
        with open_sidecar(store_path, append=True):
            pass
    return store_path, done


def _progress_bar(total: int, initial: int) -> Any:
    """Progress over the sweep's runs, starting at those the store already holds: a tqdm bar on
    a terminal (or a notebook), plain lines where stderr goes to a log or a pipe."""
    import sys

    if sys.stderr.isatty() or "ipykernel" in sys.modules:
        from tqdm.auto import tqdm

        return tqdm(total=total, initial=initial, unit="run", desc="sweep")
    return _ProgressLines(total, initial)


class _ProgressLines:
    """The bar's content as whole lines, for a log: a bar redraws itself with carriage returns,
    which a file keeps as one ever longer line. One line at most every ``every`` seconds, and
    the last."""

    def __init__(self, total: int, initial: int, every: float = 30.0) -> None:
        self.total, self.initial, self.n, self.every = total, initial, initial, every
        self.postfix = ""
        self.start = self.last = time.monotonic()

    def set_postfix_str(self, text: str, refresh: bool = True) -> None:
        self.postfix = text

    def update(self, n: int = 1) -> None:
        self.n += n
        if time.monotonic() - self.last >= self.every:
            self._print()

    def close(self) -> None:
        self._print()

    def _print(self) -> None:
        import sys

        self.last = time.monotonic()
        elapsed = self.last - self.start
        line = f"sweep: {self.n}/{self.total} runs, {elapsed:.0f} s"
        if self.total > self.n > self.initial:
            line += f", about {elapsed / (self.n - self.initial) * (self.total - self.n):.0f} s left"
        print(f"{line}, {self.postfix}" if self.postfix else line, file=sys.stderr, flush=True)


class _Recorder:
    """Takes each finished run: stamps its data, keeps it, appends it to the store, moves the bar."""

    def __init__(self, rows: list[dict[str, Any]], fingerprint: str, store_path: Path | None,
                 bar: Any) -> None:
        self.rows, self.fingerprint, self.store_path, self.bar = rows, fingerprint, store_path, bar
        self.best: tuple[float, str] = (math.inf, "")
        for row in rows:
            self._keep_best(row)

    def __call__(self, row: dict[str, Any]) -> None:
        row["data"] = self.fingerprint
        self.rows.append(row)
        if self.store_path:
            append_line(self.store_path, json.dumps(row))
        self._keep_best(row)
        if self.bar is not None:
            self.bar.update(1)

    def _keep_best(self, row: dict[str, Any]) -> None:
        if row["rmse_total"] < self.best[0]:
            self.best = (row["rmse_total"], row["key"])
            if self.bar is not None:
                self.bar.set_postfix_str(f"best {self.best[0]:.4g} {self.best[1]}", refresh=False)

    def close(self) -> None:
        """Close the progress bar, if any."""
        if self.bar is not None:
            self.bar.close()


def _sweep_on_pool(table: Any, todo: list[tuple[ModelSpec, int]], seed: int, workers: int,
                   threads: int | None, record: _Recorder) -> None:
    """Run ``todo`` on a local process pool, recording each run as it finishes."""
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool
    import multiprocessing as mp

    from posecorr.threads import default_threads

    threads = threads or default_threads(workers)
    # fork, where there is one: a script that calls run_sweep needs no `if __name__ ==
    # "__main__":` guard (spawn and forkserver import the main script in every worker).
    method = "spawn" if os.name == "nt" else "fork"
    if method == "fork":
        threads = _threads_a_fork_keeps(threads)
    ctx = mp.get_context(method)
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init,
                               initargs=(threads, os.getpid()))
    futures: list[Any] = []
    recorded: set[Any] = set()
    try:
        with sigterm_as_interrupt():
            futures = [pool.submit(_run_in_worker, table, c, r, seed, threads) for c, r in todo]
            for fut in as_completed(futures):
                row = fut.result()
                recorded.add(fut)
                record(row)
    except BaseException as exc:
        # Interrupted (Ctrl-C, SIGTERM) or a run failed: keep every run that finished.
        for fut in futures:
            if fut not in recorded and fut.done() and not fut.cancelled() and fut.exception() is None:
                record(fut.result())
        _stop_pool(pool)
        record.close()
        if isinstance(exc, BrokenProcessPool):
            raise SweepWorkerError("a sweep worker died before its run ended (killed, or out of memory); the runs "
                                   "that finished are kept") from None
        raise
    pool.shutdown(wait=True)


# How long a forked probe may take to run torch on several threads before it counts as hung:
# a healthy one takes milliseconds, a loaded machine a few hundred.
FORK_PROBE_SECONDS = 3.0


def _threads_a_fork_keeps(threads: int) -> int:
    """``threads``, or 1 where a forked worker would hang on more.

    GNU OpenMP (torch's intra-op pool on Linux) does not survive a fork: once the parent has
    run torch on several threads, a forked child that asks for more than one waits forever on
    the parent's pool threads, which it does not have. Whether the parent has is not visible
    from Python, so a forked probe tries: it runs torch on ``threads`` threads, and where it
    does not finish the workers run on one thread each, and the user is told.
    """
    import signal
    import sys

    if threads <= 1 or "torch" not in sys.modules:
        return threads  # a parent without torch has no OpenMP pool for a child to inherit
    pid = os.fork()
    if pid == 0:  # the probe: torch's parallel loop and its BLAS, as a run uses them
        code = 1
        try:
            import torch

            torch.set_num_threads(threads)
            square = torch.ones(256, 256)
            torch.tanh(torch.ones(1 << 20)).sum().item()
            (square @ square).sum().item()
            code = 0
        finally:
            os._exit(code)
    deadline = time.monotonic() + FORK_PROBE_SECONDS
    status = None
    while status is None and time.monotonic() < deadline:
        done, raw = os.waitpid(pid, os.WNOHANG)
        status = os.waitstatus_to_exitcode(raw) if done else None
        if status is None:
            time.sleep(0.005)
    if status is None:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    if status == 0:
        return threads
    warn(f"sweep workers run 1 torch thread each, not {threads}: this process has run torch on several threads, "
         "and a worker forked from it hangs on more than one (GNU OpenMP does not survive a fork); "
         "run the sweep from a fresh process (`posecorr sweep`) for more")
    return 1


class SweepWorkerError(RuntimeError):
    """A local worker process could not run or died: the cause is outside the data (one line
    from the CLI)."""


# A run lost with its node (the node died, its worker was killed) is retried on the nodes left;
# a run that raises is not (its error would only repeat) and fails the sweep.
RAY_RETRIES = 3


def _sweep_on_ray(ray: Any, address: str, table: Any, todo: list[tuple[ModelSpec, int]], seed: int,
                  record: Any) -> None:
    """Run ``todo`` as Ray tasks of one CPU each and ``record`` every row as it returns.

    On a failed run or an interrupt the runs already finished are recorded before the error
    goes on; a connection opened here is closed on the way out, which ends the sweep's tasks
    still on the cluster."""
    opened = not ray.is_initialized()
    ray.init(address=address, ignore_reinit_error=True)
    try:
        remote = ray.remote(num_cpus=1, max_retries=RAY_RETRIES)(_run_on_node)
        table_ref = ray.put(table)
        pending = [remote.remote(table_ref, c, r, seed) for c, r in todo]
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                record(ray.get(ready[0]))
        except BaseException:
            for ref in ray.wait(pending, num_returns=len(pending), timeout=0)[0] if pending else []:
                try:
                    record(ray.get(ref))
                except Exception:
                    pass  # the error being raised already names a failed run
            raise
    finally:
        if opened:
            ray.shutdown()


def _run_on_node(table: Any, config: ModelSpec, repeat: int, seed: int) -> dict[str, Any]:
    """`run_one` as a Ray task: one torch thread (the task holds one CPU), and the id of the
    node that ran it in the row."""
    import ray

    row = run_one(table, config, repeat, seed, threads=1)
    row["node"] = ray.get_runtime_context().get_node_id()
    return row


def _cost(cfg: ModelSpec) -> float:
    if not cfg.is_network:
        return 0.0
    sizes = [9, *cfg.hidden, 9]
    params = sum((a + 1) * b for a, b in zip(sizes[:-1], sizes[1:]))
    return float(params) ** 2 * (2.0 if TRAINERS.lookup(cfg.trainer).bayesian else 1.0)
