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


def _proposed_name(form: str) -> str:
    return PREFIX + form


def _class_name(form: str) -> str:
    return "".join(part.title() for part in _proposed_name(form).split("_"))


def propose(search: Any, result: dict[str, Any], kept: Sequence[str],
            dropped: Sequence[dict[str, Any]]) -> tuple[dict[str, Any] | None, str | None]:
    """(proposal, None) for the forms kept, or (None, why nothing is proposed)."""
    rows = {row["effect"]: row for row in result["candidates"]}
    forms = [name for name in kept if get_effect(name).generic]
    for record in dropped:
        twins = [twin for twin in record["indistinct_from"] if twin in forms]
        if twins:
            a, b = record["effect"], twins[0]
            return None, (f"{a} and {b} cannot be told apart by this data: held-out gains "
                          f"{rows[a]['score']:.1%} and {rows[b]['score']:.1%}, and each adds nothing given the other")
    if not forms:
        return None, _why_none(result, kept)
    return _fitted_proposal(search, result, list(kept), forms), None


def _why_none(result: dict[str, Any], kept: Sequence[str]) -> str:
    if kept:
        return (f"the catalogue explains the error: {', '.join(kept)} "
                f"{'is' if len(kept) == 1 else 'are'} present, and no form earns a place beside "
                f"{'it' if len(kept) == 1 else 'them'}")
    forms = [row for row in result["candidates"] if row["kind"] == "form"]
    if not forms:
        return "no form could be tested on this data (see the effects that cannot be determined)"
    best = max(forms, key=lambda row: row["score"])
    return (f"no form earns its place: the best, {best['effect']}, lowers the held-out whitened error by "
            f"{best['score']:.1%} (p = {best['p_value']:.2g}, worst fold {best['fold_gain_min']:.1%})")


def _fitted_proposal(search: Any, result: dict[str, Any], kept: list[str], forms: list[str]) -> dict[str, Any]:
    """The kept model fitted on every pose (the forms' values) and cross-validated on the
    diagnosis's folds (its held-out gain over the base model)."""
    from posecorr.train.physics import PhysicsModel
    from posecorr.train.pipeline import CorrectionPipeline, cross_validate
    from posecorr.train.splits import KFold

    from .diagnose import _whitened_gain

    table = search.table
    search.say(f"the proposal: {', '.join(search.effects + kept)} on every pose")
    t = table.time()
    physics = PhysicsModel(tuple(search.effects + kept), with_rotation=table.has_orientation).fit(
        table.measured, table.reference, t=t)
    cv = cross_validate(lambda: CorrectionPipeline(search.effects + kept), table, KFold(search.folds), search.seed)
    gains = [_whitened_gain(table, held, search.base.predicted, cv.predicted, search.base.per_fold[k][3])
             for k, (_, held) in enumerate(search.splits)]
    return {
        "effect": ",".join(_proposed_name(form) for form in forms),
        "forms": forms,
        "file": None,
        "gain": float(np.mean(gains)),
        "parameters": int(sum(get_effect(form).size for form in forms)),
        "values": {form: get_effect(form).describe(physics.params_[form]) for form in forms},
        "cv_rmse_pos_before": result["cv_base"]["rmse_pos"],
        "cv_rmse_pos_after": float(cv.metrics["rmse_pos"]),
        "with": kept,
        "model_effects": list(search.effects),
        "causes": {form: get_effect(form).causes for form in forms},
    }


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
                        "why": _why_not(row, form)})
    return out


def _why_not(row: dict[str, Any], form: str) -> str:
    dropped = row.get("dropped")
    if dropped is not None:
        return (f"it adds nothing once {', '.join(dropped['given'])} "
                f"{'is' if len(dropped['given']) == 1 else 'are'} in (p = {dropped['p_value_given']:.2g}, "
                f"gain {dropped['score_given']:.1%})")
    if row["implausible"]:
        return "its fitted values are not physical: " + "; ".join(row["implausible"])
    if "passes_given" in row:
        reason = "; ".join(row.get("implausible_given") or []) or (
            f"p = {row['p_value_given']:.2g}, gain {row['score_given']:.1%}")
        return f"it adds nothing given {', '.join(row['given'])} ({reason})"
    return f"{form} explains more of the same error"


def effect_file_text(proposal: dict[str, Any], command: str, data_name: str) -> str:
    """A ready effect file: the proposal's forms as user effects with their fitted defaults."""
    forms = proposal["forms"]
    head = [f'"""Proposed by `{command}`.', "",
            f"Held-out gain: the whitened error falls by {proposal['gain']:.1%} over the diagnosis's folds "
            f"(rmse_pos {1e3 * proposal['cv_rmse_pos_before']:.3g} -> {1e3 * proposal['cv_rmse_pos_after']:.3g} mm); "
            f"{proposal['parameters']} parameters.", ""]
    for form in forms:
        effect = get_effect(form)
        head += [f"{_proposed_name(form)}: {(effect.__doc__ or '').strip().splitlines()[0]}",
                 f"  Physical causes of this shape: {effect.causes}.",
                 "  Fitted on this session: " + "; ".join(
                     f"{name} = {numbers_text(values, 4)} {_unit(effect, name)}"
                     for name, values in proposal["values"][form].items()), ""]
    head += ["Fit it with:",
             f"    posecorr fit {data_name} --effect-file THIS_FILE --effects {effects_arg(proposal)}",
             '"""']
    imports = sorted({type(get_effect(form)).__name__ for form in forms})
    body = ["from posecorr.effects import Param",
            f"from posecorr.forms import {', '.join(imports)}", ""]
    for form in forms:
        effect = get_effect(form)
        params = []
        for param in effect.params:
            values = proposal["values"][form][param.name]
            default = tuple(values) if isinstance(values, list) else (values,)
            params.append(f"        Param({param.name!r}, {param.size}, {_tuple(default)}, {param.scale!r}, "
                          f"{param.unit!r},\n              doc={param.doc!r}),")
        body += ["", f"class {_class_name(form)}({type(effect).__name__}):",
                 f'    """The {form} form, its defaults the values fitted on this session."""', "",
                 f"    name = {_proposed_name(form)!r}",
                 "    generic = False  # the user's own effect now, not a form the diagnosis proposes",
                 "    params = (", *params, "    )", ""]
    return "\n".join(head + body).rstrip() + "\n"


def effects_arg(proposal: dict[str, Any]) -> str:
    names = [name for name in proposal["with"] if not get_effect(name).generic]
    return ",".join(proposal["model_effects"] + names + [_proposed_name(f) for f in proposal["forms"]])


def numbers_text(values: Any, digits: int) -> str:
    """A fitted parameter's value(s) with `digits` significant digits: '0.012' or '[0.012, -0.008]'."""
    values = values if isinstance(values, list) else [values]
    text = ", ".join(f"{v:.{digits}g}" for v in values)
    return f"[{text}]" if len(values) > 1 else text


def _unit(effect: Any, name: str) -> str:
    return next(p.unit for p in effect.params if p.name == name)


def _tuple(values: Sequence[float]) -> str:
    inner = ", ".join(repr(float(v)) for v in values)
    return f"({inner},)" if len(values) == 1 else f"({inner})"
