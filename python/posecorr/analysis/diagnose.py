"""Which physical effect is the model missing, and where does its error live?

`diagnose(table, effects)` fits the named physics model, then, for every catalogue effect
it lacks (user effects included once loaded):

* **score test on held-out residuals** (Lagrange multiplier test): in each fold, at the
  base model fitted without that fold, the held-out whitened residuals r and Jacobian
  columns J_e of the candidate (at its identity value) are projected off the base
  model's columns; pooled over folds, g = sum J_e'^T r' and I = sum J_e'^T J_e' give
  LM = g^T I^+ g / s^2, chi-square with rank(I) degrees of freedom under "not missing";
* **cross-validated RMSE before and after** adding the effect (K folds of whole poses,
  each after-fit warm-started from that fold's base fit);
* `score`: the mean over folds of the relative fall of the held-out whitened error
  (position / sigma_p, orientation / sigma_r: the fit's own objective, so a position-only
  effect is not diluted by orientation noise as it would be in rmse_total);
* `present` only when the effect is significant AND consistent: Bonferroni-corrected
  p < `alpha` (default 1e-3 over the number of candidates), the held-out whitened error
  lower in EVERY fold, and a mean relative gain of at least `min_gain` (default 0.5 %).

Candidates are ranked by their score. Pairs of effects the
data cannot tell apart are flagged as `aliases`: the largest canonical correlation of
their (base-projected) Jacobian column spaces exceeds 0.99.

It also reports residual structure that no catalogue effect may explain: for each feature
(`posecorr.analysis.features`) the cross-validated R^2 of a smooth fit (cubic spline + ridge) of
the out-of-fold residuals (position mm, orientation mrad) on that feature alone.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from ..data import PoseTable
from ..metrics import pose_errors, rmse_total
from ..rotations import matrix_to_rotvec, quat_to_matrix
from .features import FEATURES, pose_features

ALIAS_CORRELATION = 0.99
PRESENT_TEST = ("score (Lagrange multiplier) test on held-out residuals, Bonferroni-corrected p < {alpha:g}; "
                "held-out whitened error lower in every one of {folds} folds; mean gain >= {gain:.1%}")


def candidate_effects(table: PoseTable, effects: Sequence[str]) -> list[str]:
    """Registered, fittable effects not in `effects` (drift only when the table has time)."""
    from ..effects import EFFECTS

    out = []
    for name, effect in EFFECTS.items():
        if name in effects or effect.random:
            continue
        if effect.needs_time and table.time() is None:
            continue
        out.append(name)
    return out


def split_identifiable(table: PoseTable, effects: Sequence[str],
                       names: Sequence[str]) -> tuple[list[str], list[dict[str, Any]]]:
    """(candidates the data can determine, [{"effect", "reason"}] of those it cannot): a
    candidate whose every parameter the identification of the model with it added holds
    (`PhysicsModel.identifiability`) would only be ranked by noise, so it is not ranked."""
    from posecorr.train.physics import PhysicsModel

    keep, undetermined = [], []
    for name in names:
        fixed = PhysicsModel(tuple(effects) + (name,), with_rotation=table.has_orientation).identifiability(
            table.measured, table.reference, table.time())
        from ..effects import get_effect

        held = [key for key in fixed if key.split(" ")[0].split(".")[0] == name]
        whole = {key.split(" ")[0] for key in held if " along " not in key}
        if whole >= {f"{name}.{p.name}" for p in get_effect(name).params}:
            undetermined.append({"effect": name, "reason": "; ".join(f"{k}: {fixed[k]}" for k in held)})
        else:
            keep.append(name)
    return keep, undetermined


def residual_components(reference: np.ndarray, predicted: np.ndarray, with_rotation: bool) -> np.ndarray:
    """(N, 3 or 6): position error (mm) and orientation error as a rotation vector (mrad)."""
    parts = [(predicted[:, :3] - reference[:, :3]) * 1e3]
    if with_rotation:
        dR = np.swapaxes(quat_to_matrix(reference[:, 3:7]), -1, -2) @ quat_to_matrix(predicted[:, 3:7])
        parts.append(matrix_to_rotvec(dR) * 1e3)
    return np.concatenate(parts, axis=1)


def feature_r2(residuals: np.ndarray, features: dict[str, np.ndarray], folds: int = 5,
               seed: int = 0) -> list[dict[str, Any]]:
    """Cross-validated R^2 of a smooth fit of the residuals on each feature alone, best first."""
    from sklearn.linear_model import Ridge
    from sklearn.model_selection import KFold, cross_val_predict
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import OneHotEncoder, SplineTransformer

    centred = residuals - residuals.mean(axis=0)
    total = float(np.sum(centred ** 2))
    out = []
    for name in FEATURES:
        if name not in features:
            continue
        x = np.asarray(features[name], float).reshape(-1, 1)
        distinct = np.unique(x).size
        if distinct < 2 or total == 0.0:
            out.append({"feature": name, "r2": 0.0})
            continue
        # A lattice feature with few distinct values (Exp III roll: 3) is a category.
        encoder = (OneHotEncoder(handle_unknown="ignore") if distinct <= 8
                   else SplineTransformer(n_knots=8, degree=3, extrapolation="linear"))
        model = make_pipeline(encoder, Ridge(alpha=1e-3))
        cv = KFold(n_splits=folds, shuffle=True, random_state=seed)
        predicted = cross_val_predict(model, x, residuals, cv=cv)
        r2 = 1.0 - float(np.sum((residuals - predicted) ** 2)) / total
        out.append({"feature": name, "r2": max(r2, 0.0)})
    return sorted(out, key=lambda row: -row["r2"])


def _orthonormal_basis(A: np.ndarray, tol: float = 1e-8) -> np.ndarray:
    if A.size == 0:
        return A
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    return U[:, s > tol * max(s.max(), 1e-300)]


def _max_canonical_correlation(A: np.ndarray, B: np.ndarray) -> float:
    QA, QB = _orthonormal_basis(A), _orthonormal_basis(B)
    if QA.shape[1] == 0 or QB.shape[1] == 0:
        return 0.0
    return float(np.linalg.svd(QA.T @ QB, compute_uv=False).max())


def _project_off(A: np.ndarray, basis: np.ndarray) -> np.ndarray:
    return A - basis @ (basis.T @ A) if basis.size else A


@dataclass
class _FoldState:
    """A base model cross-validated: each fold's fit, held-out residuals and Jacobians."""

    effects: list[str]
    predicted: np.ndarray                  # out-of-fold corrected poses
    fold_rmse: np.ndarray                  # held-out rmse_total per fold
    before: float                          # pooled held-out rmse_total
    per_fold: list[tuple[np.ndarray, np.ndarray, np.ndarray, Any]]   # (r, J, is_extra, physics)
    column_owner: np.ndarray               # effect name of each Jacobian column


