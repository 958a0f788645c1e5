"""Which poses a model is scored on: the protocol's fixed split and the cross-validation plans.

A plan is a value, parsed once from what a user typed (`parse_plan`: "none", "loo" or a
number of folds) and handed on as it is:

* `FixedSplit`: the paper's protocol (section 2.4): a fixed test set, 15 % of the rows drawn
  once with the seed, and per repeat a fresh train / validation split of the rest
  (`split_indices`).
* `KFold`: K random folds of whole poses; every pose is predicted by a fit that never saw it.
* `LeaveOneOut`: as many folds as poses.

Every fold and split of posecorr's poses comes from here: `fit`, `fit --cv`, auto's inner
choice, the diagnosis, the sweep, PMC's choice of its ridge penalty and a network's own
early-stopping split (`validation_split`).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from enum import StrEnum
from typing import ClassVar

import numpy as np

TEST_FRACTION = 0.15
VAL_FRACTION = 0.15
# The second word of each draw's seed: the test set's stream depends on the seed alone, the
# train / validation stream on (seed, repeat) as well, so no repeat moves the test set.
TEST_STREAM = 7919
REPEAT_STREAM = 104729

Folds = list[tuple[np.ndarray, np.ndarray]]


class HeldOut(StrEnum):
    """What a held-out score rests on (and its key in `fit --json`)."""

    TEST = "test"          # a fixed test split
    CV = "cv"              # out-of-fold predictions


def split_indices(n: int, seed: int = 0, repeat: int = 0, test_fraction: float = TEST_FRACTION,
                  val_fraction: float = VAL_FRACTION) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(train, validation, test) row indices: the test set depends on ``seed`` only,
    the train/validation split of the rest on (seed, repeat). Fractions are of all rows."""
    n_test = int(round(test_fraction * n))
    order = np.random.default_rng([int(seed), TEST_STREAM]).permutation(n)
    test, rest = np.sort(order[:n_test]), order[n_test:]
    n_val = int(round(val_fraction * n))
    perm = np.random.default_rng([int(seed), int(repeat), REPEAT_STREAM]).permutation(rest)
    return np.sort(perm[n_val:]), np.sort(perm[:n_val]), test


