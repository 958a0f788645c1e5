"""What the report says in words: the diagnosis, the ledger and the worst poses read for a user.

Plain text and numbers only (no HTML, no plotting), so that the page (`page`) and the figures
(`figures`) draw the same conclusions from the same rules: which candidate is the missing
effect, when a feature's R^2 counts as structure, what a ledger entry changed, which poses
are the worst.
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from ..metrics import W_POS, W_ROT

# A feature explaining this share of the residual (cross-validated R^2) is structure the
# model misses, not noise: the takeaway says so, the page highlights it, the bar is coloured.
STRUCTURE_R2 = 0.1


def p_value_text(p: Any) -> str:
    """p-value as text: '< 1e-6' when tiny, '–' when missing."""
    if p is None:
        return "–"
    try:
        v = float(p)
    except (TypeError, ValueError):
        return str(p)
    if math.isnan(v):
        return "–"
    return "< 1e-6" if v < 1e-6 else f"{v:.2g}"


def effect_list(value: Any) -> list[str]:
    """Effect names from what a model's metadata, a diagnosis or a ledger record holds:
    a comma-separated string, a list, or a mapping keyed by name."""
    if value is None:
        return []
    if isinstance(value, str):
        return [v.strip() for v in value.split(",") if v.strip()]
    if isinstance(value, Mapping):
        return [str(k) for k in value]
    try:
        return [str(v) for v in value]
    except TypeError:
        return [str(value)]


def effects_step(previous: list[str] | None, effects: list[str]) -> str:
    """What a ledger entry changed: its effects for the first, '+added -removed' after."""
    if previous is None:
        return ",".join(effects) or "no effects"
    added = [e for e in effects if e not in previous]
    removed = [e for e in previous if e not in effects]
    parts = (["+" + ",".join(added)] if added else []) + (["-" + ",".join(removed)] if removed else [])
    return "\n".join(parts) or "same effects"


def model_effects(model_info: Mapping[str, Any] | None, diagnosis: Mapping[str, Any] | None) -> list[str]:
    """The effects of the model under report: the diagnosis' base model, else the file's metadata."""
    if diagnosis and diagnosis.get("model_effects") is not None:
        return effect_list(diagnosis.get("model_effects"))
    if model_info:
        return effect_list(model_info.get("effects"))
    return []


def ranked_candidates(diagnosis: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    """The diagnosis' candidate effects by rank (unranked ones last)."""
    return sorted([c for c in diagnosis.get("candidates") or [] if isinstance(c, Mapping)],
                  key=lambda c: (c.get("rank") if isinstance(c.get("rank"), (int, float)) else 1e9))


def cv_gain(candidate: Mapping[str, Any]) -> float | None:
    """Cross-validated RMSE before / after adding the candidate; None when not both known."""
    b, a = candidate.get("cv_rmse_before"), candidate.get("cv_rmse_after")
    if isinstance(b, (int, float)) and isinstance(a, (int, float)) and a > 0:
        return b / a
    return None


def split_features(features: Sequence[Any]) -> tuple[list[Mapping[str, Any]], list[str]]:
    """(the features along which a smooth fit explains some held-out residual, cv R^2 > 0; the
    names of those where it explains none), so that a session with no structure reads as such
    in a line. A feature without a number is in neither."""
    rows = [f for f in features if isinstance(f, Mapping) and isinstance(f.get("r2"), (int, float))]
    return [f for f in rows if f["r2"] > 0], [str(f.get("feature", "?")) for f in rows if not f["r2"] > 0]


def is_structure(r2: Any) -> bool:
    """Whether a feature's cross-validated R^2 is structure the model misses."""
    return isinstance(r2, (int, float)) and r2 >= STRUCTURE_R2


def not_ranked_why(record: Mapping[str, Any]) -> str:
    """Why the diagnosis did not rank a candidate (one of its "undetermined" records), as the
    words after its name: an effect of the model already does what it does (the data would
    determine it without that effect), or the poses cannot determine it at all."""
    spanning = record.get("in_model")
    if spanning:
        return (f"is already in the model as {spanning}" if record.get("same")
                else f"does what {spanning}, already in the model, does")
    return "cannot be determined by this data"