def _fold_state(table: PoseTable, effects: list[str], names: Sequence[str], splits: list, folds: int,
                seed: int, warm: list[dict] | None = None) -> _FoldState:
    from posecorr.train.pipeline import CorrectionPipeline, cross_validate
    from posecorr.train.splits import KFold

    measured, reference, t = table.measured, table.reference, table.time()
    with_rotation = table.has_orientation
    names = [n for n in names if n not in effects]
    if effects:
        fit_kwargs = (lambda k: {"warm_start": warm[k]}) if warm else None
        cv = cross_validate(lambda: CorrectionPipeline(effects), table, KFold(folds), seed, fit_kwargs=fit_kwargs)
        predicted, fold_rmse = cv.predicted, cv.fold_rmse
    else:
        cv, predicted = None, measured
        fold_rmse = np.array([rmse_total(*pose_errors(reference[h], measured[h], with_rotation)) for _, h in splits])
    per_fold = []
    for k, (train, held) in enumerate(splits):
        physics = _base_physics(cv, k, table, train, effects)
        r, J, is_extra = physics.residual_jacobian(measured[held], reference[held],
                                                   None if t is None else t[held], names)
        per_fold.append((r, J, is_extra, physics))
    before = rmse_total(*pose_errors(reference, predicted, with_rotation))
    return _FoldState(effects, predicted, fold_rmse, before, per_fold, _column_owners(per_fold[0][3], names))


