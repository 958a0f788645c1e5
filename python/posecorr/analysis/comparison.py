"""What the report compares: a before and an after, each scored on poses the page names.

Before: the raw measurements where they are in the reference frame already (the simulated
paper experiments). Where the frames are unregistered (the tracker's own frame, metres from
the reference: raw rmse_pos above UNREGISTERED_FACTOR times the best rigid fit's and above
UNREGISTERED_MIN_M), raw
measures that offset, not the tracker; the before is then the best rigid fit's residuals
(the rigid variants `posecorr fit` scores as its floor, `train.pipeline.rigid_candidates`)
and the improvement is against it.

After: held-out where the ledger holds the fit that wrote the model file (matched by the
file's SHA-256): on a test split the file itself on the test poses, the rigid fit refitted on
the fit's other poses; under cross-validation every pose predicted by the model and the rigid
fit refitted on the same folds without it (`pipeline.out_of_fold`; for "auto", each fold by
the candidate chosen inside its training rows, `pipeline.nested_out_of_fold`), as `fit`
scored them. Otherwise the model file on every pose, in-sample, beside the rigid fit on every pose;
where the model's digests (`training_data_digest`, `fitted_table_digest`) say the table is not
the one the fit read (a session recorded again into the same file, rows edited), no ledger
line is rebuilt on it, and the after is the model file on poses it was not fitted on. A table
of the fit's poses in another order (sorted, reversed: the digests of any order,
`training_set_digest`, `fitted_table_set_digest`) is the fit's: the folds are by row, so the
ledger line's `row_ranks` put its rows back in the fit's order (`ledger.fit_order`), and
without them it is in-sample, said so.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from ..data import PoseTable
from ..metrics import RULE, block_name, frames_unregistered, metric_block, pose_metrics


@dataclass
class Comparison:
    """The poses the page shows (`rows` of the table) before and after, and on what they rest.

    reference, before, after: (len(rows), 7) poses; scored: "held-out (...)" or "in-sample";
    raw, rigid: metrics of the measurements and of the best rigid fit on `rows`; rigid_name:
    its candidate name (rigid-joint); reason: why the after is in-sample (empty when
    held-out); ledger: the held-out block the ledger recorded for the model (for comparison
    with `after`).
    """

    rows: np.ndarray
    reference: np.ndarray
    before: np.ndarray
    after: np.ndarray
    scored: str
    held_out: bool
    unregistered: bool
    raw: dict[str, Any]
    rigid: dict[str, Any]
    rigid_name: str
    after_metrics: dict[str, Any]
    reason: str = ""
    ledger: Mapping[str, Any] | None = None

    @property
    def baseline(self) -> str:
        """The before in the page's words: "raw" or "rigid fit (VARIANT)"."""
        return rigid_label(self.rigid_name) if self.unregistered else "raw"

    @property
    def before_metrics(self) -> dict[str, Any]:
        return self.rigid if self.unregistered else self.raw

    @property
    def block(self) -> dict[str, Any]:
        """metric_block(before, after): the after's figures and the improvements against the before."""
        return metric_block(self.before_metrics, self.after_metrics)

    def to_json(self) -> dict[str, Any]:
        from .figures import arrow_keys_mm

        def figures_of(m: Mapping[str, Any]) -> dict[str, Any]:
            return {k: m.get(k) for k in ("rmse_pos", "rmse_rot", "rmse_total")}

        block = self.block
        keys = arrow_keys_mm(self.before[:, :3] - self.reference[:, :3], self.after[:, :3] - self.reference[:, :3])
        # names as fit's JSON and the ledger write them (rigid-joint), the page's words apart
        return {"baseline": {"name": self.rigid_name if self.unregistered else "raw",
                             "rmse_pos": self.before_metrics.get("rmse_pos"),
                             "rmse_rot": self.before_metrics.get("rmse_rot"),
                             # the rigid fit scored as the after is: on the fit's folds, or in-sample
                             "held_out": self.held_out and self.unregistered},
                "after": {"scored": self.scored, "held_out": self.held_out, "n": int(len(self.rows)),
                          **figures_of(self.after_metrics), "reason": self.reason or None,
                          # the ledger's figures only: the improvements fit recorded are against raw,
                          # which on unregistered frames measures the frames' offset
                          "ledger": figures_of(self.ledger) if self.ledger else None},
                "improvement": {k: block.get(f"improvement_{k}") for k in ("pos", "rot", "total")},
                "unregistered": self.unregistered, "rule": RULE,
                "raw": figures_of(self.raw), "rigid_fit": {"name": self.rigid_name, **figures_of(self.rigid)},
                "arrows": {"before_key_mm": keys[0], "after_key_mm": keys[1]}}


