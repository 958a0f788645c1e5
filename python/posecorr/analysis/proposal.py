"""What the diagnosis proposes when a generic form, not a catalogue effect, explains the error.

`propose` turns the forms the selection kept (`diagnose`) into a proposal: the forms, their
held-out gain, their parameters fitted on the whole session, and the physical causes that
produce their shape; or says why nothing is proposed. `effect_file_text` writes the proposal
as a ready effect file: one subclass per form, named `session_<form>`, its fitted values as
its defaults, which `posecorr fit --effect-file FILE --effects ...,session_<form>` accepts
unchanged. `explain_absorbed` says which catalogue effects take part of a form's gain and why
they are not the answer.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..effects import get_effect

PREFIX = "session_"
# A proposal's first words, then the command that wrote it; one that `posecorr diagnose` wrote
# opens with OPENING: `diagnose --propose` replaces such a file (an earlier proposal) and
# refuses any other effect file (`cli.failures`: the user's own code).
PROPOSED_BY = '"""Proposed by `'
OPENING = PROPOSED_BY + "posecorr diagnose "


def _proposed_name(form: str) -> str:
    return PREFIX + form


def _class_name(form: str) -> str:
    return "".join(part.title() for part in _proposed_name(form).split("_"))


def propose(search: Any, result: dict[str, Any], kept: Sequence[str], dropped: Sequence[dict[str, Any]],
            forms_off: bool = False) -> tuple[dict[str, Any] | None, str | None]:
    """(proposal, None) for the forms kept, or (None, why nothing is proposed); `forms_off`:
    the diagnosis was told to leave the forms out, which is then the reason."""
    if forms_off:
        return None, "the generic forms were not tested (--no-forms): the diagnosis ranked the catalogue's effects only"
    rows = {row["effect"]: row for row in result["candidates"]}
    forms = [name for name in kept if get_effect(name).generic]
    for record in dropped:
        twins = [twin for twin in record["indistinct_from"] if twin in forms]
        if twins:
            a, b = record["effect"], twins[0]
            return None, (f"{a} and {b} cannot be told apart by this data: held-out gains "
                          f"{rows[a]['score']:.1%} and {rows[b]['score']:.1%}, and each adds nothing given the other")
    if not forms:
        return None, _why_none(search, result, kept)
    return _fitted_proposal(search, result, list(kept), forms), None


def fewer_folds_or_more_poses(reach: dict[str, Any]) -> str:
    """What lets the test reach its threshold where it cannot: fewer folds, when they would
    hold out poses enough, else more poses."""
    from .interpretation import fewer_folds

    fewer = fewer_folds(reach)
    return f"{fewer} or more poses" if fewer else "more poses"


def _why_none(search: Any, result: dict[str, Any], kept: Sequence[str]) -> str:
    from .diagnose import PLANNING_POWER, best_form

    if kept:
        return (f"the catalogue explains the error: {', '.join(kept)} "
                f"{'is' if len(kept) == 1 else 'are'} present, and no form earns a place beside "
                f"{'it' if len(kept) == 1 else 'them'}")
    best = best_form(result["candidates"])
    if best is None:
        return "no form could be tested on this data (see the effects that cannot be determined)"
    moves = "lowers" if best["score"] >= 0 else "raises"
    reach = result["reach"]
    beyond = "" if reach["can_pass"] else (
        f"; nor could any candidate: the held-out poses leave {reach['residual_dims']} dimensions of residual that "
        f"{', '.join(search.effects) or 'the model'} cannot move, so no p falls below {reach['best_p']:.2g} "
        f"(threshold {reach['threshold']:.2g}): {fewer_folds_or_more_poses(reach)}")
    plan = reach["poses_to_pass"]
    planned = "" if plan is None else (
        f"; if its gain is real, about {plan['poses']} poses of this spread would take its p below the threshold "
        f"in {PLANNING_POWER:.0%} of sessions (its score statistic, {plan['lm_statistic']:.3g} on "
        f"{plan['df']} degree{'s' if plan['df'] != 1 else ''} of freedom, grows with the poses)")
    return (f"no form earns its place: the best form, {best['effect']}, {moves} the held-out whitened error by "
            f"{abs(best['score']):.1%} (p = {best['p_value']:.2g}, worst fold {best['fold_gain_min']:.1%}); "
            f"{_fails(search, best)}{beyond}{planned}")


def _fails(search: Any, row: dict[str, Any]) -> str:
    """The parts of the test `row` fails, with the figures, and what the poses offer the form
    to show in (a form that varies with the orientation needs the orientations to vary)."""
    from posecorr.rotations import quat_to_matrix
    from posecorr.train.identify import describe_spread, poses_lack

    from .diagnose import row_failed_parts

    fails = row_failed_parts(search, row)
    table = search.table
    spread = describe_spread(table.meas_p, quat_to_matrix(table.meas_q), table.has_orientation)
    return f"{', '.join(fails) or 'implausible values'}; {poses_lack(get_effect(row['effect']), spread, table.time())}"


def _fitted_proposal(search: Any, result: dict[str, Any], kept: list[str], forms: list[str]) -> dict[str, Any]:
    """The kept model with each form cut to the terms its data needs (`_fewest_terms`), fitted
    on every pose (the forms' values) and cross-validated on the diagnosis's folds (its
    held-out gain over the base model)."""
    from contextlib import ExitStack

    from posecorr.train.physics import PhysicsModel
    from posecorr.train.pipeline import session_setup

    table = search.table
    catalogue = [name for name in kept if name not in forms]
    with ExitStack() as registered:
        model = {form: form for form in forms}
        for form in forms:
            search.say(f"the terms of {form} this data needs")
            # the last form's cut is cross-validated with every form as it stays: the proposal's
            model[form], cv = _fewest_terms(search, catalogue, model, form, registered)
        effects = search.effects + catalogue + list(model.values())
        # the forms by their names: a cut form is registered as '_{form}_terms{count}'
        search.say(f"the proposal: {', '.join(search.effects + catalogue + list(forms))} on every pose")
        physics = PhysicsModel(tuple(effects), **session_setup(table)._asdict()).fit(
            table.measured, table.reference, t=table.time())
        gains = _gains(search, cv)
        chosen = {form: get_effect(model[form]) for form in forms}
        values = {form: chosen[form].describe(physics.params_[model[form]]) for form in forms}
        terms = {form: dict(zip(chosen[form].term_labels(), physics.params_[model[form]].tolist())) for form in forms}
        indices = {form: None if chosen[form].terms is None else list(chosen[form].terms) for form in forms}
    return {
        "effect": ",".join(_proposed_name(form) for form in forms),
        "forms": forms,
        "file": None,
        "gain": float(np.mean(gains)),
        "parameters": int(sum(effect.size for effect in chosen.values())),
        "form_parameters": int(sum(get_effect(form).size for form in forms)),
        "values": values,
        "terms": terms,
        "term_indices": indices,
        "cv_rmse_pos_before": result["cv_base"]["rmse_pos"],
        "cv_rmse_pos_after": float(cv.metrics["rmse_pos"]),
        # where the table has orientations, what a form that turns them does (None otherwise)
        "cv_rmse_rot_before": result["cv_base"]["rmse_rot"],
        "cv_rmse_rot_after": cv.metrics["rmse_rot"],
        "with": kept,
        "model_effects": list(search.effects),
        "causes": {form: get_effect(form).causes for form in forms},
    }


def _cross_validated(search: Any, effects: list[str]) -> Any:
    """`effects` cross-validated on the diagnosis's folds."""
    from posecorr.train.pipeline import CorrectionPipeline, cross_validate
    from posecorr.train.splits import KFold

    return cross_validate(lambda: CorrectionPipeline(effects), search.table, KFold(search.folds), search.seed,
                          pool=search.fitted.pool)


def _gains(search: Any, cv: Any, whiten: Sequence[Any] | None = None) -> np.ndarray:
    """Per fold, the fall of the held-out whitened error from the base model to `cv`'s,
    whitened by the sigmas of `whiten`'s fold models (default: the base model's)."""
    from .diagnose import _whitened_gain

    whiten = whiten or [fold.physics for fold in search.base.per_fold]
    return np.asarray([_whitened_gain(search.table, held, search.base.predicted, cv.predicted, whiten[k])
                       for k, (_, held) in enumerate(search.splits)])


def _fewest_terms(search: Any, catalogue: list[str], model: dict[str, str], form: str,
                  registered: Any) -> tuple[str, Any]:
    """The name of `form` cut to the fewest terms whose held-out error is within one standard
    error of the best cut's (Breiman's one-standard-error rule, on the log of the whitened
    error left in each fold), with a gain in every fold; the largest cut when no smaller one
    comes near it. Cuts keep the largest terms on this session first (|theta_j| times its
    whitened Jacobian column: SINDy's threshold on normalised coefficients), and never a
    combination the fit holds (`_free_terms`): the largest is `form` itself only where the
    data determine all of it. Returned with the cut's cross-validation. The cuts are
    registered on `registered` (an ExitStack), which removes them."""
    from posecorr.train.physics import PhysicsModel
    from posecorr.train.pipeline import session_setup

    from ..effects import register_effect, unregister_effect
    from .diagnose import _column_owners

    table, whole = search.table, get_effect(form)
    effects = search.effects + catalogue + list(model.values())
    physics = PhysicsModel(tuple(effects), **session_setup(table)._asdict()).fit(
        table.measured, table.reference, t=table.time())
    _, J, _ = physics.residual_jacobian(table.measured, table.reference, table.time())
    owned = _column_owners(physics, []) == form
    norms = np.linalg.norm(J[:, owned], axis=0)
    free, theta = _free_terms(physics.basis_[owned], physics.params_[form], norms)
    size = np.abs(theta) * norms
    order = [int(j) for j in np.argsort(-size, kind="stable") if j in free]
    # Whitened by the whole form's fold sigmas: the base model's hold the missing error itself,
    # and would make a cut that leaves three times the orientation error look as good.
    whole_cv = _cross_validated(search, effects)
    whiten = [fitted.physics_ for fitted in whole_cv.fitted]
    # each cut's name, its cross-validation and whether it gains in every fold, and the log of
    # the whitened error it leaves, per fold
    cuts, left = [], []
    for count in range(1, len(order) + 1):
        if count == whole.size:
            name, cv = form, whole_cv
        else:
            terms = sorted(order[:count])
            name = register_effect(type(whole).keeping(terms, f"_{form}_terms{count}", theta[terms]),
                                   source=__name__).name
            registered.callback(unregister_effect, name)
            cv = _cross_validated(search, search.effects + catalogue + list({**model, form: name}.values()))
        gains = _gains(search, cv, whiten)
        cuts.append((name, cv, bool(np.all(gains > 0))))
        left.append(np.log(np.clip(1.0 - gains, 1e-12, None)))
    best = left[int(np.argmin([np.mean(e) for e in left]))]
    for (name, cv, everywhere), errors in zip(cuts, left):
        worse = errors - best
        spread = np.std(worse, ddof=1) / np.sqrt(len(worse)) if len(worse) > 1 else 0.0
        if everywhere and worse.mean() <= spread:
            return name, cv
    return cuts[-1][:2]


def _free_terms(basis: np.ndarray, theta: np.ndarray, norms: np.ndarray) -> tuple[list[int], np.ndarray]:
    """The terms of a form a cut may keep, and theta with the others at zero. The fit holds
    the combinations of the form's terms the data cannot determine (`PhysicsModel.fixed_`;
    `basis`: its determined directions, the form's rows), as orientation_bias's K = e I, the
    mount's lever along z: a cut that keeps every term of one holds it too, and the fit of the
    proposal marks those terms "not determined". So one term of each is left out, the smallest
    on this session (|theta_j| times `norms`_j) first, and theta moved along the held
    combinations to where those terms are zero: for an alias, the effects before the form take
    up the rest; otherwise the data cannot tell."""
    from scipy.linalg import qr

    values, vectors = np.linalg.eigh(np.eye(len(theta)) - basis @ basis.T)
    held = vectors[:, values > 0.5]
    out: list[int] = []
    for j in np.argsort(np.abs(theta) * norms, kind="stable"):
        # left out if it reaches a held combination the terms left out so far do not, by more
        # than a tenth (what the fit's standard errors count as touching it)
        if len(out) < held.shape[1] and np.linalg.matrix_rank(held[out + [int(j)]], tol=0.1) > len(out):
            out.append(int(j))
    # Where no small term reaches a held combination by a tenth, the terms that reach the rest
    # best (QR with column pivoting): as many left out as combinations held, so theta can move.
    for j in qr(held.T, pivoting=True)[2]:
        if len(out) < held.shape[1] and j not in out and np.linalg.matrix_rank(held[out + [int(j)]]) > len(out):
            out.append(int(j))
    if out:
        theta = theta - held @ np.linalg.solve(held[out], theta[out])
    return [j for j in range(len(theta)) if j not in out], theta


def explain_absorbed(result: dict[str, Any], kept: Sequence[str]) -> list[dict[str, Any]]:
    """For each form kept, the catalogue effects that take part of its gain alone and why
    they are not the answer (they add nothing once the form is in, or their values are not
    physical)."""
    out = []
    rows = result["candidates"]
    for form in (name for name in kept if get_effect(name).generic):
        form_row = next(row for row in rows if row["effect"] == form)
        for row in rows:
            if row["kind"] != "effect" or row["present"] or row["score"] <= 0 or form_row["score"] <= 0:
                continue
            if not (row["passes"] or row["implausible"]):
                continue
            out.append({"effect": row["effect"], "form": form, "share": min(row["score"] / form_row["score"], 1.0),
                        "why": _why_not(row) or f"{form} explains more of the same error"})
    return out


def explain_absent(search: Any, result: dict[str, Any]) -> list[dict[str, Any]]:
    """The catalogue effects that lower the held-out error by the test's minimum gain and are
    still not present, each with the parts of the test it fails (a table's "no" beside a
    good score says nothing by itself); those a kept form absorbs are `explain_absorbed`'s."""
    from .diagnose import FOLD_RISES, row_failed_parts

    absorbed = {row["effect"] for row in result["absorbed"]}
    out = []
    for row in result["candidates"]:
        if row["kind"] != "effect" or row["present"] or row["score"] < search.min_gain or row["effect"] in absorbed:
            continue
        fails = row_failed_parts(search, row)
        alone = [f"{part} (worst fold {row['fold_gain_min']:.1%})" if part == FOLD_RISES else part
                 for part in fails] + list(row["implausible"])
        if alone and "passes_given" in row:   # tested again given all kept
            alone.append(f"and given {', '.join(row['given'])}, {given_fails(row)}")
        out.append({"effect": row["effect"], "score": row["score"], "p_value": row["p_value"],
                    "why": "; ".join(alone) or _why_not(row) or "it is not kept beside the others"})
    return out


def _why_not(row: dict[str, Any]) -> str | None:
    """Why a candidate that passes alone is not kept beside the others, if that is why."""
    dropped = row.get("dropped")
    if dropped is not None and "told_apart_from" in dropped:   # `_rivals`: the other is not kept either
        return f"given {dropped['told_apart_from']}, which is not named either (see the note), {given_fails(dropped)}"
    if dropped is not None:
        return (f"once {', '.join(dropped['given'])} {'is' if len(dropped['given']) == 1 else 'are'} in, "
                f"{given_fails(dropped)}")
    if row["implausible"]:
        return "its fitted values are not physical: " + "; ".join(row["implausible"])
    if "passes_given" in row:
        return f"given {', '.join(row['given'])}, {given_fails(row)}"
    return None


def given_fails(record: dict[str, Any]) -> str:
    """What a candidate's test given others (`score_given`, `p_value_given`, `fails_given`) gives."""
    gain = record["score_given"]
    moves = f"its gain is {gain:.1%}" if gain >= 0 else f"it raises the held-out whitened error by {-gain:.1%}"
    return (f"{moves} (p = {record['p_value_given']:.2g}) and it fails the test: "
            f"{'; '.join(record['fails_given'])}")


def effect_file_text(proposal: dict[str, Any], command: str, data_name: str,
                     effect_files: Sequence[str] = ()) -> str:
    """A ready effect file: the proposal's forms as user effects with their fitted defaults;
    `effect_files` are the diagnosis's own, which define effects the proposal keeps."""
    forms = proposal["forms"]
    head = [f'{PROPOSED_BY}{command}`.', "",
            f"Held-out gain over the diagnosis's folds: {gain_words(proposal)}; {proposal['parameters']} "
            "parameters.", ""]
    for form in forms:
        effect = get_effect(form)
        unit = effect.params[0].unit_after()
        head += [f"{_proposed_name(form)}: {(effect.__doc__ or '').strip().splitlines()[0]}",
                 f"  Physical causes of this shape: {effect.causes}.",
                 f"  Fitted on this session ({terms_words(proposal, form)}): " + "; ".join(
                     f"{label} = {value:.4g}{unit}" for label, value in proposal["terms"][form].items()), ""]
    head += ["Fit it with:",
             f"    {fit_command(data_name, effect_files, 'THIS_FILE', proposal)}",
             '"""']
    imports = sorted({type(get_effect(form)).__name__ for form in forms})
    body = ["from posecorr.effects import Param",
            f"from posecorr.forms import {', '.join(imports)}", ""]
    for form in forms:
        effect, terms = get_effect(form), proposal["term_indices"][form]
        if terms is not None:
            effect = type(effect).keeping(terms, _proposed_name(form))()
        params = []
        for param in effect.params:
            values = proposal["values"][form][param.name]
            default = tuple(values) if isinstance(values, list) else (values,)
            params.append(f"        Param({param.name!r}, {param.size}, {_tuple(default)}, {param.scale!r}, "
                          f"{param.unit!r},\n              doc={param.doc!r}),")
        kept = [] if terms is None else [
            f"    # the terms this session needs, of the form's {len(effect.labels)}; the others are held at zero",
            f"    terms = {_tuple(terms, int)}"]
        body += ["", f"class {_class_name(form)}({type(get_effect(form)).__name__}):",
                 f'    """The {form} form, its defaults the values fitted on this session."""', "",
                 f"    name = {_proposed_name(form)!r}",
                 "    generic = False  # the user's own effect now, not a form the diagnosis proposes",
                 *kept,
                 "    params = (", *params, "    )", ""]
    return "\n".join(head + body).rstrip() + "\n"