def _evaluate(table: PoseTable, state: _FoldState, name: str, n_candidates: int, alpha: float, min_gain: float,
              folds: int, seed: int) -> dict[str, Any]:
    """Score test and held-out gain of adding `name` to the state's model."""
    from scipy.stats import chi2

    from posecorr.train.pipeline import CorrectionPipeline, cross_validate
    from posecorr.train.splits import KFold

    g, info, ss, m = 0.0, 0.0, 0.0, 0
    for r, J, is_extra, _ in state.per_fold:
        base_basis = _orthonormal_basis(J[:, ~is_extra])
        Je = _project_off(J[:, state.column_owner == name], base_basis)
        rp = _project_off(r[:, None], base_basis)[:, 0]
        g = g + Je.T @ rp
        info = info + Je.T @ Je
        ss += float(rp @ rp)
        m += r.size - base_basis.shape[1]
    pinv, rank = _pinv_rank(np.atleast_2d(info))
    lm = float(g @ pinv @ g / (ss / max(m, 1))) if rank else 0.0
    p_value = float(chi2.sf(lm, rank)) if rank else 1.0

    warm = (lambda k: {"warm_start": state.per_fold[k][3].params_}) if state.effects else None
    plan = KFold(folds)
    cv = cross_validate(lambda: CorrectionPipeline(state.effects + [name]), table, plan, seed, fit_kwargs=warm)
    gains = np.array([_whitened_gain(table, held, state.predicted, cv.predicted, state.per_fold[k][3])
                      for k, (_, held) in enumerate(plan.folds(table.n, seed))])
    significant = p_value < alpha / max(n_candidates, 1)
    return {"effect": name, "score": float(np.mean(gains)), "p_value": p_value, "lm_statistic": lm, "df": rank,
            "cv_rmse_before": state.before, "cv_rmse_after": float(cv.metrics["rmse_total"]),
            "cv_rmse_pos_after": float(cv.metrics["rmse_pos"]), "fold_gain_min": float(gains.min()),
            "present": bool(significant and np.all(gains > 0) and np.mean(gains) >= min_gain),
            "fold_params": [model.physics_.params_ for model in cv.fitted]}


# Rows a diagnosis runs on at most (drawn evenly from a longer table).
MAX_ROWS = 5000


