"""The common estimator base of the correctors (PMC, MLP).

The estimator contract (scikit-learn conventions):

* parameters in ``__init__`` (stored as given, no work: the subclasses are dataclasses),
  fitted state with a trailing underscore, ``NotFittedError`` before ``fit``;
* ``fit(measured (N, 7), reference (N, 7), t=None, validation=None) -> self`` (the signature
  of every fit in posecorr; ``validation`` a ``Validation``): learns to predict the
  REFERENCE pose parameters (position + orientation representation) from the MEASURED
  ones, as in the paper;
* ``predict(measured (N, 7)) -> (N, 7)`` float64, unit quaternion with qw >= 0;
* ``score(measured, reference) -> -rmse_total`` (higher is better: scikit-learn's
  neg-RMSE convention, so ``GridSearchCV`` and friends maximise it);
* ``forward(pose)`` maps (N, 7) -> (N, 7) written only against the ``posecorr._xp``
  namespace: ``predict`` is ``forward`` on numpy float64, the ONNX exporter traces it on
  its symbolic tensors and torch gets gradients through it;
* ``export_info() -> dict[str, str]`` and ``to_onnx(path, **metadata)``.

``representation`` is one of ``rotations.REPRESENTATIONS``: "eaa" | "quat" | "R" | "zhou",
or "pos" for a position-only corrector (Experiment I): then only x, y, z go in and out and
the orientation passes through (sign-canonicalised so that qw >= 0, the same rotation).

The pose -> input vector encoding (``encode_pose``) and the output vector -> pose decoding
(``decode_pose``) live here so that PMC and MLP share them.
"""
from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple

import numpy as np
from scipy.sparse import issparse
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.exceptions import NotFittedError

from posecorr import rotations
from posecorr.data import quaternion_faults
from posecorr._xp import namespace
from posecorr.metrics import pose_metrics


def vector_size(rep: str) -> int:
    """Length of the input / output vector: 3 position entries + the representation's."""
    return 3 + rotations.check_representation(rep).size


def encode_pose(pose: Any, rep: str) -> Any:
    """(N, 7) pose -> (N, 3 + size) vector [x, y, z, params(rep)] in any namespace."""
    xp = namespace(pose)
    p = pose[..., 0:3]
    if not rotations.check_representation(rep).orientation:
        return p
    R = rotations.quat_to_matrix(pose[..., 3:7])
    return xp.concat([p, rotations.encode(R, rep)], axis=-1)


def decode_pose(vector: Any, pose: Any, rep: str) -> Any:
    """(N, 3 + size) vector -> (N, 7) pose with a proper rotation and qw >= 0.

    ``pose`` is the input pose: its orientation passes through for a position-only ``rep``.
    """
    xp = namespace(vector, pose)
    p = vector[..., 0:3]
    if rotations.check_representation(rep).orientation:
        q = rotations.matrix_to_quat(rotations.decode(vector[..., 3:], rep))
    else:
        q = rotations.unit_quat(pose[..., 3:7])
    return xp.concat([p, q], axis=-1)


# The contract's names of a pose's columns.
POSE_COLUMNS = ("x", "y", "z", "qw", "qx", "qy", "qz")


def check_poses(a: Any, name: str, n: int | None = None) -> np.ndarray:
    """An (N, 7) finite float64 array of unit quaternions, or an error naming the argument (in
    scikit-learn's words where it has some: sparse, complex, feature(s))."""
    if issparse(a):
        raise TypeError(f"{name}: sparse input is not supported; poses are a dense (N, 7) table")
    arr = np.asarray(a)
    if arr.dtype.kind == "c":
        raise ValueError(f"{name}: Complex data not supported; poses are real (x, y, z, qw, qx, qy, qz)")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-d array of shape (N, 7) (x, y, z, qw, qx, qy, qz), got shape {arr.shape}")
    if arr.shape[1] != 7:
        need = "while a minimum of 7 is required" if arr.shape[1] < 7 else "while 7 are expected"
        raise ValueError(f"{name} has {arr.shape[1]} feature(s) (shape={arr.shape}) {need}: "
                         "x, y, z, qw, qx, qy, qz")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} has {arr.shape[0]} rows, expected {n} like measured")
    if not np.all(np.isfinite(arr)):
        row, column = (int(i) for i in np.argwhere(~np.isfinite(arr))[0])
        raise ValueError(f"{name} contains NaN or infinite values: row {row}, column {column} "
                         f"({POSE_COLUMNS[column]}) is {arr[row, column]}")
    # The runtime's and the table reader's rule: a zero or norm-3 quaternion is a glitch that
    # normalising would turn into a made-up rotation.
    off, what = quaternion_faults(arr[:, 3:])
    if off.size:
        raise ValueError(f"{name}: row {int(off[0])}: {what} (expected a unit quaternion qw, qx, qy, qz)")
    return arr