def rigid_label(candidate_name: str) -> str:
    """"rigid-hand-eye" -> "rigid fit (hand-eye)"."""
    return f"rigid fit ({candidate_name.removeprefix('rigid-')})"


# The after's label where it is not held out, by what the model's digests say of the table.
SCORED_ON = {"training": "in-sample", None: "in-sample", "table": "the fit's table, mostly in-sample",
             "training-reordered": "the fit's poses in another order, in-sample",
             "table-reordered": "the fit's table in another order, mostly in-sample",
             False: "not the fit's table"}
# A model written before the digests of any order (`training_set_digest`) cannot tell its poses
# in another order from other poses.
NOT_IN_ITS_ORDER = "not the fit's table in its order"


def compare(table: PoseTable, corrected: np.ndarray, entry: Mapping[str, Any] | None = None,
            say: Callable[[str], None] | None = None, model_info: Mapping[str, Any] | None = None) -> Comparison:
    """The report's before and after for `table` and the model's (N, 7) `corrected` poses;
    `entry`: the ledger record of the fit that wrote the model (`ledger.entry_for_model`);
    `model_info`: its metadata, whose digests say whether `table` is the one it was fitted on."""
    from ..controller.digest import FITTED_SET_DIGESTS, fitted_on

    say = say or (lambda message: None)
    with_rot = table.has_orientation
    model_info = model_info or {}
    fitted = fitted_on(table.measured, table.reference, model_info, table.time())
    any_order = any(model_info.get(key) for key in FITTED_SET_DIGESTS.values())
    held, reason = _rebuilt(table, entry, fitted, any_order, say)
    if held is not None:
        rows, after, rigid_name, rigid_pred, scored = held
        after = corrected[rows] if after is None else after
    else:
        rows = np.arange(table.n)
        after = np.asarray(corrected, float)
        scored = SCORED_ON[fitted] if fitted is not False or any_order else NOT_IN_ITS_ORDER
        recorded = (entry or {}).get("baseline")
        wanted = block_name(recorded)
        rigid_name, rigid_pred = rigid_in_sample(table, wanted)
    reference, measured = table.reference[rows], table.measured[rows]
    raw = pose_metrics(reference, measured, with_rot)
    rigid = pose_metrics(reference, rigid_pred, with_rot)
    unregistered = frames_unregistered(raw, rigid)
    from .ledger import held_out as ledger_block

    return Comparison(rows, reference, rigid_pred if unregistered else measured, after, scored, held is not None,
                      unregistered, raw, rigid, rigid_name, pose_metrics(reference, after, with_rot),
                      reason, ledger_block(entry)[1] if entry else None)