def fit_command(data_name: str, effect_files: Sequence[str], new_file: str, proposal: dict[str, Any]) -> str:
    """The `posecorr fit` that takes the proposal, ready to run: the diagnosis's effect files
    first, as the effects they define (an earlier round's proposal) stay in the model, then
    the new one; the physics alone (`--method none`: what the diagnosis measured; fit's
    default adds a PMC core of hundreds of weights); the model beside the data, named for
    the forms it adds."""
    import shlex
    from pathlib import PurePath

    words = ["posecorr", "fit", data_name]
    for path in [*effect_files, new_file]:
        words += ["--effect-file", path]
    data = PurePath(data_name)
    model = data.with_name(f"{data.stem}-{'-'.join(_proposed_name(f) for f in proposal['forms'])}.onnx")
    return shlex.join(words + ["--effects", effects_arg(proposal), "--method", "none", "-o", str(model)])


def effects_arg(proposal: dict[str, Any]) -> str:
    names = [name for name in proposal["with"] if not get_effect(name).generic]
    return ",".join(proposal["model_effects"] + names + [_proposed_name(f) for f in proposal["forms"]])


def rmse_words(proposal: dict[str, Any]) -> str:
    """The held-out rmse before and after the proposal: 'rmse_pos 1.05 -> 0.917 mm', then
    the orientation's where the table has one (a form that turns the orientation may move
    the position little)."""
    words = (f"rmse_pos {1e3 * proposal['cv_rmse_pos_before']:.3g} -> "
             f"{1e3 * proposal['cv_rmse_pos_after']:.3g} mm")
    if proposal["cv_rmse_rot_after"] is None:
        return words
    return (f"{words}, rmse_rot {1e3 * proposal['cv_rmse_rot_before']:.3g} -> "
            f"{1e3 * proposal['cv_rmse_rot_after']:.3g} mrad")


