"""A correction pipeline: the physics stage, then a data-driven core on what it leaves.

`CorrectionPipeline(effects=("station", "mount"), core=PMC("zhou"))` fits the effects by
nonlinear least squares (`physics.PhysicsModel`), then the core (PMC or MLP, or none) on
the physics-corrected poses. Its `forward` composes both, so one ONNX graph holds the
physics stage in front of the core.

Cross-validation leaves out whole poses (`kfold_indices`: K folds or leave-one-out), and
`--method auto` (`select_auto`) picks by cross-validated rmse_total among no core,
ridge-PMC on each representation and a small MLP, never returning a model whose
cross-validated error is worse than the physics stage alone.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from posecorr.data import PoseTable
from posecorr.metrics import pose_errors, pose_metrics, rmse_total

from .physics import PhysicsModel


class CorrectionPipeline:
    """Physics stage (may be empty) followed by a core corrector (may be None)."""

    def __init__(self, effects: Sequence[str] = (), core: Any = None, sigma_p: float | None = None,
                 sigma_r: float | None = None) -> None:
        self.effects = effects
        self.core = core
        self.sigma_p = sigma_p
        self.sigma_r = sigma_r

    @property
    def representation(self) -> str:
        if self.core is not None:
            return self.core.representation
        return "pos" if not getattr(self, "with_rotation_", True) else "R"

    def fit(self, measured: np.ndarray, reference: np.ndarray, t: np.ndarray | None = None,
            with_rotation: bool = True, warm_start: dict[str, np.ndarray] | None = None,
            validation: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None) -> "CorrectionPipeline":
        """Fit the physics stage, then the core on what it leaves.

        validation: (measured, reference, t) poses for an MLP core's early stopping (trainlm).
        """
        self.with_rotation_ = with_rotation
        self.physics_ = None
        stage = np.asarray(measured, float)
        if self.effects:
            self.physics_ = PhysicsModel(self.effects, self.sigma_p, self.sigma_r).fit(
                measured, reference, t=t, with_rotation=with_rotation, warm_start=warm_start)
            stage = self.physics_.predict(measured, t)
        if self.core is not None:
            extra = {}
            if validation is not None and getattr(self.core, "method", "") == "mlp":
                val_measured, val_reference, val_t = validation
                extra["validation"] = (self.predict_physics(val_measured, val_t), val_reference)
            self.core.fit(stage, reference, **extra)
        self.n_features_in_ = 7
        return self

    def predict_physics(self, measured: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
        """The poses after the physics stage only."""
        return np.asarray(measured, float) if self.physics_ is None else self.physics_.predict(measured, t)

    def forward(self, pose: Any, t: Any = None) -> Any:
        out = pose if self.physics_ is None else self.physics_.forward(pose, t)
        return out if self.core is None else self.core.forward(out)

    def predict(self, measured: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
        if not hasattr(self, "n_features_in_"):
            raise RuntimeError("this CorrectionPipeline is not fitted yet: call fit first")
        stage = self.predict_physics(measured, t)
        return stage if self.core is None else self.core.predict(stage)

    def score(self, measured: np.ndarray, reference: np.ndarray, t: np.ndarray | None = None) -> float:
        """-rmse_total of the corrected poses (higher is better)."""
        return -pose_metrics(reference, self.predict(measured, t), self.with_rotation_)["rmse_total"]

    def export_info(self) -> dict[str, Any]:
        info: dict[str, Any] = {"method": "none", "representation": self.representation}
        if self.core is not None:
            info.update(self.core.export_info())
        if self.physics_ is not None:
            info["effects"] = list(self.physics_.params_)
            info["effect_params"] = self.physics_.describe()
            if "drift" in self.physics_.params_:
                info["drift"] = "fitted; not applied in the exported graph (no time input)"
            if self.core is None:
                info["method"] = "physics"
        return info

    def to_onnx(self, path: Any, **metadata: Any) -> Any:
        from posecorr.export import to_onnx

        return to_onnx(self, path, **metadata)


# --- cross-validation ------------------------------------------------------------------

def kfold_indices(n: int, folds: int | str, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """(train, held-out) index pairs leaving out whole poses: K random folds, or "loo"."""
    if folds == "loo":
        k = n
    else:
        k = int(folds)
        if k < 2:
            raise ValueError(f"cross-validation needs at least 2 folds, got {k}")
        if k > n:
            raise ValueError(f"{k} folds need at least {k} poses, got {n}")
    order = np.random.default_rng(seed).permutation(n) if folds != "loo" else np.arange(n)
    parts = np.array_split(order, k)
    return [(np.sort(np.concatenate(parts[:i] + parts[i + 1:])), np.sort(parts[i])) for i in range(k)]


@dataclass
class CrossValidation:
    """Out-of-fold predictions (every pose predicted by a model that never saw it)."""

    predicted: np.ndarray                      # (N, 7)
    fold_of: np.ndarray                        # (N,) fold index of each pose
    fold_rmse: np.ndarray                      # (K,) held-out rmse_total per fold
    metrics: dict[str, float | None] = field(default_factory=dict)
    fitted: list[Any] = field(default_factory=list)


def cross_validate(make: Callable[[], Any], table: PoseTable, folds: int | str = 5, seed: int = 0,
                   fit_kwargs: Callable[[int], dict] | None = None) -> CrossValidation:
    """Fit `make()` on each training part and predict the held-out poses."""
    measured, reference, t = table.measured, table.reference, table.time()
    predicted = np.empty_like(measured)
    fold_of = np.empty(table.n, dtype=int)
    fold_rmse, fitted = [], []
    for k, (train, held) in enumerate(kfold_indices(table.n, folds, seed)):
        model = make()
        extra = fit_kwargs(k) if fit_kwargs else {}
        model.fit(measured[train], reference[train], t=None if t is None else t[train],
                  with_rotation=table.has_orientation, **extra)
        predicted[held] = model.predict(measured[held], None if t is None else t[held])
        fold_of[held] = k
        dp, dr = pose_errors(reference[held], predicted[held], table.has_orientation)
        fold_rmse.append(rmse_total(dp, dr))
        fitted.append(model)
    return CrossValidation(predicted, fold_of, np.asarray(fold_rmse),
                           pose_metrics(reference, predicted, table.has_orientation), fitted)


def select_auto(table: PoseTable, effects: Sequence[str], folds: int | str = 5, seed: int = 0,
                candidates: dict[str, Callable[[], Any]] | None = None,
                progress: Callable[[str], None] | None = None) -> tuple[str, CrossValidation, dict[str, float]]:
    """The core with the lowest cross-validated rmse_total ("none" when nothing beats the physics stage).

    Returns (chosen name, its cross-validation, {name: cv rmse_total} of every candidate).
    """
    if candidates is None:
        candidates = default_auto_candidates(table)
    scores: dict[str, float] = {}
    results: dict[str, CrossValidation] = {}
    for name, make_core in candidates.items():
        if progress:
            progress(name)
        cv = cross_validate(lambda: CorrectionPipeline(effects, make_core()), table, folds, seed)
        scores[name], results[name] = float(cv.metrics["rmse_total"]), cv
    best = min(scores, key=lambda n: (scores[n], n != "none"))
    return best, results[best], scores


def default_auto_candidates(table: PoseTable) -> dict[str, Callable[[], Any]]:
    """none, ridge-PMC on each representation (position only for position-only data), a small MLP."""
    from .mlp import MLP
    from .pmc import PMC

    reps = ("eaa", "quat", "R", "zhou") if table.has_orientation else ("pos",)
    out: dict[str, Callable[[], Any]] = {"none": lambda: None}
    for rep in reps:
        out[f"pmc-{rep}"] = lambda rep=rep: PMC(representation=rep, alpha="cv")
    rep = "zhou" if table.has_orientation else "pos"
    out[f"mlp-{rep}-tansig-5-br"] = lambda: MLP(representation=rep, hidden=(5,), activation="tansig",
                                                trainer="br", epochs=200, random_state=0)
    return out


def make_core(method: str, representation: str, hidden: Sequence[int] = (20, 20, 20, 20),
              activation: str = "tansig", trainer: str = "br", epochs: int = 1000, seed: int = 0) -> Any:
    """The data-driven stage of `fit --method`: None, PMC or MLP."""
    if method == "none":
        return None
    if method == "pmc":
        from .pmc import PMC

        return PMC(representation=representation, alpha="cv")
    if method == "mlp":
        from .mlp import MLP

        return MLP(representation=representation, hidden=tuple(hidden), activation=activation, trainer=trainer,
                   epochs=epochs, random_state=seed)
    raise ValueError(f"unknown method {method!r}; expected none, pmc, mlp or auto")


@dataclass
class FitReport:
    """What `posecorr fit` learned: the model to export and its held-out evaluation."""

    model: CorrectionPipeline
    raw: dict[str, float | None]
    heldout: dict[str, float | None]
    heldout_kind: str                      # "test" (fixed split) or "cv"
    train_index: np.ndarray
    chosen: str
    auto_scores: dict[str, float] = field(default_factory=dict)


def fit_table(table: PoseTable, effects: Sequence[str] = (), method: str = "pmc", representation: str = "zhou",
              hidden: Sequence[int] = (20, 20, 20, 20), activation: str = "tansig", trainer: str = "br",
              epochs: int = 1000, cv: int | str | None = None, seed: int = 0,
              progress: Callable[[str], None] | None = None) -> FitReport:
    """Fit a pipeline on a table and evaluate it on held-out poses.

    cv None: the protocol's fixed 15 % test split (seeded); the model is fitted on the rest
    (an MLP core early-stops on 15 % validation poses of it). cv K or "loo": K-fold or
    leave-one-out cross-validation of the whole pipeline, then the model is refitted on
    all poses. method "auto" chooses the core by cross-validation (K = cv, or 5).
    """
    from posecorr.data import require_rows
    from posecorr.metrics import metric_block

    from .protocol import split_indices

    require_rows(table, 10 if cv is None else 4,
                 "a fit with a held-out test split" if cv is None else "a cross-validated fit")
    if not table.has_orientation:
        representation = "pos"
    say = progress or (lambda message: None)
    chosen, scores = method, {}
    if method == "auto":
        folds = cv if cv is not None else (5 if table.n >= 25 else "loo")
        candidates = default_auto_candidates(table)
        chosen, _, scores = select_auto(table, effects, folds, seed, candidates,
                                        progress=lambda name: say(f"auto: cross-validating {name}"))
        make = lambda: CorrectionPipeline(effects, candidates[chosen]())  # noqa: E731
    else:
        make = lambda: CorrectionPipeline(effects, make_core(method, representation, hidden, activation,  # noqa: E731
                                                             trainer, epochs, seed))
    M, R, t = table.measured, table.reference, table.time()
    with_rotation = table.has_orientation
    if cv is None:
        train, val, test = split_indices(table.n, seed)
        fit_rows = np.sort(np.concatenate([train, val]))
        say(f"fitting on {len(fit_rows)} poses, testing on {len(test)}")
        model = make()
        validation = (M[val], R[val], None if t is None else t[val])
        if getattr(model.core, "method", "") == "mlp":
            fit_rows = train
        model.fit(M[fit_rows], R[fit_rows], t=None if t is None else t[fit_rows], with_rotation=with_rotation,
                  validation=validation)
        raw = pose_metrics(R[test], M[test], with_rotation)
        corrected = pose_metrics(R[test], model.predict(M[test], None if t is None else t[test]), with_rotation)
        return FitReport(model, raw, metric_block(raw, corrected), "test", fit_rows, chosen, scores)
    say(f"cross-validating ({cv} folds)" if cv != "loo" else "cross-validating (leave one out)")
    result = cross_validate(make, table, cv, seed)
    raw = pose_metrics(R, M, with_rotation)
    say(f"fitting on all {table.n} poses")
    model = make().fit(M, R, t=t, with_rotation=with_rotation)
    return FitReport(model, raw, metric_block(raw, result.metrics), "cv", np.arange(table.n), chosen, scores)


__all__ = ["make_core", "FitReport", "fit_table", "CorrectionPipeline", "kfold_indices", "cross_validate", "CrossValidation", "select_auto",
           "default_auto_candidates"]