def check_times(t: Any, n: int, name: str = "t") -> np.ndarray | None:
    """None, or the poses' times as an (n,) finite float64 array (s since the session's
    start), or an error naming the argument."""
    if t is None:
        return None
    arr = np.asarray(t, dtype=np.float64)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), one time a pose in seconds, got shape {arr.shape}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise ValueError(f"{name}[{int(bad[0])}] is {arr[bad[0]]}: a pose's time must be a finite number of seconds")
    return arr


def check_pair(measured: Any, reference: Any) -> tuple[np.ndarray, np.ndarray]:
    """(measured, reference) as checked poses of equal length: what every fit starts with."""
    if reference is None:
        raise ValueError("fit requires y to be passed, but the target y is None: give the reference poses")
    measured = check_poses(measured, "measured")
    return measured, check_poses(reference, "reference", len(measured))


class Rule(NamedTuple):
    """What a numeric parameter must be: `test` of a finite real number, said as `words`;
    whole: an integer; none: None allowed (a default chosen at fit)."""

    test: Callable[[float], bool]
    words: str
    whole: bool = False
    none: bool = False


def finite_number(value: Any, whole: bool = False) -> bool:
    """Whether `value` is a finite real number (an integer where `whole`): a bool is none."""
    import numbers

    kind = numbers.Integral if whole else numbers.Real
    return isinstance(value, kind) and not isinstance(value, (bool, np.bool_)) and bool(np.isfinite(value))


def check_parameters(estimator: Any, rules: dict[str, Rule], flags: tuple[str, ...] = ()) -> None:
    """ValueError naming the first of the estimator's parameters in `rules` that breaks its
    rule (a bool is no number, nor is NaN: an LM damping of 0 never grew and the training
    never ended), or of its `flags` that is not True or False ("no" was True)."""
    for name, rule in rules.items():
        value = getattr(estimator, name)
        if value is None and rule.none:
            continue
        if not (finite_number(value, rule.whole) and rule.test(value)):
            what = "a whole number" if rule.whole else "a finite number"
            raise ValueError(f"{name} must be {'None or ' if rule.none else ''}{what} {rule.words}, got {value!r}")
    for name in flags:
        if not isinstance(getattr(estimator, name), (bool, np.bool_)):
            raise ValueError(f"{name} must be True or False, got {getattr(estimator, name)!r}")


class Validation(NamedTuple):
    """Held-out poses for early stopping: the one shape ``fit(..., validation=)`` takes everywhere."""

    measured: Any
    reference: Any
    t: Any = None


def as_validation(validation: Any) -> Validation | None:
    return None if validation is None else Validation(*validation)


def keeps_last_fit(fit: Callable[..., Any]) -> Callable[..., Any]:
    """A `fit` that raises leaves its estimator as it was: fitted state is set step by step, and
    a refusal half-way (a parameter the solver checks, a fold's data) would otherwise leave a
    model that predicts neither the last fit nor the new one."""
    @functools.wraps(fit)
    def fit_or_keep(self: Any, *args: Any, **kwargs: Any) -> Any:
        before = dict(self.__dict__)
        try:
            return fit(self, *args, **kwargs)
        except BaseException:
            self.__dict__.clear()
            self.__dict__.update(before)
            raise
    return fit_or_keep


class PoseRegressorMixin(RegressorMixin):
    """What every corrector shares: scikit-learn's tags of a regressor from (N, 7) poses to
    (N, 7) poses, and its export."""

    def to_onnx(self, path: Any, **metadata: Any) -> Any:
        """Write the fitted corrector as an ONNX model (``posecorr.export.to_onnx``)."""
        self._check_fitted()
        from posecorr.export import to_onnx

        return to_onnx(self, path, **metadata)

    def __sklearn_tags__(self) -> Any:
        tags = super().__sklearn_tags__()
        tags.target_tags.required = True
        tags.target_tags.multi_output = True
        tags.target_tags.single_output = False       # the target is the (N, 7) reference pose
        return tags