def validation_split(n: int, fraction: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(train, held) rows of a network's own early-stopping split: a random `fraction` of the
    n rows (at least one) drawn from `rng`, in the order drawn (the generator then goes on to
    the initial weights)."""
    order = rng.permutation(n)
    n_val = max(1, int(round(fraction * n)))
    return order[n_val:], order[:n_val]


def _folds(order: np.ndarray, k: int) -> Folds:
    parts = np.array_split(order, k)
    return [(np.sort(np.concatenate(parts[:i] + parts[i + 1:])), np.sort(parts[i])) for i in range(k)]


@dataclass(frozen=True)
class FixedSplit:
    """The protocol's fixed, seeded test set (and per repeat a train / validation split of the rest)."""

    test_fraction: float = TEST_FRACTION
    val_fraction: float = VAL_FRACTION
    heldout: ClassVar[HeldOut] = HeldOut.TEST

    def indices(self, n: int, seed: int = 0, repeat: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(train, validation, test), `split_indices`."""
        return split_indices(n, seed, repeat, self.test_fraction, self.val_fraction)

    def test_recipe(self, seed: int = 0) -> str:
        """The test rows of `indices(N, seed)` as a numpy expression in N, written from the
        draw itself (the model cards state it and tests/test_models.py evaluates it)."""
        return (f"numpy.sort(numpy.random.default_rng([{int(seed)}, {TEST_STREAM}]).permutation(N)"
                f"[:round({self.test_fraction!r} * N)])")

    @property
    def description(self) -> str:
        return "test split"

    def __str__(self) -> str:
        return "none"


@dataclass(frozen=True)
class KFold:
    """K folds of whole poses in a seeded random order."""

    k: int
    heldout: ClassVar[HeldOut] = HeldOut.CV

    def __post_init__(self) -> None:
        if int(self.k) < 2:
            raise ValueError(f"cross-validation needs at least 2 folds, got {self.k}")

    def folds(self, n: int, seed: int = 0) -> Folds:
        """(train, held-out) index pairs, each sorted."""
        if self.k > n:
            raise ValueError(f"{self.k} folds need at least {self.k} poses, got {n}")
        return _folds(np.random.default_rng(seed).permutation(n), int(self.k))

    @property
    def description(self) -> str:
        return f"{self.k} folds"

    def __str__(self) -> str:
        return str(self.k)


@dataclass(frozen=True)
class LeaveOneOut:
    """One fold per pose (the seed plays no part)."""

    heldout: ClassVar[HeldOut] = HeldOut.CV

    def folds(self, n: int, seed: int = 0) -> Folds:
        return _folds(np.arange(n), n)

    @property
    def description(self) -> str:
        return "leave one out"

    def __str__(self) -> str:
        return "loo"


CrossValidationPlan = KFold | LeaveOneOut
Plan = FixedSplit | KFold | LeaveOneOut


# What a table of n poses can bear. Below MIN_TEST_SPLIT a 15 % test split holds a handful of
# poses, so the table is cross-validated instead: every pose held out once (leave one out) up
# to LOO_MAX_POSES, five folds beyond. A choice nested inside each fold's training set (auto's)
# multiplies its cost by the outer folds: it leaves one out only below NESTED_LOO_BELOW poses.
MIN_TEST_SPLIT = 100
LOO_MAX_POSES = 40
NESTED_LOO_BELOW = 10


def plan_for(n: int, nested: bool = False) -> CrossValidationPlan:
    """The cross-validation n poses can bear (the rule above): for a table's held-out score,
    or, `nested`, for a choice made inside an outer fold's training poses."""
    if nested:
        return LeaveOneOut() if n < NESTED_LOO_BELOW else KFold(5)
    return LeaveOneOut() if n <= LOO_MAX_POSES else KFold(5)


# The fewest poses a fit takes (a rigid registration needs three points): the physics stage
# and the rigid fits refuse fewer, and the folds are checked against it before any work.
MIN_FIT_POSES = 3


def fewest_to_fit(n: int, plan: CrossValidationPlan, nested: bool = False) -> int:
    """The fewest poses a fold of `plan` on n poses leaves to fit on; `nested`: the fewest that
    the cross-validation of a choice made inside such a fold (`plan_for(m, nested=True)`, auto's)
    leaves."""
    k = n if isinstance(plan, LeaveOneOut) else min(int(plan.k), n)
    fewest = n - -(-n // max(k, 1))                  # the largest held-out part is ceil(n / k)
    return fewest_to_fit(fewest, plan_for(fewest, nested=True)) if nested and fewest > 1 else fewest


def fewest_rows_to_fit(nested: bool = False, needs: int = MIN_FIT_POSES) -> int:
    """The fewest rows on which some plan (leave one out, and `nested`: the choice made inside
    its folds) leaves every fit `needs` poses."""
    return next(m for m in itertools.count(2) if fewest_to_fit(m, LeaveOneOut(), nested) >= needs)


def require_enough_to_fit(n: int, plan: Plan, nested: bool = False, needs: int = MIN_FIT_POSES,
                          model: str = "a fit") -> None:
    """ValueError when a fold of `plan` (and, `nested`, the choice made inside it) would fit on
    fewer than `needs` poses (what `model` needs, MIN_FIT_POSES at least), naming the folds that
    would do, or the rows it takes; or when it asks for more folds than n rows, naming the
    most it takes."""
    if isinstance(plan, FixedSplit):
        return
    needs = max(needs, MIN_FIT_POSES)
    fewest = fewest_to_fit(n, plan, nested)
    if fewest >= needs:
        # more folds than rows: counted above as n folds of one pose each, which fit, the most there are
        if isinstance(plan, KFold) and plan.k > n:
            raise ValueError(f"{n} rows, but {plan.k} folds need at least {plan.k}: at most {n} folds (--cv {n}), "
                             "or --cv loo")
        return
    where = "a choice made inside a fold (auto's)" if nested else "a fold"
    more = [k for k in range(int(getattr(plan, "k", n)) + 1, n + 1) if fewest_to_fit(n, KFold(k), nested) >= needs]
    advice = (f"more folds (--cv {more[0]})" if more
              else f"at least {fewest_rows_to_fit(nested, needs)} rows (with --cv loo)")
    raise ValueError(f"{n} rows, but with {plan.description} {where} fits on {fewest} of them, and {model} needs "
                     f"at least {needs}: {advice}")


def parse_plan(text: str | int | None) -> Plan:
    """"none" (or None): the fixed test split; "loo": leave one out; a number: that many folds."""
    if text is None or text == "none":
        return FixedSplit()
    if text == "loo":
        return LeaveOneOut()
    try:
        k = int(text)
    except ValueError:
        raise ValueError(f"cross-validation takes none, loo or a number of folds, got {text!r}") from None
    return KFold(k)
