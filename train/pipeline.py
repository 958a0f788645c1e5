"""A correction pipeline: the physics stage, then a data-driven core on what it leaves.

`CorrectionPipeline(effects=("station", "mount"), core=PMC("zhou"))` fits the effects by
nonlinear least squares (`physics.PhysicsModel`), then the core (PMC or MLP, or none) on
the physics-corrected poses. Its `forward` composes both, so one ONNX graph holds the
physics stage in front of the core.

Cross-validation leaves out whole poses (the plans of `splits`: K folds or leave-one-out).
`fit_table` is what `posecorr fit` runs: it scores the requested model (a `spec.ModelSpec`,
or for the method "auto" a nested choice among `auto_candidates`) on held-out poses beside
the plain rigid fits (`physics.RigidModel`, every variant of `identify.RIGID_VARIANTS`) on
the same poses, and returns the best rigid fit when the richer model does not beat it.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
from sklearn.base import BaseEstimator, clone
from sklearn.exceptions import NotFittedError

from posecorr.data import PoseTable
from posecorr.metrics import metric_block, pose_errors, pose_metrics, rmse_total
from posecorr.registration import orientation_notes
from posecorr.rotations import POSITION_ONLY
from posecorr.textui import percent

from .base import (PoseRegressorMixin, Validation, as_validation, check_pair, check_poses, check_times, decode_pose,
                   keeps_last_fit, vector_size)
from .folds import IN_PROCESS, FoldPool
from .identify import describe_spread, rigid_variants
from .physics import PhysicsModel, RigidModel
from .spec import SESSION_EPOCHS, SESSION_HIDDEN, ModelSpec, spec_from_options
from .splits import (MIN_TEST_SPLIT, CrossValidationPlan, FixedSplit, HeldOut, KFold, Plan, fewest_to_fit,
                     plan_for, require_enough_to_fit)


class SessionSetup(NamedTuple):
    """What a session fixes of every model fitted on it, as `PhysicsModel` parameters: whether
    its reference has orientations, and where its base station stood (`PoseTable.station_pose`)."""

    with_rotation: bool = True
    station_pose: str | None = None

    def params_for(self, estimator: Any) -> dict[str, Any]:
        """The settings `estimator` takes (a rigid fit has no station)."""
        return {k: v for k, v in self._asdict().items() if k in estimator.get_params(deep=False)}


def session_setup(table: PoseTable) -> SessionSetup:
    return SessionSetup(table.has_orientation, table.station_pose)


class CorrectionPipeline(PoseRegressorMixin, BaseEstimator):
    """Physics stage (may be empty) followed by a core corrector (may be None).

    scikit-learn conventions: the parameters (`effects`, `core`, `sigma_p`, `sigma_r`,
    `rigid` (a variant of `identify.RIGID_VARIANTS`, or "" for none), `with_rotation`,
    `prior_strength` (the physics stage's, `PhysicsModel`)) are never changed by fit; the fitted parts are `physics_` and
    `core_`, a clone of `core` (so `clone(pipeline)` and nested parameters such as
    `core__alpha` work). `with_rotation` False for a position-only table, `station_pose` where
    the base station stood (both `PhysicsModel`'s).
    """

    def __init__(self, effects: Sequence[str] = (), core: Any = None, sigma_p: float | None = None,
                 sigma_r: float | None = None, rigid: str = "", with_rotation: bool = True,
                 prior_strength: float = 0.0, station_pose: str | None = None) -> None:
        self.effects = effects
        self.core = core
        self.sigma_p = sigma_p
        self.sigma_r = sigma_r
        self.rigid = rigid
        self.with_rotation = with_rotation
        self.prior_strength = prior_strength
        self.station_pose = station_pose

    @property
    def representation(self) -> str:
        if self.core is not None:
            return self.core.representation
        return "R" if getattr(self, "with_rotation_", bool(self.with_rotation)) else POSITION_ONLY

    @keeps_last_fit
    def fit(self, measured: np.ndarray, reference: np.ndarray, t: np.ndarray | None = None,
            validation: Validation | None = None, *, warm_start: Any = None,
            physics: PhysicsModel | None = None) -> "CorrectionPipeline":
        """Fit the physics stage (the rigid registration when `rigid`), then the core on what it leaves.

        validation: held-out poses (`Validation`) for the core's early stopping (an MLP's trainlm).
        warm_start: {effect: theta} or a fitted PhysicsModel to start from (`PhysicsModel.fit`).
        physics: a physics stage already fitted on these very poses (shared by candidates that
        differ only in their core), used as it is.
        """
        measured, reference = check_pair(measured, reference)
        t = check_times(t, len(measured))
        if self.rigid and self.effects:
            raise ValueError("a rigid pipeline has no further effects; give either a rigid variant or effects")
        with_rotation = bool(self.with_rotation)
        if physics is None and self.rigid:
            physics = RigidModel(with_rotation, self.rigid).fit(measured, reference, t=t, warm_start=warm_start)
        elif physics is None and self.effects:
            physics = PhysicsModel(self.effects, self.sigma_p, self.sigma_r, with_rotation=with_rotation,
                                   prior_strength=self.prior_strength, station_pose=self.station_pose).fit(
                measured, reference, t=t, warm_start=warm_start)
        core = None if self.core is None else clone(self.core)
        if core is not None:
            stage = measured if physics is None else physics.predict(measured, t)
            validation = as_validation(validation)
            if validation is not None:   # the core sees the held-out poses as the physics stage leaves them
                held = (check_poses(validation.measured, "validation measured") if physics is None
                        else physics.predict(validation.measured, validation.t))
                validation = Validation(held, validation.reference)
            core.fit(stage, reference, validation=validation)
        self.with_rotation_, self.physics_, self.core_ = with_rotation, physics, core
        self.n_features_in_ = 7
        return self

    def predict_physics(self, measured: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
        """The poses after the physics stage only."""
        return check_poses(measured, "measured") if self.physics_ is None else self.physics_.predict(measured, t)

    def _check_fitted(self) -> None:
        if not hasattr(self, "n_features_in_"):
            raise NotFittedError("this CorrectionPipeline is not fitted yet: call fit first")

    def forward(self, pose: Any, t: Any = None) -> Any:
        self._check_fitted()
        if self.physics_ is None and self.core_ is None:
            return decode_pose(pose[..., 0:3], pose, POSITION_ONLY)   # the contract's output, passed through
        out = pose if self.physics_ is None else self.physics_.forward(pose, t)
        return out if self.core_ is None else self.core_.forward(out)

    def predict(self, measured: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
        self._check_fitted()
        if self.physics_ is None and self.core_ is None:
            return self.forward(check_poses(measured, "measured"))
        return self.predict_core(self.predict_physics(measured, t))

    def predict_core(self, stage: np.ndarray) -> np.ndarray:
        """The poses the physics stage left (`predict_physics`) through the core."""
        self._check_fitted()
        return stage if self.core_ is None else self.core_.predict(stage)

    def score(self, measured: np.ndarray, reference: np.ndarray, t: np.ndarray | None = None) -> float:
        """-rmse_total of the corrected poses (higher is better)."""
        self._check_fitted()
        measured, reference = check_pair(measured, reference)
        return -pose_metrics(reference, self.predict(measured, t), self.with_rotation_)["rmse_total"]

    def export_info(self) -> dict[str, Any]:
        self._check_fitted()
        # the representation is the core's input: a model without a core has none
        info: dict[str, Any] = {"method": "none", "representation": None}
        if self.core_ is not None:
            info.update(self.core_.export_info())
        if self.physics_ is not None:
            info["effects"] = list(self.physics_.params_)
            info["effect_params"] = self.physics_.describe()
            behaviours = self.physics_.user_behaviours()
            if behaviours:
                info["effect_behaviour"] = behaviours
            if self.core_ is None:
                info["method"] = "rigid" if self.rigid else "physics"
            if self.rigid:
                info["rigid_variant"] = self.rigid
            if self.physics_.fixed_:
                info["fixed"] = dict(self.physics_.fixed_)
            if self.physics_.station_pose is not None:
                info["station_pose"] = self.physics_.station_placed()
            if not self.rigid:
                # the stage's free directions are fitted parameters too: the core's count
                # alone undercounted a physics + core model
                free = int(self.physics_.basis_.shape[1])
                info["n_parameters"] = str(free + int(info.get("n_parameters", 0)))
        return info

    @property
    def needs_time(self) -> bool:
        self._check_fitted()
        return self.physics_ is not None and self.physics_.needs_time


# --- cross-validation ------------------------------------------------------------------

@dataclass
class CrossValidation:
    """Out-of-fold predictions (every pose predicted by a model that never saw it).

    raw: the metrics of the measured poses; metrics: those of the pooled out-of-fold
    predictions with their improvements over raw (`metrics.metric_block`)."""

    predicted: np.ndarray                      # (N, 7)
    fold_of: np.ndarray                        # (N,) fold index of each pose
    fold_rmse: np.ndarray                      # (K,) held-out rmse_total per fold
    raw: dict[str, float | None] = field(default_factory=dict)
    metrics: dict[str, float | None] = field(default_factory=dict)
    fitted: list[Any] = field(default_factory=list)


def cross_validate(make: Callable[[], Any], table: PoseTable, plan: CrossValidationPlan = KFold(5), seed: int = 0,
                   fit_kwargs: Callable[[int], dict] | None = None, pool: FoldPool = IN_PROCESS) -> CrossValidation:
    """Fit `make()` on each training part of `plan`'s folds and predict the held-out poses.
    `make()` builds an estimator with a `with_rotation` parameter (a pipeline or physics
    stage; a bare core goes in `CorrectionPipeline(core=...)`): the table sets it, and the
    station's pose where the estimator has one (`SessionSetup`). `pool`: the processes the
    folds are fitted in (`folds.FoldPool`), with the same results as in this one."""
    measured, reference, t = table.measured, table.reference, table.time()
    predicted = np.empty_like(measured)
    fold_of = np.empty(table.n, dtype=int)
    fold_rmse, fitted, tasks = [], [], []
    splits = plan.folds(table.n, seed)
    for k, (train, held) in enumerate(splits):
        model = make()
        model.set_params(**session_setup(table).params_for(model))
        tasks.append((model, measured[train], reference[train], None if t is None else t[train],
                      fit_kwargs(k) if fit_kwargs else {}, measured[held], None if t is None else t[held]))
    for k, ((_, held), (model, out, detached)) in enumerate(zip(splits, pool.map(_fit_fold, tasks))):
        if detached is not None:
            _physics_stage(model).attach(detached)
        predicted[held] = out
        fold_of[held] = k
        dp, dr = pose_errors(reference[held], predicted[held], table.has_orientation)
        fold_rmse.append(rmse_total(dp, dr))
        fitted.append(model)
    raw = pose_metrics(reference, measured, table.has_orientation)
    return CrossValidation(predicted, fold_of, np.asarray(fold_rmse), raw,
                           metric_block(raw, pose_metrics(reference, predicted, table.has_orientation)), fitted)


def _fit_fold(task: tuple) -> tuple[Any, np.ndarray, dict | None]:
    """One fold of `cross_validate`, in whichever process: (the fitted model, its predictions
    of the held-out poses, what of its physics stage travels beside it, `PhysicsModel.detach`)."""
    model, measured, reference, t, extra, held, t_held = task
    model.fit(measured, reference, t=t, **extra)
    predicted = model.predict(held, t_held)
    physics = _physics_stage(model)
    return model, predicted, None if physics is None else physics.detach()


def _physics_stage(model: Any) -> PhysicsModel | None:
    """The physics stage of a pipeline, or the model itself where it is one."""
    return model if isinstance(model, PhysicsModel) else getattr(model, "physics_", None)


# --- candidates, the rigid baseline and the choice ---------------------------------------

# Below SMALL_TABLE poses auto tries only cheap candidates (no MLP, one representation): a
# network cannot be held out of 6 to 40 poses. Below MIN_TEST_SPLIT poses a 15 % test split
# holds too few poses to mean anything, so fit cross-validates instead (and says so); a
# held-out score resting on fewer than MIN_HELDOUT poses carries a warning.
SMALL_TABLE = 200
MIN_HELDOUT = 20
# The physics stage's prior strengths auto chooses among (by the same held-out poses as
# everything else): 0 is the free fit, each step ten times stronger holds the physical
# parameters nearer their identity (`PhysicsModel.prior_strength`).
PRIOR_STRENGTHS = (0.0, 0.1, 1.0, 10.0)


@dataclass(frozen=True)
class Candidate:
    """A model fit may return: a physics stage (`effects` with a `prior_strength`, or a rigid
    variant of `identify.RIGID_VARIANTS`) and a core (`core`, built with `seed`)."""

    name: str
    effects: tuple[str, ...] = ()
    core: ModelSpec | None = None
    rigid: str = ""
    prior_strength: float = 0.0
    seed: int = 0

    def make_core(self) -> Any:
        return None if self.core is None else self.core.make(self.seed)

    def make(self, setup: SessionSetup = SessionSetup()) -> CorrectionPipeline:
        return CorrectionPipeline(self.effects, self.make_core(), rigid=self.rigid, with_rotation=setup.with_rotation,
                                  prior_strength=self.prior_strength, station_pose=setup.station_pose)


def rigid_candidates(table: PoseTable) -> list[Candidate]:
    """The floor: every plain rigid fit the table allows (`identify.rigid_variants`)."""
    from posecorr.rotations import quat_to_matrix

    axes = describe_spread(table.meas_p, quat_to_matrix(table.meas_q), table.has_orientation).rotation_axes
    return [Candidate(f"rigid-{variant}", rigid=variant) for variant in rigid_variants(table.has_orientation, axes)]


def auto_candidates(table: PoseTable, effects: Sequence[str], representation: str = "zhou") -> list[Candidate]:
    """What `--method auto` chooses from: the plain Kabsch fit; the physics stage (the
    registration when no effect is named) at every strength of PRIOR_STRENGTHS; the free
    physics stage with a ridge-regularised affine or quadratic core (the penalty chosen by
    an inner cross-validation); on tables of SMALL_TABLE poses or more also the quadratic
    core in every representation and a small MLP. The other rigid variants are the floor
    `fit_table` compares auto's choice with on the outer folds: inside the choice they would
    only add selection noise and time."""
    from posecorr.rotations import orientations

    physics = tuple(effects) or ("station", "mount")
    rep = representation if table.has_orientation else POSITION_ONLY

    def pmc(representation: str, **params: Any) -> ModelSpec:
        return spec_from_options("pmc", representation, **params)

    out = [candidate for candidate in rigid_candidates(table) if candidate.rigid == "kabsch"]
    out += [Candidate(physics_name(strength), physics, prior_strength=strength) for strength in PRIOR_STRENGTHS]
    out += [Candidate(f"physics+affine-{rep}", physics, pmc(rep, degree=1)),
            Candidate(f"physics+pmc-{rep}", physics, pmc(rep))]
    if table.n >= SMALL_TABLE:
        reps = orientations() if table.has_orientation else ()
        out += [Candidate(f"physics+pmc-{r}", physics, pmc(r)) for r in reps if r != rep]
        small_network = spec_from_options("mlp", rep, hidden=SESSION_HIDDEN, epochs=SESSION_EPOCHS)
        out.append(Candidate(f"physics+{small_network.stem}", physics, small_network))
    return out


def physics_name(strength: float) -> str:
    """'physics' for the free fit, 'physics(prior 1)' with a prior."""
    return "physics" if strength == 0 else f"physics(prior {strength:g})"


def requested_candidate(effects: Sequence[str], spec: ModelSpec, seed: int = 0) -> Candidate:
    """The model the user asked for (`--method none/pmc/mlp`): the physics stage of `effects`
    and `spec`'s core."""
    core = f"{spec.method}-{spec.representation}" if spec.has_core else ""
    name = "+".join(part for part in ("physics" if effects else "", core) if part) or "identity"
    return Candidate(name, tuple(effects), spec if spec.has_core else None, seed=seed)


def _stops_early(candidate: Candidate) -> bool:
    """The candidate's core uses the validation poses (`uses_validation`): its fit on the
    training rows is the one to keep, a refit on more rows would have nothing to stop on."""
    return getattr(candidate.make_core(), "uses_validation", False)


def _fit(candidate: Candidate, rows: np.ndarray, arrays: tuple, setup: SessionSetup, prior: dict,
         shared: dict | None = None, validation: Validation | None = None) -> CorrectionPipeline:
    """Fit a candidate on `rows`; physics stages of equal effects and prior strength are
    fitted once per `shared` dict (candidates that differ only in their core share them) and
    start from `prior` (the free fit of those effects)."""
    M, R, t = arrays
    t_rows = None if t is None else t[rows]
    physics = None
    effects = _fitted_effects(candidate)
    if effects:
        shared = {} if shared is None else shared
        free = (effects, 0.0)
        if free not in shared:
            shared[free] = PhysicsModel(effects, **setup._asdict()).fit(
                M[rows], R[rows], t=t_rows, warm_start=prior.get(effects))
        key = (effects, candidate.prior_strength)
        if key not in shared:       # a prior strength: the free fit shrunk, no further solve
            shared[key] = shared[free].shrunk(candidate.prior_strength)
        physics = shared[key]
    return candidate.make(setup).fit(M[rows], R[rows], t=t_rows, validation=validation, physics=physics)


def _fitted_effects(candidate: Candidate) -> tuple[str, ...]:
    """The effects a candidate's physics stage fits by least squares (shared between
    candidates): its own, those of the "joint" rigid variant, none for a closed form."""
    if candidate.rigid:
        return tuple(RigidModel().effects) if candidate.rigid == "joint" else ()
    return candidate.effects


def out_of_fold(candidates: Sequence[Candidate], rows: np.ndarray, arrays: tuple, setup: SessionSetup,
                splits: list[tuple[np.ndarray, np.ndarray]], prior: dict,
                say: Callable[[str], None] | None = None) -> dict[str, np.ndarray]:
    """{name: (len(rows), 7) predictions}, each pose predicted by a fit that never saw it;
    `splits` index into `rows`. `say`: where to report the folds as they start."""
    M, _, t = arrays
    predicted = {c.name: np.empty((len(rows), 7)) for c in candidates}
    for train, held in _progress_iter(splits, say, "fold") if say else splits:
        shared: dict = {}
        stages: dict = {}          # candidates sharing a physics stage correct the held-out poses once
        for candidate in candidates:
            model = _fit(candidate, rows[train], arrays, setup, prior, shared)
            key = id(model.physics_)           # the stage is held in `stages`: its id stays its own
            if key not in stages:
                stages[key] = (model.physics_, model.predict_physics(M[rows[held]], None if t is None else t[rows[held]]))
            predicted[candidate.name][held] = model.predict_core(stages[key][1])
    return predicted


def _score(reference: np.ndarray, predicted: np.ndarray, with_rotation: bool) -> float:
    return float(pose_metrics(reference, predicted, with_rotation)["rmse_total"])


# Held-out scores this close (relative) are one model fitted twice, not a loss: the physics
# stage of station and mount on a table without orientations is a rigid variant, and the two
# iterative fits stop 1e-9 apart (a fit of it fell back, "0.0000024 % worse").
SAME_SCORE = 1e-6


def _best(candidates: Sequence[Candidate], scores: dict[str, float]) -> Candidate:
    """The lowest score; on ties a rigid variant, then the earlier candidate (the simpler)."""
    return min(candidates, key=lambda c: (scores[c.name], not c.rigid))


def choose(candidates: Sequence[Candidate], rows: np.ndarray, arrays: tuple, setup: SessionSetup,
           plan: CrossValidationPlan, seed: int, prior: dict) -> tuple[Candidate, dict[str, float]]:
    """The candidate with the lowest cross-validated rmse_total on `rows` (a rigid variant on ties)."""
    splits = plan.folds(len(rows), seed)
    predicted = out_of_fold(candidates, rows, arrays, setup, splits, prior)
    reference = arrays[1][rows]
    scores = {name: _score(reference, p, setup.with_rotation) for name, p in predicted.items()}
    return _best(candidates, scores), scores


@dataclass
class FitReport:
    """What `posecorr fit` learned: the model to export and its held-out evaluation.

    heldout: metrics of the returned model on poses it never saw (test split, or out of fold;
    for auto the choice itself is made inside each outer fold). baseline: the best rigid
    variant's metrics on the same poses (`baseline_name`, one of `rigid_candidates`; the
    rigid variants' scores in `rigid_scores`, and under cross-validation their rmse_pos in
    `rigid_rmse_pos`). n_heldout: how many poses each score rests on.
    notes: what the user must know (a fallback to the rigid fit, a switch to
    cross-validation, a thin score).
    """

    model: CorrectionPipeline
    raw: dict[str, float | None]
    heldout: dict[str, float | None]
    plan: Plan                             # what `heldout` rests on: the fixed split or the folds
    train_index: np.ndarray
    chosen: str
    auto_scores: dict[str, float] = field(default_factory=dict)
    baseline: dict[str, float | None] = field(default_factory=dict)
    n_heldout: int = 0
    fell_back: bool = False
    notes: list[str] = field(default_factory=list)
    test_index: np.ndarray | None = None    # the test split's rows (plan `FixedSplit`)
    baseline_name: str = ""
    rigid_scores: dict[str, float] = field(default_factory=dict)
    rigid_rmse_pos: dict[str, float] = field(default_factory=dict)
    # where it fell back: what the model asked for scored ({"name", "rmse_total", "on"}), which
    # the ledger keeps so that a report's history shows what was tried, not four rigid fits
    asked: dict[str, Any] | None = None

    @property
    def heldout_kind(self) -> HeldOut:
        """HeldOut.TEST (fixed split) or HeldOut.CV: the held-out block's key in `fit --json`."""
        return self.plan.heldout

    @property
    def fixed(self) -> dict[str, str]:
        physics = self.model.physics_
        return dict(physics.fixed_) if physics is not None else {}

    @property
    def shrinkage(self) -> dict[str, float] | None:
        """{"prior_strength", "effective_params"} of the returned physics stage (None for a
        rigid fit): how far the prior held the physical parameters, and how many parameters
        the fit used (the trace of its hat matrix)."""
        physics = self.model.physics_
        if physics is None or not hasattr(physics, "effective_params_"):     # a closed form: no fit, no prior
            return None
        return {"prior_strength": float(physics.prior_strength), "effective_params": physics.effective_params_}


def fit_table(table: PoseTable, effects: Sequence[str], spec: ModelSpec, plan: Plan = FixedSplit(), seed: int = 0,
              progress: Callable[[str], None] | None = None) -> FitReport:
    """Fit a pipeline (the physics stage of `effects`, then `spec`'s core) on a table and
    evaluate it on held-out poses, never returning a model that does worse there than the best
    plain rigid fit.

    plan `FixedSplit`: the protocol's fixed 15 % test split (seeded); candidates are fitted on
    the training rows and compared on the validation rows, the chosen one refitted on both (an
    MLP keeps its early-stopped fit); tables under MIN_TEST_SPLIT poses are cross-validated
    instead. `KFold` or `LeaveOneOut`: out-of-fold predictions of the requested model and of
    every rigid variant on the same folds; the best rigid variant is returned when it does
    better. A spec whose method chooses ("auto"): nested: inside each outer fold an inner
    cross-validation chooses among `auto_candidates` (around `spec.representation`), the outer
    folds score that choice; the final model is chosen the same way on all poses.
    """
    from posecorr.data import require_rows
    from posecorr.effects import require_time

    require_rows(table, 4, "a fit", outliers=check_outliers)
    require_time(effects, table)
    spec = spec_for_table(spec, table)
    say = progress or (lambda message: None)
    notes = orientation_notes(table.meas_q, table.ref_q, table.meas_p, table.ref_p)
    plan = _plan_for_size(plan, table.n, notes)
    floor = rigid_candidates(table)
    auto = spec.method_entry.chooses
    require_enough_to_fit(table.n, plan, nested=auto)
    if auto:
        candidates = auto_candidates(table, effects, spec.representation)
    else:
        candidates = [requested_candidate(effects, spec, seed), *floor]
        core = candidates[0].make_core()
        if core is not None:   # a core that needs more poses than a fold leaves fails before any work
            require_enough_to_fit(table.n, plan, needs=core.min_rows(), model=candidates[0].name)
        _note_more_weights_than_numbers(candidates[0], table.n, plan, seed, say, notes)
    fit_phase = _fit_fixed_split if isinstance(plan, FixedSplit) else _fit_cross_validated
    return _warn_thin(_note_trade(fit_phase(table, candidates, floor, auto, plan, seed, say, notes), effects))


def spec_for_table(spec: ModelSpec, table: PoseTable) -> ModelSpec:
    """The model `fit_table` fits for `spec` on `table`: on a table without reference
    orientations, its core in position only (the representation's orientation part has
    nothing to learn from). `report` rebuilds a fit's held-out predictions by the same rule."""
    from dataclasses import replace

    return spec if table.has_orientation else replace(spec, representation=POSITION_ONLY)


def _note_more_weights_than_numbers(candidate: Candidate, n: int, plan: Plan, seed: int,
                                    say: Callable[[str], None], notes: list[str]) -> None:
    """Said before the work: a core with more weights than the poses it is fitted on hold
    numbers (a default MLP on a session of tens of poses) is settled by its regularisation
    more than by the data; an MLP there takes minutes and seldom beats the rigid fit."""
    core = candidate.make_core()
    weights = None if core is None else core.n_weights()
    if weights is None:
        return
    rows = len(plan.indices(n, seed)[0]) if isinstance(plan, FixedSplit) else fewest_to_fit(n, plan)
    numbers = rows * vector_size(core.representation)
    if weights <= numbers:
        return
    note = (f"{candidate.name} has {weights:,} weights to fit on {rows} poses ({numbers:,} numbers) in each fit: "
            "its regularisation, not the data, settles most of them")
    say(f"note: {note}")
    notes.append(note)


def _plan_for_size(plan: Plan, n: int, notes: list[str]) -> Plan:
    """The held-out plan the table can bear: a fixed split of fewer than MIN_TEST_SPLIT poses
    would test on a handful, so such tables are cross-validated instead (said in `notes`)."""
    if isinstance(plan, FixedSplit) and n < MIN_TEST_SPLIT:
        plan = plan_for(n)
        notes.append(f"{n} poses are too few for a 15 % test split (fewer than {MIN_TEST_SPLIT}); "
                     f"cross-validated ({plan}) instead")
    return plan


def _fit_fixed_split(table: PoseTable, candidates: list[Candidate], floor: list[Candidate], auto: bool,
                     plan: FixedSplit, seed: int, say: Callable[[str], None], notes: list[str]) -> FitReport:
    """The fixed-split phase: candidates fitted on the training rows, chosen on the validation
    rows, the choice and the best rigid fit refitted on both and scored on the test rows."""
    M, R, t = table.measured, table.reference, table.time()
    arrays, setup = (M, R, t), session_setup(table)
    with_rotation = setup.with_rotation
    train, val, test = plan.indices(table.n, seed)
    fit_rows = np.sort(np.concatenate([train, val]))
    # Every rigid variant is fitted and scored: the floor, and the fallback where the
    # validation poses prefer one ("auto"'s candidates hold one of them only).
    named = {c.name for c in candidates}
    pool = list(candidates) + [c for c in floor if c.name not in named]
    say(f"fitting {len(pool)} candidate(s) on {len(train)} poses, choosing on {len(val)}, testing on {len(test)}")
    prior = _priors(pool, train, arrays, setup)
    shared: dict = {(names, 0.0): model for names, model in prior.items()}   # fitted on these very rows
    held = Validation(M[val], R[val], None if t is None else t[val])
    fitted = {c.name: _fit(c, train, arrays, setup, prior, shared, validation=held) for c in pool}
    scores = {name: _score(R[val], m.predict(M[val], None if t is None else t[val]), with_rotation)
              for name, m in fitted.items()}
    best = _best(pool, scores)
    floor_best = _best(floor, scores)
    model = fitted[best.name] if _stops_early(best) else _fit(best, fit_rows, arrays, setup, prior)
    rigid = model if best == floor_best else _fit(floor_best, fit_rows, arrays, setup, prior)
    t_test = None if t is None else t[test]
    raw = pose_metrics(R[test], M[test], with_rotation)
    heldout = metric_block(raw, pose_metrics(R[test], model.predict(M[test], t_test), with_rotation))
    baseline = metric_block(raw, pose_metrics(R[test], rigid.predict(M[test], t_test), with_rotation))
    if best.rigid and not auto:
        notes.append(f"the requested model did worse than the rigid fit on the {len(val)} validation poses "
                     f"({scores[candidates[0].name]:.4g} against {scores[best.name]:.4g} rmse_total): "
                     f"returning the rigid fit ({best.name})" + _without_registration(candidates[0], raw, baseline))
    fell_back = bool(best.rigid) and not auto
    asked = ({"name": candidates[0].name, "rmse_total": scores[candidates[0].name], "on": "validation"}
             if fell_back else None)
    return FitReport(model, raw, heldout, plan, np.sort(fit_rows if not _stops_early(best) else train),
                     best.name, auto_scores=scores if auto else {}, baseline=baseline, n_heldout=len(test),
                     fell_back=fell_back, notes=notes, test_index=test,
                     baseline_name=floor_best.name, rigid_scores={c.name: scores[c.name] for c in floor}, asked=asked)


def _fit_cross_validated(table: PoseTable, candidates: list[Candidate], floor: list[Candidate], auto: bool,
                         plan: Plan, seed: int, say: Callable[[str], None], notes: list[str]) -> FitReport:
    """The cross-validated phase: out-of-fold scores of the choice and of every rigid variant,
    a fallback to the best rigid variant where it does better, then the final fit on all poses."""
    M, R, t = table.measured, table.reference, table.time()
    arrays, setup = (M, R, t), session_setup(table)
    with_rotation = setup.with_rotation
    everything = np.arange(table.n)
    raw_all = pose_metrics(R, M, with_rotation)
    splits = plan.folds(table.n, seed)
    prior = _priors(candidates, everything, arrays, setup)
    if auto:
        best, scores, predicted, floor_predicted = _out_of_fold_auto(
            candidates, floor, arrays, setup, splits, seed, prior, say)
    else:
        say(f"cross-validating {candidates[0].name} and the rigid fits ({plan.description})")
        every = out_of_fold(candidates, everything, arrays, setup, splits, prior, say)
        best, scores = candidates[0], {}
        predicted, floor_predicted = every[best.name], {c.name: every[c.name] for c in floor}
    floor_metrics = {c.name: metric_block(raw_all, pose_metrics(R, floor_predicted[c.name], with_rotation))
                     for c in floor}
    rigid_scores = {name: m["rmse_total"] for name, m in floor_metrics.items()}
    floor_best = _best(floor, rigid_scores)
    baseline = floor_metrics[floor_best.name]
    # A rigid variant returned is scored as itself on these folds.
    heldout = (floor_metrics[best.name] if best.rigid
               else metric_block(raw_all, pose_metrics(R, predicted, with_rotation)))
    fell_back = best != floor_best and baseline["rmse_total"] * (1.0 + SAME_SCORE) < heldout["rmse_total"]
    asked = None
    if fell_back:
        _note_fallback(best, floor_best, heldout, baseline, auto, notes, raw_all)
        asked = {"name": "auto" if auto else best.name, "rmse_total": heldout["rmse_total"], "on": "held-out"}
        best, heldout = floor_best, baseline
    say(f"fitting {best.name} on all {table.n} poses")
    model = _fit(best, everything, arrays, setup, prior)
    return FitReport(model, raw_all, heldout, plan, everything, best.name, auto_scores=scores, baseline=baseline,
                     n_heldout=table.n, fell_back=fell_back, notes=notes, baseline_name=floor_best.name,
                     rigid_scores=rigid_scores, asked=asked,
                     rigid_rmse_pos={name: m["rmse_pos"] for name, m in floor_metrics.items()})


def _out_of_fold_auto(candidates: Sequence[Candidate], floor: Sequence[Candidate], arrays: tuple,
                      setup: SessionSetup, splits: list, seed: int, prior: dict,
                      say: Callable[[str], None]) -> tuple[Candidate, dict[str, float], np.ndarray, dict]:
    """The nested phase of "auto": each outer fold predicted by the choice an inner
    cross-validation makes on its training rows, then the final choice made on all poses.
    Returns (final choice, its inner scores, the outer folds' predictions, the rigid variants')."""
    n = len(arrays[0])
    everything = np.arange(n)
    predicted = nested_out_of_fold(candidates, arrays, setup, splits, seed, prior, say)
    say("auto: choosing on all poses")
    best, scores = choose(candidates, everything, arrays, setup, plan_for(n, nested=True), seed, prior)
    floor_predicted = out_of_fold(floor, everything, arrays, setup, splits, prior)
    return best, scores, predicted, floor_predicted


def nested_out_of_fold(candidates: Sequence[Candidate], arrays: tuple, setup: SessionSetup, splits: list,
                       seed: int, prior: dict, say: Callable[[str], None]) -> np.ndarray:
    """(N, 7): each outer fold's poses predicted by the candidate an inner cross-validation on
    the fold's training rows chooses, fitted on those rows: how "auto" is scored."""
    M, _, t = arrays
    say(f"auto: choosing among {len(candidates)} candidates inside each of {len(splits)} outer folds")
    predicted = np.empty_like(M)
    for train, held in _progress_iter(splits, say, "outer fold"):
        best, _ = choose(candidates, train, arrays, setup, plan_for(len(train), nested=True), seed, prior)
        model = _fit(best, train, arrays, setup, prior)
        predicted[held] = model.predict(M[held], None if t is None else t[held])
    return predicted


def _note_fallback(best: Candidate, floor_best: Candidate, heldout: dict, baseline: dict, auto: bool,
                   notes: list[str], raw: dict) -> None:
    """Tells the user why the rigid fit is returned instead of the requested (or auto's) model."""
    worse = 100.0 * (heldout["rmse_total"] / baseline["rmse_total"] - 1.0)
    # auto is scored by the choices made inside each outer fold, not by its scores on all poses
    what = f"auto (its choice in each outer fold; {best.name} on all poses)" if auto else best.name
    notes.append(f"{what} did worse on held-out poses than the best rigid fit, {floor_best.name} "
                 f"({heldout['rmse_total']:.4g} against {baseline['rmse_total']:.4g} rmse_total, "
                 f"{percent(worse)} % worse): returning {floor_best.name}"
                 + ("" if auto else _without_registration(best, raw, baseline)))


def _without_registration(requested: Candidate, raw: dict, rigid: dict) -> str:
    """Where a core was asked for with no physics stage on frames nobody registered: the core
    had to learn the frames' offset (metres) from the poses, which the stage fits first."""
    from posecorr.metrics import frames_unregistered

    if requested.core is None or requested.effects or not frames_unregistered(raw, rigid):
        return ""
    return (f"; the frames are unregistered (raw rmse_pos {1e3 * raw['rmse_pos']:.4g} mm, the rigid fit "
            f"{1e3 * rigid['rmse_pos']:.4g} mm) and no physics stage came before the core, so it had to learn "
            "their offset: --effects station,mount fits the registration first")


def check_outliers(table: PoseTable) -> list[str]:
    """TableError naming the rows a rigid fit of the other poses misses by metres (a blunder in
    the table: a unit slip, a swapped row, that no model should be fitted to); else the
    warning lines naming the rows it misses by ten times the others' median or more (a
    tracker glitch, a frozen pose: kept, the user decides). `require_rows`' `outliers`."""
    from posecorr.data import TableError
    from posecorr.rotations import quat_to_matrix
    from posecorr.textui import counted

    from .identify import OUTLIER_FACTOR, OUTLIER_MIN_M, SUSPECT_FACTOR, outliers

    found = outliers(table.meas_p, quat_to_matrix(table.meas_q), table.ref_p)
    ids = table.extras.get("id")

    def named(o) -> str:
        return f"row {table.file_row(o.index)}" + (f" (id {ids[o.index]})" if ids is not None else "")

    gross = [o for o in found if o.gross]
    if gross:
        rows = "; ".join(f"{named(o)}: {o.miss:.3g} m" for o in gross)
        raise TableError(table.path, f"gross outlier(s): a rigid fit of the other poses misses {rows}, against a "
                         f"median of {1000 * gross[0].typical:.3g} mm (more than {OUTLIER_FACTOR:g} times, and "
                         f"{OUTLIER_MIN_M:g} m); fix or remove the row(s)", row=table.file_row(gross[0].index))
    if not found:
        return []
    rows = "; ".join(f"{named(o)}: {1000 * o.miss:.3g} mm, {o.miss / o.typical:.0f} times {1000 * o.typical:.3g} mm"
                     for o in found)
    return [f"{table.source}: a rigid fit of the other poses misses {counted(len(found), 'row')} by {SUSPECT_FACTOR:g} "
            f"times their median miss or more: {rows}; a tracker glitch or a frozen pose? Kept: every fit and "
            "held-out figure includes it (posecorr report lists the worst poses)"]


def _priors(candidates: Sequence[Candidate], rows: np.ndarray, arrays: tuple, setup: SessionSetup) -> dict:
    """The physics stage of each distinct effect list, fitted once on `rows`: the warm start
    (and the determined directions) of every fold's fit."""
    M, R, t = arrays
    prior = {}
    for candidate in candidates:
        effects = _fitted_effects(candidate)
        if effects and effects not in prior:
            prior[effects] = PhysicsModel(effects, **setup._asdict()).fit(
                M[rows], R[rows], t=None if t is None else t[rows])
    return prior


def _progress_iter(splits: list, say: Callable[[str], None], label: str):
    for k, split in enumerate(splits):
        if k % max(1, len(splits) // 10) == 0:
            say(f"{label} {k + 1}/{len(splits)}")
        yield split


def floor_instead(report: FitReport, table: PoseTable, why: str) -> FitReport:
    """The report of the best rigid fit in place of `report`'s model, which cannot be written
    (`why`: its export failed its parity check): the floor fitted on the poses the model was
    (all of them, or all but the test split), scored as `report` scored it."""
    M, R, t = table.measured, table.reference, table.time()
    rows = np.setdiff1d(np.arange(table.n), report.test_index if report.test_index is not None else [])
    floor = {c.name: c for c in rigid_candidates(table)}[report.baseline_name]
    model = _fit(floor, rows, (M, R, t), session_setup(table), {})
    on = "held-out" if report.test_index is None else "test"
    note = (f"{report.chosen} could not be written: {why}; the rigid fit ({report.baseline_name}) is written in its "
            f"place, its figures on the same {on} poses")
    return replace(report, model=model, heldout=report.baseline, chosen=report.baseline_name, fell_back=True,
                   train_index=rows, auto_scores={},
                   notes=[n for n in report.notes if not n.startswith(f"{report.chosen} beats")] + [note],
                   asked={"name": report.chosen, "rmse_total": report.heldout.get("rmse_total"), "on": on,
                          "why": "its file failed the export's parity check"})


def _note_trade(report: FitReport, effects: Sequence[str]) -> FitReport:
    """The choice is made on rmse_total (metres plus radians, the paper's score): a model that
    beats the rigid fit there while it is worse in position (or in rotation) trades one for
    the other, which a user who reads one column must be told, with what to fit instead: the
    physics stage of the effects given (the registration's with them) without the core, or,
    where that is the model, the rigid fit."""
    from posecorr.effects import registration_names

    held, floor = report.heldout, report.baseline
    if report.chosen == report.baseline_name or not floor:
        return report
    registration = registration_names()
    if report.model.core_ is not None:
        instead = "the physics stage alone"
        names = registration + [name for name in effects if name not in registration]
    else:
        instead, names = "the rigid fit itself", registration
    advice = f"{instead} (`--effects {','.join(names)} --method none`)"
    for key, unit, scale, other, other_unit in (("rmse_pos", "mm", 1e3, "rmse_rot", "mrad"),
                                                ("rmse_rot", "mrad", 1e3, "rmse_pos", "mm")):
        worse, better = held.get(key), held.get(other)
        if worse is None or better is None or floor.get(key) is None or floor.get(other) is None:
            continue
        if worse > floor[key] * (1.0 + TRADE_MARGIN) and better < floor[other]:
            report.notes.append(
                f"{report.chosen} beats the rigid fit ({report.baseline_name}) in rmse_total, not in {key}: "
                f"{scale * worse:.4g} against {scale * floor[key]:.4g} {unit} held out "
                f"({100.0 * (worse / floor[key] - 1.0):.1f} % worse), for {scale * better:.4g} against "
                f"{scale * floor[other]:.4g} {other_unit} in {other}; where {key} matters most, fit {advice}")
    return report


# How much worse in one of position and rotation a model may be than the rigid fit before
# fit says it trades that for the other: less is the folds' rounding.
TRADE_MARGIN = 1e-3


def _warn_thin(report: FitReport) -> FitReport:
    if report.n_heldout < MIN_HELDOUT:
        report.notes.append(f"the held-out score rests on {report.n_heldout} poses (fewer than {MIN_HELDOUT}): "
                            "treat it as a rough figure")
    return report


__all__ = ["FitReport", "fit_table", "CorrectionPipeline", "cross_validate", "CrossValidation", "Candidate",
           "rigid_candidates", "auto_candidates", "requested_candidate", "choose", "out_of_fold"]