def gain_words(proposal: dict[str, Any]) -> str:
    """The proposal's held-out gain: the rmse it acts on first (`rmse_words`), then the
    diagnosis's score, the fall of the whitened error, whose scale says why it is smaller:
    position and rotation each count in units of what the model without the proposal leaves
    of it (the fit's sigmas), so both weigh alike and a gain in one alone shows as about 29 %
    (1 - 1/sqrt 2) at most; the strain of the loop's session, 88 % of rmse_pos, scores 29.0 %."""
    words = f"{rmse_words(proposal)}; the held-out whitened error falls by {proposal['gain']:.1%}"
    if proposal["cv_rmse_rot_after"] is None:
        return words
    return (words + " (position and rotation each in units of what the model leaves of it, so a gain in one alone "
            "shows as about 29% at most)")


def numbers_text(values: Any, digits: int) -> str:
    """A fitted parameter's value(s) with `digits` significant digits: '0.012' or '[0.012, -0.008]'."""
    values = values if isinstance(values, list) else [values]
    text = ", ".join(f"{v:.{digits}g}" for v in values)
    return f"[{text}]" if len(values) > 1 else text


def terms_words(proposal: dict[str, Any], form: str) -> str:
    kept, whole = len(proposal["terms"][form]), get_effect(form).size
    return f"all {whole} terms" if kept == whole else f"{kept} of its {whole} terms"


def _tuple(values: Sequence[float], kind: type = float) -> str:
    inner = ", ".join(repr(kind(v)) for v in values)
    return f"({inner},)" if len(values) == 1 else f"({inner})"