def diagnose(table: PoseTable, effects: Sequence[str] = (), folds: int = 5, seed: int = 0,
             alpha: float = 1e-3, min_gain: float = 0.005, candidates: Sequence[str] | None = None,
             model_predict: Callable[[np.ndarray], np.ndarray] | None = None,
             progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Rank the effects `effects` lacks; JSON-ready dict in the `diagnose` layout of docs/design.md.

    Forward selection keeps partial look-alikes out: walking down the ranking, a candidate
    that passes is re-tested with the effects already found present added to the model
    (a missing station rotation makes a sweep phase look useful until the station is in).
    model_predict: corrected poses of a given model (an ONNX file, say); when given, the
    feature R^2 uses its residuals instead of the base physics model's out-of-fold ones.
    """
    from posecorr.data import require_rows
    from posecorr.train.splits import KFold

    require_rows(table, max(folds, 2), f"a {folds}-fold diagnosis")
    rows_given = table.n
    if table.n > MAX_ROWS:
        # Its cost grows with the rows (a fit per candidate and fold): a long recording is
        # diagnosed on an even draw of MAX_ROWS of them, which ranks the same effects.
        drawn, keep = table.draw(MAX_ROWS, seed)
        if model_predict is not None:
            corrected = np.asarray(model_predict(table.measured))
            model_predict = lambda measured: corrected[keep]  # noqa: E731
        table = drawn
    effects = list(effects)
    names = list(candidates) if candidates is not None else candidate_effects(table, effects)
    say = progress or (lambda message: None)
    say("which candidate effects this data can determine")
    names, undetermined = split_identifiable(table, effects, names)
    splits = KFold(folds).folds(table.n, seed)
    say(f"base model ({', '.join(effects) or 'no effects'}), {folds}-fold cross-validation")
    state = _fold_state(table, effects, names, splits, folds, seed)
    rows = []
    for name in names:
        say(f"candidate {name}")
        rows.append(_evaluate(table, state, name, len(names), alpha, min_gain, folds, seed))
    rows.sort(key=lambda row: (-row["score"], row["p_value"]))

    accepted: list[str] = []
    warm_accepted: list[dict] | None = None
    for row in rows:
        if row["present"] and accepted:
            say(f"candidate {row['effect']} given {', '.join(accepted)}")
            given = _fold_state(table, effects + accepted, names, splits, folds, seed, warm_accepted)
            conditional = _evaluate(table, given, row["effect"], len(names), alpha, min_gain, folds, seed)
            row["present"] = conditional["present"]
            row["given"] = list(accepted)
            row["p_value_given"] = conditional["p_value"]
            row["score_given"] = conditional["score"]
        if row["present"]:
            accepted.append(row["effect"])
            warm_accepted = row["fold_params"]
    for rank_index, row in enumerate(rows, start=1):
        row["rank"] = rank_index
        row.pop("fold_params")

    aliases = _aliases(names, state, effects)
    residual_pred = model_predict(table.measured) if model_predict is not None else state.predicted
    feats = pose_features(table.reference, table.time())
    features = feature_r2(residual_components(table.reference, residual_pred, table.has_orientation),
                          feats, folds, seed)
    dp, _ = pose_errors(table.reference, state.predicted, table.has_orientation)
    return {
        "model_effects": effects,
        "candidates": rows,
        "undetermined": undetermined,
        "features": features,
        "aliases": aliases,
        "test": PRESENT_TEST.format(alpha=alpha, folds=folds, gain=min_gain),
        "folds": folds,
        "cv_base": {"rmse_total": state.before, "rmse_pos": float(np.sqrt(np.mean(dp ** 2)))},
        "rows": {"given": rows_given, "used": table.n},
    }


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

    if base_cv is not None:
        return base_cv.fitted[k].physics_
    t = table.time()
    return PhysicsModel((), with_rotation=table.has_orientation).fit(table.measured[train], table.reference[train],
                                                                     t=None if t is None else t[train])


def _column_owners(physics: Any, names: Sequence[str]) -> np.ndarray:
    from ..effects import sorted_effects

    chosen = sorted_effects(tuple(physics.params_) + tuple(names))
    return np.concatenate([np.full(e.size, e.name, dtype=object) for e in chosen])


def _pinv_rank(A: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, int]:
    U, s, Vt = np.linalg.svd(A)
    keep = s > tol * max(s.max(), 1e-300) if s.size else s.astype(bool)
    inv = (Vt[keep].T / s[keep]) @ U[:, keep].T
    return inv, int(keep.sum())


def _aliases(names: list[str], state: _FoldState, effects: list[str]) -> list[list[str]]:
    """Pairs whose column spaces (held-out rows of all folds) are nearly the same: among the
    candidates (projected off the model's columns) and between a candidate and a model effect."""
    pairs = []
    projected = {}
    for name in names:
        blocks = []
        for _, J, is_extra, _ in state.per_fold:
            blocks.append(_project_off(J[:, state.column_owner == name], _orthonormal_basis(J[:, ~is_extra])))
        projected[name] = np.concatenate(blocks)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if _max_canonical_correlation(projected[a], projected[b]) > ALIAS_CORRELATION:
                pairs.append([a, b])
    full = np.concatenate([J for _, J, _, _ in state.per_fold])
    for a in names:
        for b in effects:
            owner = state.column_owner
            if _max_canonical_correlation(full[:, owner == a], full[:, owner == b]) > ALIAS_CORRELATION:
                pairs.append([b, a])
    return pairs