def _same(a: Any, b: Any) -> bool:
    """Whether two parameter values are equal (arrays by their text: == gives no one answer)."""
    try:
        return bool(a == b)
    except (TypeError, ValueError):
        return repr(a) == repr(b)


class BaseCorrector(PoseRegressorMixin, BaseEstimator):
    """Shared plumbing; subclasses implement ``_fit_vectors`` and ``_core``.

    A scikit-learn regressor from (N, 7) poses to (N, 7) poses: the parameters are the
    subclass's fields, the fitted state ends in an underscore, and every ``predict`` /
    export before ``fit`` raises ``NotFittedError``.
    """

    method = "base"
    uses_validation = False       # fit uses `validation` poses (an MLP: early stopping, trainbr's monitor)
    # The parameters the fitted state is built for and `predict` and the export read: one
    # changed by set_params after fit would give another model's shape to these weights.
    shaping: tuple[str, ...] = ("representation",)

    # --- fitting -----------------------------------------------------------------------
    @keeps_last_fit
    def fit(self, measured: Any, reference: Any, t: Any = None, validation: Any = None) -> "BaseCorrector":
        """Learn measured -> reference. ``t`` is taken for the common signature and checked as
        every estimator checks it (these correctors take no time input); ``validation``
        (``Validation``) is for early stopping."""
        rotations.check_representation(self.representation)
        self._check_parameters()
        measured, reference = check_pair(measured, reference)
        check_times(t, len(measured))
        if len(measured) < self.min_rows():
            raise ValueError(f"{type(self).__name__}({self.representation}) needs at least "
                             f"{self.min_rows()} poses, got {len(measured)}")
        X = encode_pose(measured, self.representation)
        Y = encode_pose(reference, self.representation)
        self._fit_vectors(np.asarray(X, np.float64), np.asarray(Y, np.float64), as_validation(validation))
        self.fitted_with_ = {name: getattr(self, name) for name in self.shaping}
        self.n_features_in_ = 7
        return self

    def _check_parameters(self) -> None:
        """ValueError where a parameter is out of its range, before any work."""

    def min_rows(self) -> int:
        """The fewest poses `fit` takes (a quadratic PMC: one more than its terms)."""
        return 1

    def n_weights(self) -> int | None:
        """The numbers `fit` sets (weights and biases), known before the fit; None where a
        core cannot say."""
        return None

    def _fit_vectors(self, X: np.ndarray, Y: np.ndarray, validation: Validation | None) -> None:
        raise NotImplementedError

    def _core(self, x: Any) -> Any:
        """Input vectors (N, d) -> output vectors (N, d), xp namespace only."""
        raise NotImplementedError

    def _check_fitted(self) -> None:
        if not hasattr(self, "n_features_in_"):
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet: call fit first")
        changed = next((name for name, value in getattr(self, "fitted_with_", {}).items()
                        if not _same(getattr(self, name), value)), None)
        if changed is not None:
            raise NotFittedError(f"this {type(self).__name__} was fitted with {changed}="
                                 f"{self.fitted_with_[changed]!r}, and set_params made it {getattr(self, changed)!r}: "
                                 "call fit again")

    # --- inference -----------------------------------------------------------------------
    def forward(self, pose: Any) -> Any:
        """(N, 7) measured pose -> (N, 7) corrected pose, in any ``posecorr._xp`` namespace."""
        self._check_fitted()
        x = encode_pose(pose, self.representation)
        y = self._core(x)
        return decode_pose(y, pose, self.representation)

    def predict(self, measured: Any, t: Any = None) -> np.ndarray:
        """Corrected poses (N, 7), float64, qw >= 0; ``t`` as in `fit` (checked, not used)."""
        self._check_fitted()
        measured = check_poses(measured, "measured")
        check_times(t, len(measured))
        return np.asarray(self.forward(measured), dtype=np.float64)

    def score(self, measured: Any, reference: Any, with_rotation: bool | None = None) -> float:
        """-rmse_total (paper eq. 43) of the prediction: higher is better (sklearn convention).

        With a position-only representation only the position error counts (Exp I).
        """
        self._check_fitted()
        measured, reference = check_pair(measured, reference)
        if with_rotation is None:
            with_rotation = rotations.check_representation(self.representation).orientation
        return -float(pose_metrics(reference, self.predict(measured), with_rotation)["rmse_total"])

    # --- export --------------------------------------------------------------------------
    def export_info(self) -> dict[str, str]:
        """What the exported file's metadata says about the corrector (after fit)."""
        raise NotImplementedError