def fewer_folds(reach: Mapping[str, Any]) -> str | None:
    """'fewer folds (--cv 2 would leave about 18 dimensions: ...)', where fewer folds would let
    the test reach its threshold (`diagnose._folds_to_pass`); None otherwise. Possible, not
    likely: each fold then trains on fewer poses, and on real Exp2 --cv 4 took the best
    form's p from 0.026 to 0.74."""
    fewer = reach.get("folds_to_pass") if isinstance(reach.get("folds_to_pass"), Mapping) else None
    if not fewer or not isinstance(fewer.get("folds"), int):
        return None
    return (f"fewer folds (--cv {fewer['folds']} would leave about {fewer.get('residual_dims')} dimensions: "
            "a pass becomes possible, not likely, for each fold trains on fewer poses)")


def _reach_advice(reach: Mapping[str, Any]) -> str:
    """What would let the test reach its threshold: more poses (if the best form's gain is
    real), fewer folds."""
    plan = reach.get("poses_to_pass") if isinstance(reach.get("poses_to_pass"), Mapping) else None
    more = (f"; if its gain is real, about {plan['poses']} poses of this spread would let {plan['effect']} pass"
            if plan and plan.get("poses") and plan.get("effect") else "")
    fewer = fewer_folds(reach)
    return more + (f"; {fewer}" if fewer else "")


def _structure_words(features: Sequence[Any]) -> str | None:
    """'0.23 of the residual's position is explained by t: an effect outside the catalogue
    ...' of the feature that explains most, where that is structure; else None."""
    r2 = [f for f in features if isinstance(f, Mapping) and isinstance(f.get("r2"), (int, float))]
    structure = max(r2, key=lambda f: f["r2"]) if r2 else None
    if structure is None or not is_structure(structure["r2"]):
        return None
    block = structure.get("error")
    part = f"the residual's {block}" if block in ("position", "orientation") else "the residual"
    return (f"{structure['r2']:.2f} of {part} is explained by {structure.get('feature')}: an effect outside the "
            "catalogue (add your own with --effect-file)")