def _rebuilt(table: PoseTable, entry: Mapping[str, Any] | None, fitted: str | bool | None, any_order: bool,
             say: Callable[[str], None]) -> tuple["Rebuilt | None", str]:
    """`_held_out` on `table` as the fit read it, its rows those of `table`; (None, why not)
    where the table is not the fit's (`fitted`: `digest.fitted_on`'s verdict; `any_order`:
    the model states the digests of its poses in any order), or is in another order that the
    ledger line cannot undo: the fit's folds are by row."""
    from ..controller.digest import FITTED_SET_DIGESTS, REORDERED
    from .ledger import fit_order

    if fitted is False:
        order_words = ("in any order of the rows" if any_order else
                       "in this order of the rows; the model, written before posecorr stated a digest of its poses "
                       "in any order, cannot tell them in another order from other poses")
        return None, ("these poses are not those the model was fitted on (their digest is neither the model's "
                      f"training_data_digest nor its fitted_table_digest, {order_words}): the after is the model "
                      "file on them, and what the ledger recorded was scored on the fit's own table")
    if not (isinstance(fitted, str) and fitted.endswith(REORDERED)):
        return _held_out(table, entry, say)
    order = None if entry is None else fit_order(entry, table)
    if order is None:
        return None, (f"these are the poses the model was fitted on, in another order (the model's "
                      f"{FITTED_SET_DIGESTS[fitted.removesuffix(REORDERED)]}), and the fit's folds are by row: "
                      + _no_fit_order(table, entry))
    say("the table holds the fit's poses in another order: its rows are taken in the fit's order for its folds")
    held, reason = _held_out(table.subset(order), entry, say)
    if held is None:
        return None, reason
    rows, *rest = held
    return (order[rows], *rest), ""


def _no_fit_order(table: PoseTable, entry: Mapping[str, Any] | None) -> str:
    """Why `ledger.fit_order` cannot put `table` back in the order of the fit `entry` records."""
    if entry is None:
        return "no ledger line for this model file (fits by `posecorr fit` are recorded beside the data)"
    if "row_ranks" not in entry:
        return "its ledger line has no row_ranks to put them back in that order (written by an older posecorr)"
    if entry.get("n") != table.n:
        return f"its ledger line is of a fit on a table of {entry.get('n')} poses, this one has {table.n}"
    return "its ledger line's row_ranks do not give the fit's table from these rows"


def rigid_in_sample(table: PoseTable, wanted: str | None) -> tuple[str, np.ndarray]:
    """(candidate name, (N, 7) poses) of the rigid fit on every pose: `wanted` when it is one
    the table allows, else the variant with the lowest rmse_total."""
    from ..train.pipeline import rigid_candidates, session_setup

    M, R, t = table.measured, table.reference, table.time()
    best: tuple[float, str, np.ndarray] | None = None
    for candidate in rigid_candidates(table):
        if wanted and candidate.name != wanted:
            continue
        predicted = candidate.make(session_setup(table)).fit(M, R, t=t).predict(M, t)
        score = pose_metrics(R, predicted, table.has_orientation)["rmse_total"]
        if best is None or score < best[0]:
            best = (score, candidate.name, predicted)
    if best is None:
        return rigid_in_sample(table, None)
    return best[1], best[2]


# (rows, the model's poses on them or None for the model file's own, rigid name, its poses, label)
Rebuilt = tuple[np.ndarray, "np.ndarray | None", str, np.ndarray, str]


def _held_out(table: PoseTable, entry: Mapping[str, Any] | None,
              say: Callable[[str], None]) -> tuple[Rebuilt | None, str]:
    """(`Rebuilt`, "") or (None, why the after is in-sample)."""
    from ..train.splits import FixedSplit, parse_plan

    if entry is None:
        return None, "no ledger line for this model file (fits by `posecorr fit` are recorded beside the data)"
    missing = [k for k in ("plan", "seed", "n", "baseline") if k not in entry]
    if missing:
        return None, f"the ledger line of this model lacks {', '.join(missing)} (written by an older posecorr)"
    if entry["n"] != table.n:
        return None, f"the model was fitted on a table of {entry['n']} poses, this one has {table.n}"
    try:
        plan, seed = parse_plan(entry["plan"]), int(entry["seed"])
        rigid = _rigid_candidate(table, block_name(entry["baseline"]))
        if isinstance(plan, FixedSplit):
            # The model file itself never saw the test poses; the rigid fit is refitted on the
            # others, from fit's start (the physics stage on the training rows).
            train, val, test = plan.indices(table.n, seed)
            predicted = _out_of_fold([rigid], train, [(np.union1d(train, val), test)], table)
            return (test, None, rigid.name, predicted[rigid.name][test], f"held-out ({plan.description}, {len(test)} poses)"), ""
        return _cross_validated(table, entry, plan, seed, rigid, say)
    except (KeyError, ValueError, TypeError) as exc:
        return None, f"the held-out predictions could not be rebuilt from the ledger line ({exc})"


