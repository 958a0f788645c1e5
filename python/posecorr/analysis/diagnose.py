"""Which physical effect is the model missing, and where does its error live?

`diagnose(table, effects)` fits the named physics model, then, for every catalogue effect
it lacks (user effects included once loaded):

* **score test on held-out residuals** (Lagrange multiplier test): in each fold, at the
  base model fitted without that fold, the held-out whitened residuals r and Jacobian
  columns J_e of the candidate (at its identity value) are projected off what the base
  fit can move (its Jacobian along the directions it determined); pooled over folds,
  g = sum J_e'^T r' and I = sum J_e'^T J_e' give LM = g^T I^+ g / s^2, chi-square with
  rank(I) degrees of freedom under "not missing" (`score_test_reach`: LM <= m, the
  residual's dimensions left, so few poses bound p from below);
* **held-out prediction test**: the score test sees the candidate only along its Jacobian at
  identity, blind to a large effect that bends out of that plane (a mount turned by half a
  turn, frames nobody registered). So each fold's candidate is also fitted without the
  fold, and the change it makes to the held-out residual, projected likewise, is tested as
  a predictor of that residual (`_prediction_z`, one-sided normal). The candidate's p is the
  smaller of the two, doubled (Bonferroni over the two tests); z^2 <= m too, so the reach
  is the same;
* **cross-validated RMSE before and after** adding the effect (K folds of whole poses,
  each after-fit warm-started from that fold's base fit);
* `score`: the mean over folds of the relative fall of the held-out whitened error
  (position / sigma_p, orientation / sigma_r: the fit's own objective, so a position-only
  effect is not diluted by orientation noise as it would be in rmse_total);
* `present` only when the effect is significant AND consistent: Bonferroni-corrected
  p < `alpha` (default 1e-3 over the number of candidates), the held-out whitened error
  lower in EVERY fold, and a mean relative gain of at least `min_gain` (default 0.5 %).

Candidates are ranked by their score, except that a catalogue effect goes before a form when
it scores at least 1 - `INDISTINCT_GAIN` of the form's score (`rank_key`): forward selection
walks the ranking, and where both explain the error alike, the physical effect with its
documented parameters is the answer, not the form that contains it (a range scale is an
isotropic strain). Pairs of effects that move the poses alike along some direction are
flagged as `aliases`: a canonical correlation of their (base-projected) Jacobian column
spaces exceeds 0.99; the record counts how many do (`shared`, of the smaller space's `of`
directions), and only a pair that shares them all cannot be told apart.

It also reports residual structure that no catalogue effect may explain: for each feature
(`posecorr.analysis.features`) the cross-validated R^2 of a smooth fit (cubic spline + ridge) of
the out-of-fold residuals (position mm, orientation mrad) on that feature alone.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from ..data import PoseTable
from ..effects import EFFECTS, get_effect, registration_names, require_time
from ..metrics import frames_unregistered, pose_errors, pose_metrics, rmse_total
from ..registration import orientation_notes
from ..rotations import matrix_to_rotvec, quat_to_matrix
from ..textui import counted
from .features import FEATURES, UNPLACED_STATION, pose_features, stated_station

ALIAS_CORRELATION = 0.99
# The test's level, before the Bonferroni correction over the candidates.
ALPHA = 1e-3
# The least mean relative fall of the held-out whitened error that counts as a gain.
MIN_GAIN = 0.005
PRESENT_TEST = ("score test or held-out prediction test (the smaller p, doubled), Bonferroni-corrected "
                "p < {alpha:g}; "
                "held-out whitened error lower in every one of {folds} folds; mean gain >= {gain:.1%}; "
                "still so given the others present (forward selection in rank order: by score, but a catalogue "
                "effect before a form when it gains at least {share:.0%} as much; a catalogue effect that fails "
                "alone tested again given all kept; backward elimination; then each kept tested given a catalogue "
                "effect not kept: a form gives way to one that passes and leaves it nothing, and two catalogue effects "
                "of which one leaves the other nothing, gaining as much, are neither named); "
                "catalogue effects within their plausible ranges")


def _addable(effects: Sequence[str], forms: bool) -> list[tuple[str, Any]]:
    """(name, effect) of the registered, fittable effects not in `effects`; the generic forms
    (`posecorr.forms`) too unless `forms` is False."""
    return [(name, effect) for name, effect in EFFECTS.items()
            if name not in effects and not effect.random and (forms or not effect.generic)]


def candidate_effects(table: PoseTable, effects: Sequence[str], forms: bool = True) -> list[str]:
    """The `_addable` effects the table can show: those acting over time only where it has
    times, those acting on the orientation alone only where its reference has orientations."""
    timed = table.time() is not None
    return [name for name, effect in _addable(effects, forms)
            if (timed or not effect.needs_time) and (table.has_orientation or effect.changes_position)]


def _table_notes(table: PoseTable, effects: Sequence[str], candidates: Sequence[str] | None,
                 forms: bool) -> list[str]:
    """What the diagnosis says of the table before its figures: its quaternions' order
    (`registration.orientation_notes`), and the effects it leaves untried for want of a
    clock or of reference orientations (they would be left out without a word, or ranked
    as held by the data for a cause that is not theirs)."""
    addable = [] if candidates is not None else _addable(effects, forms)
    untimed = [name for name, effect in addable if effect.needs_time and table.time() is None]
    unturned = [name for name, effect in addable if not effect.changes_position and not table.has_orientation]
    return orientation_notes(table.meas_q, table.ref_q, table.meas_p, table.ref_p) + (
        [f"not tried: {', '.join(untimed)} (acting over the session's time, they need a time column t, which this "
         "table lacks)"] if untimed else []) + (
        [f"not tried: {', '.join(unturned)} (acting on the orientation alone, they need the reference's "
         "orientations, which this table lacks)"] if unturned else [])


def split_identifiable(table: PoseTable, effects: Sequence[str],
                       names: Sequence[str]) -> tuple[list[str], list[dict[str, Any]]]:
    """(candidates the data can determine, [{"effect", "reason"}] of those it cannot): a
    candidate whose every parameter the identification of the model with it added holds
    (`PhysicsModel.identifiability`) would only be ranked by noise, so it is not ranked. Where
    an effect of the model (not a registration) is what holds it, the data could determine it
    without that effect: its record names that effect as "in_model", and says whether the
    effect is the candidate itself (its subclass: a proposal fitted and taken) as "same"."""
    from posecorr.train.identify import BEFORE_IT

    keep, undetermined = [], []
    for name in names:
        held = _held(table, list(effects), name)
        if held is None:
            keep.append(name)
            continue
        record = {"effect": name, "reason": "; ".join(f"{k}: {v}" for k, v in held.items())}
        spanning = _spanning_effect(table, effects, name)
        if spanning is not None:
            record.update(in_model=spanning, same=isinstance(get_effect(spanning), type(get_effect(name))),
                          reason=record["reason"].replace(BEFORE_IT, f"(the rest is what {spanning} does)"))
        undetermined.append(record)
    return keep, undetermined


def _held(table: PoseTable, effects: list[str], name: str) -> dict[str, str] | None:
    """{parameter: why} of `name` held in the model `effects` + `name`, None unless all are."""
    from posecorr.train.physics import PhysicsModel
    from posecorr.train.pipeline import session_setup

    fixed = PhysicsModel(tuple(effects) + (name,), **session_setup(table)._asdict()).identifiability(
        table.measured, table.reference, table.time())
    held = {key: why for key, why in fixed.items() if key.split(" ")[0].split(".")[0] == name}
    whole = {key.split(" ")[0] for key in held if " along " not in key}
    return held if whole >= {f"{name}.{p.name}" for p in get_effect(name).params} else None


def _spanning_effect(table: PoseTable, effects: Sequence[str], name: str) -> str | None:
    """The model's effect without which the data determines `name`, or None. Registrations are
    not tried: a model without them is no model of unregistered frames, and a candidate they
    alias is one these poses cannot tell from the registration ("cannot be determined")."""
    for other in effects:
        if get_effect(other).registration:
            continue
        if _held(table, [e for e in effects if e != other], name) is None:
            return other
    return None


def residual_components(reference: np.ndarray, predicted: np.ndarray, with_rotation: bool) -> np.ndarray:
    """(N, 3 or 6): position error (mm) and orientation error as a rotation vector (mrad)."""
    parts = [(predicted[:, :3] - reference[:, :3]) * 1e3]
    if with_rotation:
        dR = np.swapaxes(quat_to_matrix(reference[:, 3:7]), -1, -2) @ quat_to_matrix(predicted[:, 3:7])
        parts.append(matrix_to_rotvec(dR) * 1e3)
    return np.concatenate(parts, axis=1)


# The residual_components' blocks that feature_r2 scores apart: millimetres and milliradians
# pooled into one R^2 hid a drift of position (R^2 0.28 along t alone) under the orientation's
# noise (pooled 0).
ERROR_BLOCKS = {"position": slice(0, 3), "orientation": slice(3, 6)}


def feature_r2(residuals: np.ndarray, features: dict[str, np.ndarray], folds: int = 5,
               seed: int = 0, blocks: dict[str, slice] | None = None) -> list[dict[str, Any]]:
    """Cross-validated R^2 of a smooth fit of the residuals on each feature alone, best first:
    {"feature", "r2", "error"}, the R^2 of the block of columns (`blocks`, by name; default
    all the columns as one, "error") the feature explains best."""
    from sklearn.linear_model import Ridge
    from sklearn.model_selection import cross_val_predict

    from posecorr.train.splits import KFold
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import OneHotEncoder, SplineTransformer

    blocks = blocks or {"error": slice(0, residuals.shape[1])}
    centred = residuals - residuals.mean(axis=0)
    totals = {block: float(np.sum(centred[:, cols] ** 2)) for block, cols in blocks.items()}
    out = []
    for name in FEATURES:
        if name not in features:
            continue
        x = np.asarray(features[name], float).reshape(-1, 1)
        distinct = np.unique(x).size
        if distinct < 2:
            out.append({"feature": name, "r2": 0.0, "error": next(iter(blocks))})
            continue
        # A lattice feature with few distinct values (Exp III roll: 3) is a category.
        encoder = (OneHotEncoder(handle_unknown="ignore") if distinct <= 8
                   else SplineTransformer(n_knots=8, degree=3, extrapolation="linear"))
        model = make_pipeline(encoder, Ridge(alpha=1e-3))
        predicted = cross_val_predict(model, x, residuals, cv=KFold(folds).folds(len(x), seed))
        r2 = {block: 1.0 - float(np.sum((residuals[:, cols] - predicted[:, cols]) ** 2)) / totals[block]
              if totals[block] > 0.0 else 0.0 for block, cols in blocks.items()}
        best = max(r2, key=r2.get)
        out.append({"feature": name, "r2": max(r2[best], 0.0), "error": best})
    return sorted(out, key=lambda row: -row["r2"])


# Singular values below this fraction of the largest are the Jacobian's noise, not directions:
# forward differences at a fit converged to its tolerance differ by ~1e-6 between float
# kernels, and a structural degeneracy (two held-out poses against twelve parameters) shows as
# 1e-12 to 1e-8 depending on the CPU's kernels, while the weakest direction a fit determines
# stands at 6e-5 and more (the shared real sessions). A threshold inside the noise made the
# projection's rank, and the p value, depend on the CPU.
RANK_TOLERANCE = 1e-6


def _orthonormal_basis(A: np.ndarray, tol: float = RANK_TOLERANCE) -> np.ndarray:
    if A.size == 0:
        return A
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    return U[:, s > tol * max(s.max(), 1e-300)]


def _canonical_correlations(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, int]:
    """(the canonical correlations of the column spaces of A and B, largest first; the
    smaller space's dimension)."""
    QA, QB = _orthonormal_basis(A), _orthonormal_basis(B)
    if QA.shape[1] == 0 or QB.shape[1] == 0:
        return np.zeros(0), 0
    return np.linalg.svd(QA.T @ QB, compute_uv=False), min(QA.shape[1], QB.shape[1])


def _alias(a: str, b: str, A: np.ndarray, B: np.ndarray) -> dict[str, Any] | None:
    """The pair as `aliases` records it, or None: `shared` of the smaller space's `of`
    directions move the poses alike (canonical correlation above ALIAS_CORRELATION); on
    Exp2's bare measurements (nine poses at one orientation) the mount and the station share
    four of six. Only shared == of makes the pair one the data cannot tell apart."""
    correlations, of = _canonical_correlations(A, B)
    shared = int(np.sum(correlations > ALIAS_CORRELATION))
    if not shared:
        return None
    return {"effects": [a, b], "correlation": float(correlations[0]), "shared": shared, "of": of}


def _project_off(A: np.ndarray, basis: np.ndarray) -> np.ndarray:
    return A - basis @ (basis.T @ A) if basis.size else A


@dataclass
class _Fold:
    """One fold of the base model, on its held-out poses."""

    r: np.ndarray            # whitened residuals
    J: np.ndarray            # their Jacobian: the base model's columns, then the candidates' (`is_extra`)
    is_extra: np.ndarray
    physics: Any             # the fold's fitted physics model
    # An orthonormal basis of what the base fit can move on these rows: its Jacobian along the
    # directions it determined (`basis_`); directions it holds are not part of the null model.
    base: np.ndarray
    r_off: np.ndarray        # r projected off `base`: what both tests read, for every candidate

    @classmethod
    def of(cls, r: np.ndarray, J: np.ndarray, is_extra: np.ndarray, physics: Any) -> "_Fold":
        base = J[:, ~is_extra]
        if base.shape[1]:
            base = base @ physics.directions_
        base = _orthonormal_basis(base)
        return cls(r, J, is_extra, physics, base, _project_off(r[:, None], base)[:, 0])


@dataclass
class _FoldState:
    """A base model cross-validated: each fold's fit, held-out residuals and Jacobians."""

    effects: list[str]
    predicted: np.ndarray                  # out-of-fold corrected poses
    fold_rmse: np.ndarray                  # held-out rmse_total per fold
    before: float                          # pooled held-out rmse_total
    per_fold: list[_Fold]
    column_owner: np.ndarray               # effect name of each Jacobian column

    @property
    def residual_dims(self) -> int:
        """The held-out residual's dimensions that the base fit cannot move, over all folds:
        the score test's m. A fold of one pose against twelve parameters leaves none."""
        return sum(fold.r.size - fold.base.shape[1] for fold in self.per_fold)

    def held_off(self, name: str) -> list[np.ndarray]:
        """Each fold's Jacobian columns of candidate `name` on its held-out rows, projected off
        what its base fit can move: what the score test, the prediction test's variance and
        the aliases read."""
        return [_project_off(fold.J[:, self.column_owner == name], fold.base) for fold in self.per_fold]

    @property
    def residual_variance(self) -> float:
        """s^2 of both tests: the projected held-out residual's sum of squares over m; 0 where
        m is 0 (what is left then is rounding, ~1e-30, and a statistic divided by it is noise)."""
        if not self.residual_dims:
            return 0.0
        return sum(float(fold.r_off @ fold.r_off) for fold in self.per_fold) / self.residual_dims


def p_threshold(alpha: float, n_candidates: int) -> float:
    """The test's p threshold: `alpha` Bonferroni-corrected over the candidates."""
    return alpha / max(n_candidates, 1)


def score_test_reach(state: _FoldState, n_candidates: int, alpha: float, poses: int) -> dict[str, Any]:
    """How far the score test can go on these poses. The statistic is the share of the
    projected residual a candidate explains, times m (`residual_dims`), so it never exceeds
    m: p >= chi2.sf(m, df) for any candidate, whatever it explains (the prediction test's
    z^2 too). Where even one parameter cannot reach the threshold, no candidate can pass:
    the folds hold out too few poses, or the session has too few. `folds_to_pass`: the most
    folds, fewer than these, at which the threshold comes within reach (`_folds_to_pass`),
    None where none does."""
    from scipy.stats import chi2

    m = state.residual_dims
    threshold = p_threshold(alpha, n_candidates)
    best_p = float(chi2.sf(m, 1)) if m > 0 else 1.0
    can_pass = best_p < threshold
    return {"residual_dims": m, "best_p": best_p, "threshold": threshold, "can_pass": can_pass,
            "folds_to_pass": None if can_pass else _folds_to_pass(state, poses, threshold)}


def _folds_to_pass(state: _FoldState, poses: int, threshold: float) -> dict[str, int] | None:
    """{folds, residual_dims}: the most folds, fewer than the state's, whose held-out poses would
    leave the score test's m large enough for p to reach `threshold`, with training poses
    enough for the base fit; estimated without refitting, each fold leaving the residual
    dimensions of its held-out poses less the directions its base fit determines."""
    from scipy.stats import chi2

    from posecorr.train.splits import KFold

    dims = sum(fold.r.size for fold in state.per_fold) / poses            # residuals a pose holds
    moved = max(fold.physics.directions_.shape[1] for fold in state.per_fold)
    for folds in range(len(state.per_fold) - 1, 1, -1):
        sizes = [len(held) for _, held in KFold(folds).folds(poses, 0)]
        m = sum(max(0, round(dims * size) - moved) for size in sizes)
        if chi2.sf(m, 1) < threshold and round(dims * (poses - max(sizes))) > moved:
            return {"folds": folds, "residual_dims": m}
    return None


# The chance of passing at which `poses_to_pass` plans: the usual figure, four sessions in five.
PLANNING_POWER = 0.8


def poses_to_pass(lm: float, df: int, poses: int, threshold: float, power: float = PLANNING_POWER) -> int | None:
    """Poses of the same spread at which the score test's p falls below `threshold` with
    chance `power`, if the candidate's effect is as large as this session's statistic says.
    Under an effect the statistic is noncentral chi-square with `df` degrees; its
    noncentrality grows in proportion to the poses (the score's information is a sum over
    them) and is estimated here as lm - df, its mean's excess. A rough guide: that estimate
    is as noisy as the statistic. None where the statistic shows no effect (lm <= df) or its
    p already passes."""
    from scipy.optimize import brentq
    from scipy.stats import chi2, ncx2

    if df < 1 or lm <= df or chi2.sf(lm, df) < threshold:
        return None
    critical = float(chi2.isf(threshold, df))
    needed = brentq(lambda nc: ncx2.sf(critical, df, nc) - power, 1e-9, 10.0 * critical + 100.0)
    return max(poses + 1, int(np.ceil(poses * needed / (lm - df))))


def best_form(rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The form with the largest held-out gain among the ranked candidates, or None."""
    return max((row for row in rows if row["kind"] == "form"), key=lambda row: row["score"], default=None)


def _planned(rows: list[dict[str, Any]], kept: Sequence[str], poses: int, threshold: float,
             min_gain: float) -> dict[str, Any] | None:
    """Where nothing is kept: how many poses would let the best form (by held-out gain) pass
    the p part of its test, when its gain already reaches the minimum (more poses do not
    raise a gain too small to count). Planned on the score test, at half the threshold (the
    test's p is the smaller of two, doubled): planned on the prediction test, whose one degree
    of freedom asks fewer poses, the forms study's seed-5 session passed p by eight orders at
    the poses asked and still had a fold where the error rose."""
    best = best_form(rows)
    if kept or best is None or best["score"] < min_gain or best["p_value"] < threshold:
        return None
    poses_needed = poses_to_pass(best["lm_statistic"], best["df"], poses, threshold / 2)
    return None if poses_needed is None else {"effect": best["effect"], "poses": poses_needed,
                                                "lm_statistic": best["lm_statistic"], "df": best["df"]}


def _cross_validated(table: PoseTable, effects: Sequence[str], folds: int, seed: int,
                     fit_kwargs: Callable[[int], dict] | None, fitted: "_Fits | None") -> Any:
    """The cross-validation of the model of `effects` (`pipeline.cross_validate`), done once
    per set of effects in `fitted`: the selection asks for the same model again and again (the
    model of all kept, given each of them in turn; a base model for each candidate), and these
    refits were most of a diagnosis' time (56 of 89 s on 300 poses of the paper's Experiment
    II). The first fit of a set stands for it, whichever warm start it had: where the data
    determine the model they converge alike, and where two of its effects share a direction
    (a range scale within a strain) one fit of a model is as good as another, and each test
    given that model now sees the same one."""
    from posecorr.train.folds import IN_PROCESS
    from posecorr.train.pipeline import CorrectionPipeline, cross_validate
    from posecorr.train.splits import KFold

    key = frozenset(effects)
    if fitted is not None and key in fitted:
        return fitted[key]
    cv = cross_validate(lambda: CorrectionPipeline(list(effects)), table, KFold(folds), seed, fit_kwargs=fit_kwargs,
                        pool=fitted.pool if fitted is not None else IN_PROCESS)
    if fitted is not None:
        for model in cv.fitted:     # kept for the whole diagnosis: without what only a prior's shrink reads
            model.physics_.forget_free_fit()
        fitted[key] = cv
    return cv


def _fold_state(table: PoseTable, effects: list[str], names: Sequence[str], splits: list, folds: int,
                seed: int, warm: list[dict] | None = None, fitted: "_Fits | None" = None) -> _FoldState:
    measured, reference, t = table.measured, table.reference, table.time()
    with_rotation = table.has_orientation
    names = [n for n in names if n not in effects]
    if effects:
        cv = _cross_validated(table, effects, folds, seed, (lambda k: {"warm_start": warm[k]}) if warm else None,
                              fitted)
        predicted, fold_rmse = cv.predicted, cv.fold_rmse
    else:
        cv, predicted = None, measured
        fold_rmse = np.array([rmse_total(*pose_errors(reference[h], measured[h], with_rotation)) for _, h in splits])
    per_fold = []
    for k, (train, held) in enumerate(splits):
        physics = _base_physics(cv, k, table, train, effects)
        r, J, is_extra = physics.residual_jacobian(measured[held], reference[held],
                                                   None if t is None else t[held], names)
        per_fold.append(_Fold.of(r, J, is_extra, physics))
    before = rmse_total(*pose_errors(reference, predicted, with_rotation))
    return _FoldState(effects, predicted, fold_rmse, before, per_fold, _column_owners(per_fold[0].physics, names))


# The part of the test a candidate fails when its held-out error rises in some fold (the
# words `failed_parts` gives it; `proposal.explain_absent` adds the worst fold's figure).
FOLD_RISES = "a fold where the error rises"


def failed_parts(p_value: float, fold_gain_min: float, score: float, n_candidates: int, alpha: float,
                 min_gain: float) -> list[str]:
    """The parts of the test (`PRESENT_TEST`, alone) a candidate fails, each with its figure:
    none when it passes."""
    threshold = p_threshold(alpha, n_candidates)
    parts = []
    if not p_value < threshold:
        parts.append(f"p above {threshold:.2g} ({alpha:g} over {n_candidates} candidates)")
    if not fold_gain_min > 0:
        parts.append(FOLD_RISES)
    if not score >= min_gain:
        parts.append(f"a mean gain below {min_gain:.1%}")
    return parts


def _evaluate(table: PoseTable, state: _FoldState, name: str, n_candidates: int, alpha: float, min_gain: float,
              folds: int, seed: int, fitted: "_Fits | None" = None) -> dict[str, Any]:
    """The score and prediction tests and the held-out gain of adding `name` to the state's
    model (its cross-validation kept in `fitted`, `_cross_validated`)."""
    from scipy.stats import chi2, norm

    from posecorr.train.splits import KFold

    g, info, variance = 0.0, 0.0, state.residual_variance
    for fold, Je in zip(state.per_fold, state.held_off(name)):
        g = g + Je.T @ fold.r_off
        info = info + Je.T @ Je
    pinv, rank = _pinv_rank(np.atleast_2d(info))
    lm = float(g @ pinv @ g / variance) if rank and variance > 0 else 0.0
    p_local = float(chi2.sf(lm, rank)) if rank else 1.0

    warm = (lambda k: {"warm_start": state.per_fold[k].physics.params_}) if state.effects else None
    plan = KFold(folds)
    cv = _cross_validated(table, state.effects + [name], folds, seed, warm, fitted)
    splits = plan.folds(table.n, seed)
    gains = np.array([_whitened_gain(table, held, state.predicted, cv.predicted, state.per_fold[k].physics)
                      for k, (_, held) in enumerate(splits)])
    z = _prediction_z(table, state, name, cv, splits)
    p_predictive = float(norm.sf(z))
    # The score test sees the candidate's Jacobian at identity: a large nonlinear effect (a
    # mount turned half a turn) reaches out of that tangent plane, and only its refit shows
    # it. Either test may carry the evidence; Bonferroni over the two.
    p_value = min(1.0, 2.0 * min(p_local, p_predictive))
    effect = get_effect(name)
    # A physical explanation must take physical values in every fold (`Param.plausible`), where
    # the fold's data determines them (the standard errors, computed only for a value outside).
    worst: dict[str, str] = {}   # one line per parameter: its farthest value over the folds
    for model in sorted(cv.fitted, key=lambda m: -np.abs(m.physics_.params_[name]).max()):
        theta = model.physics_.params_[name]
        if effect.implausible(theta):
            for words in effect.implausible(theta, model.physics_.std_errors_[name]):
                worst.setdefault(words.split(" = ")[0], words)
    implausible = list(worst.values())
    return {"effect": name, "kind": "form" if effect.generic else "effect", "parameters": effect.size,
            "score": float(np.mean(gains)), "p_value": p_value, "lm_statistic": lm, "df": rank,
            "p_local": p_local, "prediction_z": z, "p_predictive": p_predictive,
            "cv_rmse_before": state.before, "cv_rmse_after": float(cv.metrics["rmse_total"]),
            "cv_rmse_pos_after": float(cv.metrics["rmse_pos"]), "fold_gain_min": float(gains.min()),
            "passes": not failed_parts(p_value, float(gains.min()), float(np.mean(gains)), n_candidates, alpha,
                                       min_gain),
            "implausible": implausible,
            "fold_params": [model.physics_.params_ for model in cv.fitted]}


def _prediction_z(table: PoseTable, state: _FoldState, name: str, cv: Any, splits: list) -> float:
    """The held-out prediction test's statistic: does the change of residual the candidate
    makes, fitted without the held-out poses, predict the base model's residual there? In
    each fold the change d = r_base - r_candidate on the held-out poses (both whitened by the
    base fold's sigmas) and r_base are projected off what the base fit can move; pooled,
    z = sum d'.r' / (s |d'| sqrt(c)), s^2 the score test's residual variance: the score
    statistic of lambda in r = lambda d + noise (forecast encompassing). Under "not missing"
    d is fixed by the other folds' poses, independent of the held-out noise; but the pooled
    sum also holds those folds' residuals, so its terms are correlated, and c >= 1
    (`fold_sharing`) scales the variance for it (without c, p ran below its level on null
    sessions: `calibration` in the forms bench). Like the score test's statistic, z^2 never
    exceeds m."""
    t = table.time()
    num = den = 0.0
    for k, (_, held) in enumerate(splits):
        fold = state.per_fold[k]
        after = cv.fitted[k].physics_.whitened_residual(
            table.measured[held], table.reference[held], None if t is None else t[held],
            sigmas=(fold.physics.sigma_p_, fold.physics.sigma_r_))
        change = _project_off((fold.r - after)[:, None], fold.base)[:, 0]
        num += float(change @ fold.r_off)
        den += float(change @ change)
    variance = state.residual_variance
    if not (den > 0 and variance > 0):
        return 0.0
    return num / np.sqrt(den * variance * max(fold_sharing(state, name), 1.0))


def fold_sharing(state: _FoldState, name: str) -> float:
    """How much the prediction test's pooled sum varies beyond what its folds alone would.

    Fold k's change d_k is fitted on the other folds' poses, so it holds their noise, and the
    term d_j . r_j of a fold j among them holds that noise too: the terms are correlated,
    and treating d as fixed (the denominator s |d|) understates the sum's variance. On the
    model linearised at the base fits (each fold's Jacobian on its held-out rows, stacked for
    the rows the fold was fitted on), with white noise of variance s^2, the sum is
    S = sum_k e_k' M_kj e_j over pairs of folds, M_kj = A_k B_kj': A_k = P_k J_k G_k (the
    candidate's columns on fold k's rows, off what its base can move, times the inverse of
    their information on its training rows) and B_kj the candidate's columns, off the base,
    on fold j's rows of fold k's training stack. Then var S = s^4 sum_{k<j} |M_kj + M_jk'|^2
    while "d fixed" counts s^4 sum_{k<j} (|M_kj|^2 + |M_jk|^2); this returns their ratio
    (0 to 2; 1 where the folds share nothing). Only q x q products: a table of thousands of
    poses forms no rows x rows matrix."""
    folds = state.per_fold
    owner = state.column_owner
    A, B = [], []
    for k, (fold, held) in enumerate(zip(folds, state.held_off(name))):
        others = [j for j in range(len(folds)) if j != k]
        base = np.vstack([folds[j].J[:, ~folds[j].is_extra] for j in others]) @ fold.physics.directions_
        candidate = _project_off(np.vstack([folds[j].J[:, owner == name] for j in others]), _orthonormal_basis(base))
        inverse, _ = _pinv_rank(np.atleast_2d(candidate.T @ candidate))
        A.append(held @ inverse)
        rows = np.cumsum([0] + [folds[j].r.size for j in others])
        B.append({j: candidate[rows[i]:rows[i + 1]] for i, j in enumerate(others)})
    fixed = shared = 0.0
    for k in range(len(folds)):
        for j in range(k + 1, len(folds)):
            # |A B'|^2 = tr(A'A B'B); tr(M_kj M_jk) = tr(B_jk' A_k B_kj' A_j)
            own_k = float(np.trace((A[k].T @ A[k]) @ (B[k][j].T @ B[k][j])))
            own_j = float(np.trace((A[j].T @ A[j]) @ (B[j][k].T @ B[j][k])))
            cross = float(np.trace((B[j][k].T @ A[k]) @ (B[k][j].T @ A[j])))
            fixed += own_k + own_j
            shared += own_k + own_j + 2.0 * cross
    return shared / fixed if fixed > 0 else 1.0


# Rows a diagnosis runs on at most (drawn evenly from a longer table).
MAX_ROWS = 5000
# Two forms whose held-out gains lie within this fraction of each other, each adding nothing
# given the other, cannot be told apart by the data: nothing is proposed.
INDISTINCT_GAIN = 0.1


class _Fits(dict):
    """Each model's cross-validation, by its set of effects (`_cross_validated`), and the
    processes their folds are fitted in."""

    def __init__(self, pool: Any) -> None:
        super().__init__()
        self.pool = pool


@dataclass
class _Search:
    """What the selection needs at every step: the data, the base model's folds and the test."""

    table: PoseTable
    effects: list[str]
    names: list[str]
    splits: list
    folds: int
    seed: int
    alpha: float
    min_gain: float
    say: Callable[[str], None]
    base: "_FoldState"
    fitted: "_Fits"

    def evaluate(self, name: str, state: "_FoldState") -> dict[str, Any]:
        """The test of `name` added to the cross-validated model `state`."""
        return _evaluate(self.table, state, name, len(self.names), self.alpha, self.min_gain, self.folds, self.seed,
                         self.fitted)

    def given(self, name: str, others: Sequence[str], warm: list[dict] | None = None) -> dict[str, Any]:
        """The test of `name` added to the model of the effects and `others`."""
        state = _fold_state(self.table, self.effects + list(others), self.names, self.splits, self.folds,
                            self.seed, warm, self.fitted)
        return self.evaluate(name, state)


def _earns(row: dict[str, Any]) -> bool:
    return row["passes"] and not row["implausible"]


def row_failed_parts(search: Any, row: dict[str, Any]) -> list[str]:
    """`failed_parts` of a candidate's row, at the threshold of `search` (its candidates
    `names`, `alpha`, `min_gain`)."""
    return failed_parts(row["p_value"], row["fold_gain_min"], row["score"], len(search.names), search.alpha,
                        search.min_gain)


def _failures(search: _Search, row: dict[str, Any]) -> list[str]:
    """Why `row` does not earn its place: the parts of the test it fails, then its values
    that are not physical."""
    return row_failed_parts(search, row) + list(row["implausible"])


def _forward(search: _Search, rows: list[dict[str, Any]]) -> list[str]:
    """Walk down the ranking; a candidate that passes alone is kept if it still passes given
    those kept before it (a missing station rotation makes a sweep phase look useful until
    the station is in)."""
    accepted: list[str] = []
    warm: list[dict] | None = None
    for row in rows:
        if _earns(row) and accepted:
            search.say(f"candidate {row['effect']} given {', '.join(accepted)}")
            conditional = search.given(row["effect"], accepted, warm)
            _record_given(search, row, accepted, conditional)
            if not _earns(conditional):
                continue
        if _earns(row):
            accepted.append(row["effect"])
            warm = row["fold_params"]
    return accepted


def _record_given(search: _Search, row: dict[str, Any], others: list[str], conditional: dict[str, Any]) -> None:
    row.update(given=list(others), p_value_given=conditional["p_value"], score_given=conditional["score"],
               passes_given=_earns(conditional), implausible_given=conditional["implausible"],
               fails_given=_failures(search, conditional))


def _second_chance(search: _Search, rows: list[dict[str, Any]], accepted: list[str],
                   dropped: set[str] = frozenset()) -> list[str]:
    """A catalogue effect that failed alone, tested again given all that is kept, until none
    joins. Frames nobody registered: alone, a robot session's mount gains 1.2 % with one fold
    0.06 % worse, for the station's error swamps it; given the station it gains 99.5 % in
    every fold. Likewise a form: a range scale of 0.4 % under a bend of the space gains 1.1 %
    alone with a fold 0.1 % worse, and given the quadratic that takes the bend, every fold.
    Also one that earned alone but was tested given an effect no longer kept (dropped, or a
    form that gave way): its record would explain its absence by a model that is not the one
    named. Backward elimination then tests each kept given the others; what it (or `_rivals`)
    has `dropped` is not tested again."""
    while True:
        context = list(accepted)
        waiting = [row for row in rows if row["effect"] not in accepted and row["effect"] not in dropped
                   and not get_effect(row["effect"]).generic
                   and (not _earns(row) or not set(row.get("given", ())) <= set(context))
                   and row.get("given") != context]
        if not context:   # nothing kept to test them given: their test alone says why they are not
            for row in waiting:
                _settle_given(search, row, [], {})
            return accepted
        if not waiting:
            return accepted
        for row in waiting:
            search.say(f"candidate {row['effect']} given {', '.join(context)}")
            conditional = search.given(row["effect"], context)
            _record_given(search, row, context, conditional)
            if _earns(conditional):
                accepted.append(row["effect"])
                break   # the context has changed: those still waiting are tested given it
        else:
            return accepted


def _backward(search: _Search, accepted: list[str], by_name: dict[str, dict]) -> tuple[list[str], list[dict]]:
    """Each kept candidate tested given all the others kept (backward elimination): while some
    fail, drop one (a form before a catalogue effect, so a physical explanation that does the
    form's work stays; then the smallest gain) and test again. Returns what stays and the
    record of each drop."""
    accepted, dropped = list(accepted), []
    while len(accepted) > 1:
        tests = {}
        for name in accepted:
            search.say(f"candidate {name} given the others kept")
            tests[name] = search.given(name, [a for a in accepted if a != name])
        failing = [name for name in accepted if not _earns(tests[name])]
        if not failing:
            break
        drop = min(failing, key=lambda name: (not get_effect(name).generic, tests[name]["score"]))
        others = [a for a in accepted if a != drop]
        twins = [name for name in failing if name != drop and get_effect(name).generic and get_effect(drop).generic
                 and abs(by_name[name]["score"] - by_name[drop]["score"])
                 <= INDISTINCT_GAIN * max(by_name[name]["score"], by_name[drop]["score"])]
        dropped.append({"effect": drop, "given": others, "p_value_given": tests[drop]["p_value"],
                        "score_given": tests[drop]["score"], "implausible_given": tests[drop]["implausible"],
                        "fails_given": _failures(search, tests[drop]), "indistinct_from": twins})
        accepted.remove(drop)
    return accepted, dropped


def _rivals(search: _Search, accepted: list[str], by_name: dict[str, dict]) -> tuple[list[str], list[dict]]:
    """Each kept candidate tested given a catalogue effect not kept that may explain the same
    error (backward elimination tests it given those kept only), one with physical values:
    - a form kept gives way to a catalogue effect that passes given the others kept and
      leaves the form nothing: a drift over the session (tau 3600 s, a UR5e's 40 poses, seed
      8) that the form linear and quadratic in t takes whole, 9.7 % against drift's 8.6 % held
      out; the drift failed given it, and the form was proposed;
    - a catalogue effect kept is not named where another not kept gains at least as much
      given the others kept (within `INDISTINCT_GAIN`) and leaves it nothing: a range scale of
      0.25 % (a UR5e's 40 poses, seed 4) gains 16 % alone with one fold 3.4 % worse, and the
      incidence bias that took its place passed; the data cannot tell them apart.
    Returns what stays and the record of each drop, as `_backward`'s."""
    accepted, dropped = list(accepted), []

    def beside(name: str, others: list[str]) -> dict[str, Any]:
        return search.given(name, others) if others else by_name[name]

    for name in list(accepted):
        form = get_effect(name).generic
        others = [a for a in accepted if a != name]
        own = beside(name, others)
        for rival in by_name.values():
            if (rival["effect"] in accepted or get_effect(rival["effect"]).generic or rival["implausible"]
                    or rival["score"] < search.min_gain):
                continue
            context = beside(rival["effect"], others)
            if context["implausible"] or not (_earns(context) if form
                                              else context["score"] >= (1.0 - INDISTINCT_GAIN) * own["score"]):
                continue
            search.say(f"candidate {name} given {', '.join(others + [rival['effect']])}")
            test = search.given(name, others + [rival["effect"]])
            if _earns(test):
                continue
            record = {"effect": name, "given": others + [rival["effect"]], "p_value_given": test["p_value"],
                      "score_given": test["score"], "implausible_given": test["implausible"],
                      "fails_given": _failures(search, test), "indistinct_from": [],
                      "scores": {name: own["score"], rival["effect"]: context["score"]}}
            if form:
                accepted[accepted.index(name)] = rival["effect"]
                _settle_given(search, rival, others, context)
                record["gave_way_to"] = rival["effect"]
            else:   # the other way round too: where the rival adds more, the data tells them apart
                accepted.remove(name)
                search.say(f"candidate {rival['effect']} given {', '.join(others + [name])}")
                back = search.given(rival["effect"], others + [name])
                record.update(told_apart_from=rival["effect"], rival_given={
                    "score_given": back["score"], "p_value_given": back["p_value"],
                    "fails_given": _failures(search, back),
                    "adds": set(row_failed_parts(search, back)) <= {FOLD_RISES}})
            dropped.append(record)
            break
    return accepted, dropped


def _settle_given(search: _Search, row: dict[str, Any], others: list[str], context: dict[str, Any]) -> None:
    """`row`'s record of its test given `others` (the test `context`), or with no others none:
    its test alone then says why it is kept (taking a form's place: its forward test given
    that form no longer does) or not (everything it was tested given has been dropped)."""
    if others:
        _record_given(search, row, others, context)
    else:
        for key in ("given", "p_value_given", "score_given", "passes_given", "implausible_given", "fails_given"):
            row.pop(key, None)


def _rival_words(record: dict[str, Any]) -> str:
    """The note on a candidate `_rivals` dropped: the gains of both, what the dropped one does
    given the other, and, for two catalogue effects, what the other does given it: where it
    adds more, though it fails the test, the data tells them apart."""
    def moves(gain: float, p: float) -> str:
        return (f"gains {gain:.1%}" if gain >= 0 else f"raises the held-out whitened error by {-gain:.1%}") \
            + f" (p = {p:.2g})"

    name = record["effect"]
    rival = record.get("gave_way_to") or record["told_apart_from"]
    others = [g for g in record["given"] if g != rival]
    where = f"given {', '.join(others)}" if others else "alone"
    scores = f"{name} gains {record['scores'][name]:.1%} {where} and {rival} {record['scores'][rival]:.1%}"
    given = f"given {rival}, {name} {moves(record['score_given'], record['p_value_given'])}"
    if "gave_way_to" in record:
        return (f"{scores}, but {given}: {rival}, the catalogue's physical effect, explains the same error, and is "
                "named instead of the form")
    back = record["rival_given"]
    back_words = f"given {name}, {rival} {moves(back['score_given'], back['p_value_given'])}"
    if back["adds"]:
        return (f"{name} is not named: {scores}; {given}, and {back_words}: {rival} explains {name}'s gain and "
                f"more, but is not named either ({'; '.join(back['fails_given'])})")
    return f"{name} and {rival} cannot be told apart by this data: {scores}; {given}, and {back_words}; neither is named"


def require_diagnosable(table: PoseTable, folds: int) -> None:
    """ValueError (TableError for the table's own faults) when `table` cannot be diagnosed with
    `folds` folds, naming the folds that can or the rows it takes."""
    from posecorr.data import TableError, require_rows
    from posecorr.train.pipeline import check_outliers
    from posecorr.train.splits import (MIN_FIT_POSES, KFold, fewest_rows_to_fit, fewest_to_fit,
                                       require_enough_to_fit)

    if table.n < folds:
        fewer = [k for k in range(table.n, 1, -1) if fewest_to_fit(table.n, KFold(k)) >= MIN_FIT_POSES]
        fewest = fewest_rows_to_fit()
        if not fewer:   # no number of folds will do: the one minimum that matters
            raise TableError(table.path, f"{counted(table.n, 'row')}, but a diagnosis takes at least {fewest} "
                                         f"(with --cv {fewest})")
        raise TableError(table.path, f"{counted(table.n, 'row')}, but a {folds}-fold diagnosis needs at least "
                                     f"{folds}: fewer folds (--cv {fewer[0]})")
    require_rows(table, max(folds, 2), f"a {folds}-fold diagnosis", outliers=check_outliers)
    require_enough_to_fit(table.n, KFold(folds))


def _unregistered_words(table: PoseTable) -> str | None:
    """Where the frames are unregistered (`metrics.frames_unregistered` against the best
    in-sample rigid fit), the figures in words; None where they are not."""
    from .comparison import rigid_in_sample

    raw = pose_metrics(table.reference, table.measured, table.has_orientation)
    rigid_name, rigid = rigid_in_sample(table, None)
    fitted = pose_metrics(table.reference, rigid, table.has_orientation)
    if not frames_unregistered(raw, fitted):
        return None
    return (f"the frames are unregistered (raw rmse_pos {1e3 * raw['rmse_pos']:.3g} mm, the rigid fit's "
            f"{1e3 * fitted['rmse_pos']:.3g} mm in-sample, {rigid_name})")


def station_bound_words(names: Sequence[str], station_pose: str | None = None) -> str | None:
    """What a verdict on the effects among `names` that bend about the base station
    (`Effect.about_station`) rests on, naming them in the order they apply: the station the
    session states (`station_pose`), or on unregistered frames the nominal one, which they do
    not place; None where there are none."""
    from posecorr.geometry import parse_station_pose

    bound = sorted({name for name in names if get_effect(name).about_station}, key=lambda name: get_effect(name).order)
    if not bound:
        return None
    one = len(bound) == 1
    stated = parse_station_pose(station_pose)
    named = bound[0] if one else f"{', '.join(bound[:-1])} and {bound[-1]}"
    if station_pose is not None:
        return f"{named} {'is' if one else 'are'} taken about the stated base station, at {stated.words()}"
    where = ", ".join(f"{x:.2f}" for x in stated.t)
    return (f"{named} {'bends' if one else 'bend'} about where the base station stands, which unregistered "
            f"frames do not say: {'it is' if one else 'they are'} taken about the nominal station (the paper's, at "
            f"({where}) m in the reference frame), so a verdict on {'it' if one else 'them'} holds only if yours "
            "stands there")


def _with_registration(effects: list[str], candidates: Sequence[str] | None, unregistered: str | None
                       ) -> tuple[list[str], str | None]:
    """(the model's effects, a note or None): where the frames are unregistered and the model
    holds no registration effect, the registration in front of them, as `fit`'s rigid floor
    holds it. Against the bare measurements every candidate would gain by taking up the
    frames' offset: a sweep passed given the station and the mount alone where a bend, which
    ran away fitted to metres of offset, was never tried again; a form stood in for the
    mount; a proposal quoted the registration's gain as its own. `unregistered`: the
    table's `_unregistered_words`."""
    registration = registration_names()
    if candidates is not None or unregistered is None or any(name in effects for name in registration):
        return effects, None
    return registration + effects, (f"{unregistered}: the model starts from their registration, "
                                    f"{', '.join(registration)}, as fit's rigid floor does")


def advised_effects(table: PoseTable, given: Sequence[str], effects: Sequence[str], present: Sequence[str]
                    ) -> tuple[list[str] | None, str | None]:
    """(the effects to fit next, a note or None): the model's `effects` and the catalogue
    effects present; None where that is what was `given`. Where the frames
    are unregistered and the advice holds part of the registration only, the rest joins it,
    said in the note: on a few poses turned alike the test may keep the mount and fail the
    station given it (their effects alike along most directions), and a model of a part fits
    the frames' offset worse than the rigid fit, the floor every model is compared with,
    which holds them all."""
    advice = list(effects) + [name for name in present if name not in effects]
    registration = registration_names()
    missing = [name for name in registration if name not in advice]
    unregistered = None if not missing or len(missing) == len(registration) else _unregistered_words(table)
    if unregistered is None:
        return (advice if advice != list(given) else None), None
    held = [name for name in registration if name in advice]
    note = (f"{' and '.join(missing)} {'joins' if len(missing) == 1 else 'join'} {', '.join(held)} in the advice, "
            f"though not present by the test: {unregistered}, and the rigid fit, the floor `fit` compares every "
            f"model with, holds the whole registration")
    return registration + [name for name in advice if name not in registration], note


def diagnose(table: PoseTable, effects: Sequence[str] = (), folds: int = 5, seed: int = 0,
             alpha: float = ALPHA, min_gain: float = MIN_GAIN, candidates: Sequence[str] | None = None,
             forms: bool = True, model_corrected: np.ndarray | None = None,
             progress: Callable[[str], None] | None = None, workers: int = 1) -> dict[str, Any]:
    """Rank the effects `effects` lacks, catalogue effects and generic forms on the same
    held-out poses; JSON-ready dict in the `diagnose` layout of docs/design.md.

    A candidate is `present` when it passes the test alone, still passes given those kept
    before it (forward selection), and given all the others kept (backward elimination); a
    catalogue effect also needs physically plausible values in every fold (`Param.plausible`).
    Present forms make the `proposal` (`posecorr.analysis.proposal`); present catalogue
    effects the advice to add them.
    model_corrected: (N, 7) poses of the table's rows as a given model (an ONNX file, say)
    corrects them; when given, the feature R^2 uses its residuals instead of the base physics
    model's out-of-fold ones. workers: the processes the cross-validations' folds are fitted
    in (`train.folds.FoldPool`): the same result, sooner on a large table.
    """
    from posecorr.train.folds import FoldPool

    with FoldPool(workers) as pool:
        return _diagnosed(table, list(effects), folds, seed, alpha, min_gain, candidates, forms, model_corrected,
                          progress, _Fits(pool))


def _diagnosed(table: PoseTable, effects: list[str], folds: int, seed: int, alpha: float, min_gain: float,
               candidates: Sequence[str] | None, forms: bool, model_corrected: np.ndarray | None,
               progress: Callable[[str], None] | None, fitted: "_Fits") -> dict[str, Any]:
    """`diagnose`, its cross-validations kept in `fitted`."""
    from posecorr.train.splits import KFold

    from .proposal import explain_absent, explain_absorbed, propose

    require_diagnosable(table, folds)
    require_time(effects, table)
    rows_given = table.n
    if model_corrected is not None and np.shape(model_corrected) != (table.n, 7):
        raise ValueError(f"model_corrected has shape {np.shape(model_corrected)}, expected ({table.n}, 7): "
                         f"a corrected pose for each row of the table")
    table, model_corrected = _thinned(table, model_corrected, seed)
    unregistered = _unregistered_words(table)   # the model's start and the features' alike
    effects, registered = _with_registration(list(effects), candidates, unregistered)
    names = list(candidates) if candidates is not None else candidate_effects(table, effects, forms)
    say = progress or (lambda message: None)
    say("which candidate effects this data can determine")
    names, undetermined = split_identifiable(table, effects, names)
    splits = KFold(folds).folds(table.n, seed)
    say(f"base model ({', '.join(effects) or 'no effects'}), {folds}-fold cross-validation")
    state = _fold_state(table, effects, names, splits, folds, seed, fitted=fitted)   # the search's too
    search = _Search(table, effects, names, splits, folds, seed, alpha, min_gain, say, state, fitted)
    rows, kept, dropped = _select(search)
    features, unplaced = _feature_scan(table, model_corrected if model_corrected is not None else state.predicted,
                                       folds, seed, placed=unregistered is None, tested=list(effects) + names)
    base = pose_metrics(table.reference, state.predicted, table.has_orientation)
    result = {
        "model_effects": effects,
        "candidates": rows,
        "undetermined": undetermined,
        "features": features,
        "aliases": _aliases(names, state, effects),
        "test": PRESENT_TEST.format(alpha=alpha, folds=folds, gain=min_gain, share=1.0 - INDISTINCT_GAIN),
        "folds": folds,
        "cv_base": {"rmse_total": state.before, "rmse_pos": base["rmse_pos"], "rmse_rot": base["rmse_rot"]},
        "rows": {"given": rows_given, "used": table.n},
        "reach": score_test_reach(state, len(names), alpha, table.n),
        "notes": _table_notes(table, effects, candidates, forms) + ([registered] if registered else []) + unplaced,
    }
    result["reach"]["poses_to_pass"] = _planned(rows, kept, table.n, result["reach"]["threshold"], min_gain)
    result["proposal"], result["no_proposal"] = propose(search, result, kept, dropped, not forms and candidates is None)
    result["notes"] += [_rival_words(record) for record in dropped if "scores" in record]   # `_rivals`' drops
    result["absorbed"] = explain_absorbed(result, kept)
    result["absent"] = explain_absent(search, result)
    return result


def _feature_scan(table: PoseTable, predicted: np.ndarray, folds: int, seed: int, placed: bool,
                  tested: Sequence[str]) -> tuple[list[dict[str, Any]], list[str]]:
    """(`feature_r2` of the residuals, notes): where the frames are unregistered (not `placed`)
    and the session states no station, no feature is taken from the station, whose place in
    them nobody knows; the effects `tested` that bend about it are named with the station
    they are taken about (`station_bound_words`)."""
    blocks = {name: cols for name, cols in ERROR_BLOCKS.items() if table.has_orientation or name == "position"}
    station = stated_station(table)
    features = feature_r2(residual_components(table.reference, predicted, table.has_orientation),
                          pose_features(table.reference, table.time(), placed, station), folds, seed, blocks)
    bound = station_bound_words(tested, table.station_pose)
    if station is not None:
        return features, [bound] if bound else []
    if placed:
        return features, []
    return features, [f"residual structure by feature: {UNPLACED_STATION}"] + ([bound] if bound else [])


def _thinned(table: PoseTable, corrected: np.ndarray | None,
             seed: int) -> tuple[PoseTable, np.ndarray | None]:
    """The table (and the model's corrections) on an even draw of MAX_ROWS rows when longer:
    the diagnosis costs a fit per candidate and fold, and a draw ranks the same effects."""
    if table.n <= MAX_ROWS:
        return table, corrected
    drawn, keep = table.draw(MAX_ROWS, seed)
    return drawn, None if corrected is None else np.asarray(corrected)[keep]


def rank_key(row: dict[str, Any]) -> tuple[float, float]:
    """The order forward selection walks: by score, but a catalogue effect ahead of a form
    when it gains at least 1 - `INDISTINCT_GAIN` (90 %) as much, the gains within
    `INDISTINCT_GAIN` of each other as `_backward` counts twins. A range scale of 0.5 % on a 40-pose UR5e
    session scores 0.2674 and a strain, whose three diagonal terms take it whole, 0.2680:
    walked by score alone, the strain was proposed and the range scale, given it, gained
    nothing."""
    score = row["score"]
    if score > 0 and not get_effect(row["effect"]).generic:
        score /= 1.0 - INDISTINCT_GAIN
    return -score, row["p_value"]


def _select(search: _Search) -> tuple[list[dict[str, Any]], list[str], list[dict[str, Any]]]:
    """Every candidate alone, ranked; then forward selection and backward elimination.
    Returns the ranked rows (with `rank`, `present` and any drop's record), what stays, and
    the drops."""
    rows = []
    for name in search.names:
        search.say(f"candidate {name}")
        rows.append(search.evaluate(name, search.base))
    rows.sort(key=rank_key)
    by_name = {row["effect"]: row for row in rows}
    kept, dropped = _forward(search, rows), []
    # A drop, or a form giving way to a catalogue effect, changes the context the others were
    # tested in: they are tested again in the new one, until it holds.
    for _ in range(len(rows)):
        dropped_before = {record["effect"] for record in dropped}
        kept, backed = _backward(search, _second_chance(search, rows, kept, dropped_before), by_name)
        kept, rivalled = _rivals(search, kept, by_name)
        dropped += backed + rivalled
        if not (backed or rivalled):
            break
    dropped = [record for record in dropped if record["effect"] not in kept]
    for rank_index, row in enumerate(rows, start=1):
        row["rank"] = rank_index
        row["present"] = row["effect"] in kept
        row.pop("fold_params")
    for record in dropped:
        by_name[record["effect"]]["dropped"] = record
    return rows, kept, dropped


def _whitened_gain(table: PoseTable, held: np.ndarray, before: np.ndarray, after: np.ndarray, physics: Any) -> float:
    """Relative fall of the held-out RMS of the whitened error (position / sigma_p and
    orientation / sigma_r, the fit's own objective, with the base fold's sigmas), so that a
    position-only effect is not diluted by orientation noise as it is in rmse_total."""
    def whitened(predicted: np.ndarray) -> float:
        dp, dr = pose_errors(table.reference[held], predicted[held], table.has_orientation)
        total = (dp / physics.sigma_p_) ** 2
        if dr is not None:
            total = total + (dr / physics.sigma_r_) ** 2
        return float(np.sqrt(np.mean(total)))

    b = whitened(before)
    return (b - whitened(after)) / b


def _base_physics(base_cv: Any, k: int, table: PoseTable, train: np.ndarray, effects: list[str]) -> Any:
    """The physics model of fold k (an empty one, still carrying frames and sigmas, if no effects)."""
    from posecorr.train.physics import PhysicsModel
    from posecorr.train.pipeline import session_setup

    if base_cv is not None:
        return base_cv.fitted[k].physics_
    t = table.time()
    return PhysicsModel((), **session_setup(table)._asdict()).fit(table.measured[train], table.reference[train],
                                                                     t=None if t is None else t[train])


def _column_owners(physics: Any, names: Sequence[str]) -> np.ndarray:
    from ..effects import sorted_effects

    chosen = sorted_effects(tuple(physics.params_) + tuple(names))
    return np.concatenate([np.full(e.size, e.name, dtype=object) for e in chosen])


# The score's information matrix: eigenvalues below this fraction of the largest are noise
# (up to 1e-8 across float kernels on the shared real sessions, from directions projected off
# the base), while a candidate's weakest real direction there stands at 6e-7 and more.
INFORMATION_TOLERANCE = 1e-7


def _pinv_rank(A: np.ndarray, tol: float = INFORMATION_TOLERANCE) -> tuple[np.ndarray, int]:
    U, s, Vt = np.linalg.svd(A)
    keep = s > tol * max(s.max(), 1e-300) if s.size else s.astype(bool)
    inv = (Vt[keep].T / s[keep]) @ U[:, keep].T
    return inv, int(keep.sum())


def _aliases(names: list[str], state: _FoldState, effects: list[str]) -> list[dict[str, Any]]:
    """Pairs whose column spaces (held-out rows of all folds) move the poses alike along some
    direction (`_alias`): among the catalogue's candidates (projected off the model's columns)
    and between such a candidate and a model effect."""
    pairs = []
    # A form holds catalogue effects as special cases (range_scale in strain): that nesting is
    # what the selection weighs, not an alias; aliases are between catalogue effects.
    physical = [name for name in names if not get_effect(name).generic]
    projected = {name: np.concatenate(state.held_off(name)) for name in physical}
    for i, a in enumerate(physical):
        for b in physical[i + 1:]:
            pairs.append(_alias(a, b, projected[a], projected[b]))
    full = np.concatenate([fold.J for fold in state.per_fold])
    owner = state.column_owner
    for a in physical:
        for b in effects:
            pairs.append(_alias(b, a, full[:, owner == b], full[:, owner == a]))
    return [pair for pair in pairs if pair is not None]