def takeaway(diagnosis: Mapping[str, Any] | None, model_effects: Sequence[str] = (), why_none: str | None = None) -> str:
    """The diagnosis in one plain-language line (plain text, not escaped); why_none: why there
    is none, where the data cannot have one."""
    if not diagnosis:
        if why_none:
            return f"No diagnosis: {why_none}."
        return "No diagnosis given (run `posecorr diagnose` to rank missing effects)."
    candidates = ranked_candidates(diagnosis)
    present = [c for c in candidates if c.get("present")]
    if present:
        top = present[0]
        effect = str(top.get("effect", "?"))
        p = top.get("p_value")
        p_text = f", p {p_value_text(p)}" if p is not None and p_value_text(p).startswith("<") else (
            f", p = {p_value_text(p)}" if p is not None else "")
        effects = list(model_effects)
        if effect not in effects:
            effects.append(effect)
        gain = cv_gain(top)
        gain_text = f"; it cuts the cross-validated RMSE {gain:.2g}×" if gain is not None else ""
        what = f"{effect}, a form outside the catalogue" if top.get("kind") == "form" else effect
        return (f"Most likely missing: {what} (present: yes{p_text}{gain_text}). "
                f"Add it with --effects {','.join(effects)}")
    structure_text = _structure_words(diagnosis.get("features") or [])
    reach = diagnosis.get("reach") if isinstance(diagnosis.get("reach"), Mapping) else {}
    if reach.get("can_pass") is False and all(isinstance(reach.get(k), (int, float)) for k in ("best_p", "threshold")):
        # Not "nothing is missing": on these poses the test could not have said otherwise.
        used = (diagnosis.get("rows") or {}).get("used") if isinstance(diagnosis.get("rows"), Mapping) else None
        line = (f"{f'These {used} poses' if used else 'These poses'} cannot show a missing effect: no candidate's p can "
                f"fall below the test's threshold (at best {reach['best_p']:.2g} against {reach['threshold']:.2g})"
                f"{_reach_advice(reach)}.")
        return line + (f" Yet {structure_text}." if structure_text else "")
    # The test's words stand under the candidates' table; the banner keeps to the finding.
    absent = [a for a in diagnosis.get("absent") or [] if isinstance(a, Mapping)]
    if absent and isinstance(absent[0].get("score"), (int, float)):
        # Not "nothing is missing": an effect gains and fails the test, which says why.
        first = absent[0]
        return (f"No effect passes the test: {first.get('effect')} lowers the held-out whitened error by "
                f"{first['score']:.1%} but is not present: {first.get('why')}. No form earns its place.")
    # What the poses cannot show is not shown missing: the claim keeps to what they determine.
    unseen = _unseen(diagnosis, model_effects)
    none_missing = ("No catalogue effect is missing" if not unseen else
                    f"No catalogue effect these poses can determine is missing ({len(unseen)} "
                    f"{'candidate' if len(unseen) == 1 else 'candidates'} they cannot determine or tell apart: "
                    f"{', '.join(unseen)})")
    if structure_text:
        return f"{none_missing}, but {structure_text}."
    # Named by kind: the proposal's words name the best form, which may be another candidate;
    # one the poses cannot tell from another is not "best" (it was just named as such).
    told = [c for c in candidates if c.get("effect") not in unseen]
    kind = "form" if told and told[0].get("kind") == "form" else "catalogue effect"
    top = f" (best {kind}: {told[0].get('effect')}, not present)" if told else ""
    # Not "noise": on a few poses an error no candidate explains fails the test just the same.
    return f"{none_missing} and no form earns its place{top}; nothing tried explains what is left."


def alias_whole(pair: Mapping[str, Any]) -> bool:
    """Whether every direction of the pair's smaller effect moves the poses as the other
    does (a record without the count, as a diagnosis written before it, counts as whole)."""
    shared, of = pair.get("shared"), pair.get("of")
    return not (isinstance(shared, int) and isinstance(of, int) and shared < of)


def alias_text(pair: Mapping[str, Any]) -> str:
    """One alias record in words: 'cannot be told apart' only where the smaller effect is
    wholly the other's on these poses; else how many of its directions are shared."""
    a, b = (str(e) for e in pair.get("effects") or ["?", "?"])
    correlation = pair.get("correlation")
    figure = f"canonical correlation {correlation:.4f}" if isinstance(correlation, (int, float)) else ""
    if alias_whole(pair):
        return f"cannot be told apart by this data: {a} ~ {b}" + (f" ({figure} of their effects on these poses)"
                                                                  if figure else "")
    return (f"partly alike on these poses: {a} ~ {b} along {pair['shared']} of {pair['of']} directions "
            f"({figure}); this data cannot tell those apart")


def _unseen(diagnosis: Mapping[str, Any], model_effects: Sequence[str]) -> list[str]:
    """The candidates the diagnosis could not judge: those the poses cannot determine (not
    those an effect of the model already does), then those wholly aliased with another."""
    out = [str(u.get("effect")) for u in diagnosis.get("undetermined") or []
           if isinstance(u, Mapping) and not u.get("in_model")]
    for pair in diagnosis.get("aliases") or []:
        if isinstance(pair, Mapping) and alias_whole(pair):
            out += [str(e) for e in pair.get("effects") or [] if e not in model_effects and str(e) not in out]
    return out


def worst_order(pos_err: np.ndarray, rot_err: np.ndarray | None = None) -> np.ndarray:
    """Row indices sorted worst first by w_pos * pos_err (m) + w_rot * rot_err (rad) (eq. 43 per pose)."""
    score = W_POS * np.asarray(pos_err, float)
    if rot_err is not None:
        score = score + W_ROT * np.asarray(rot_err, float)
    return np.argsort(-score, kind="stable")