def _cross_validated(table: PoseTable, entry: Mapping[str, Any], plan: Any, seed: int, rigid: Any,
                     say: Callable[[str], None]) -> tuple[Rebuilt | None, str]:
    from ..train.pipeline import auto_candidates, requested_candidate, spec_for_table
    from ..train.spec import ModelSpec

    spec = spec_for_table(ModelSpec(**entry["spec"]), table) if isinstance(entry.get("spec"), Mapping) else None
    effects = tuple(entry.get("effects") or ())
    everything, splits = np.arange(table.n), plan.folds(table.n, seed)
    scored = f"held-out ({plan.description}, {table.n} poses)"
    if entry.get("rigid"):
        model = _rigid_candidate(table, entry.get("chosen"))
    elif spec is None:
        return None, "the ledger line of this model lacks its spec (written by an older posecorr)"
    elif spec.method_entry.chooses:
        # scored as fit scored it: each fold by the choice made inside its training rows
        say(f"rebuilding the held-out predictions: {spec.method}'s choice inside each fold and {rigid.name}, "
            f"{plan.description}")
        chosen = _nested_out_of_fold(auto_candidates(table, effects, spec.representation), splits, seed, table, say)
        return (everything, chosen, rigid.name, _out_of_fold([rigid], everything, splits, table)[rigid.name],
                scored), ""
    else:
        model = requested_candidate(effects, spec, seed)
    say(f"rebuilding the held-out predictions: {model.name}" + ("" if model.name == rigid.name else f" and {rigid.name}")
        + f", {plan.description}")
    candidates = [model] if model.name == rigid.name else [model, rigid]
    predicted = _out_of_fold(candidates, everything, splits, table)
    return (everything, predicted[model.name], rigid.name, predicted[rigid.name], scored), ""


def _out_of_fold(candidates: list, start_rows: np.ndarray, splits: list, table: PoseTable) -> dict[str, np.ndarray]:
    """{name: (N, 7)} predictions of each held-out row (rows outside every split: undefined), as
    `posecorr fit` makes them: every fold's fit starts from the physics stage fitted on
    `start_rows` (`_priors`), so the iterative fits reach the solutions fit scored."""
    from ..train.pipeline import _priors, out_of_fold, session_setup

    arrays = (table.measured, table.reference, table.time())
    setup = session_setup(table)
    prior = _priors(candidates, start_rows, arrays, setup)
    return out_of_fold(candidates, np.arange(table.n), arrays, setup, splits, prior)


def _nested_out_of_fold(candidates: list, splits: list, seed: int, table: PoseTable,
                        say: Callable[[str], None]) -> np.ndarray:
    """(N, 7): each fold's poses predicted by the candidate chosen inside its training rows,
    from the same start as `posecorr fit --method auto` (the physics stages on every pose)."""
    from ..train.pipeline import _priors, nested_out_of_fold, session_setup

    arrays = (table.measured, table.reference, table.time())
    setup = session_setup(table)
    prior = _priors(candidates, np.arange(table.n), arrays, setup)
    return nested_out_of_fold(candidates, arrays, setup, splits, seed, prior, say)


def _rigid_candidate(table: PoseTable, name: Any) -> Any:
    from ..train.pipeline import rigid_candidates

    found = [c for c in rigid_candidates(table) if c.name == name]
    if not found:
        raise ValueError(f"no rigid fit named {name!r} for this table")
    return found[0]
