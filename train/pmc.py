"""Polynomial Model Correction (paper section 2.3, eqs. 24-37).

Every output k of the vector [x, y, z, params(rep)] is a full quadratic polynomial of all
d inputs: X'_k = sum_{i<=j} a_kij X_i X_j + sum_i b_ki X_i + c_k (eqs. 24-26), i.e. all
squares, all cross terms, the linear terms and a constant: 1 + d + d(d+1)/2 coefficients
per output (d = 3 position only, 6 eaa, 7 quat, 12 R, 9 zhou).

Numerics (what differs from a textbook normal-equation fit, not the model):

* the inputs are scaled to [-1, 1] per column (min/max of the training set) before the
  features are formed, so the columns of the design matrix have comparable size, but no
  column is stretched beyond STRETCH_LIMIT times its unit's widest (`column_scaling`; the
  units: the position, the representation's parameters). A column the data barely moves
  (the tilt of a session turned about one axis only, the paper's Exp II: 0.2 to 0.8 % of
  the yaw's span) holds noise about a constant; stretched to [-1, 1], its terms escape the
  ridge, and the polynomial moves a pose tilted 5 degrees by metres and turns float32
  rounding into millimetres. Without a ridge (alpha 0, which the cross-validation may
  choose) the scaling changes nothing of the fit. Exp III's columns span 20 % of their
  unit's widest and more: the limit leaves them as they were;
* the coefficients are found with an SVD-based least squares solve (``numpy.linalg.lstsq``),
  never the normal equations (which square the condition number);
* the fit is done on the correction Y - X and the identity is folded back into the
  coefficients afterwards: without a ridge term this is exactly the paper's model; with one
  (``alpha > 0``, or ``alpha="cv"`` = K-fold cross-validation over ``alpha_grid``) the
  coefficients shrink towards "no correction" instead of towards zero output. The constant
  term is never penalised.

``forward`` is a fixed graph: scale (constants) -> quadratic feature vector built with xp
ops -> ONE ``xp.linear`` (a Gemm) -> decode. Outputs are decoded to a proper rotation by
``rotations.decode`` (Rodrigues / normalisation / projection / Gram-Schmidt).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from posecorr._xp import namespace

from .base import BaseCorrector, Rule, Validation, check_parameters, finite_number, vector_size

DEFAULT_ALPHA_GRID = (0.0, 1e-10, 1e-8, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0)


def n_features(d: int, degree: int = 2) -> int:
    """Number of non-constant features of d inputs: d linear (+ d(d+1)/2 products if quadratic)."""
    return d + (d * (d + 1) // 2 if degree == 2 else 0)


def quadratic_features(xs: Any, degree: int = 2) -> Any:
    """(N, d) -> (N, d + d(d+1)/2): [x_1..x_d, x_i x_j for i <= j (row-major)], any namespace.
    degree 1: the linear terms alone (an affine map)."""
    if degree == 1:
        return xs
    xp = namespace(xs)
    d = xs.shape[-1]
    products = [xs[..., i] * xs[..., j] for i in range(d) for j in range(i, d)]
    return xp.concat([xs, xp.stack(products, axis=-1)], axis=-1)


STRETCH_LIMIT = 10.0


def column_scaling(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """gain, offset with X * gain + offset centred per column and in [-1, 1], each column's
    span taken as at least 1 / STRETCH_LIMIT of the widest in its unit (positions: the first
    3 columns; the representation's: the rest); a unit of constant columns keeps gain 1."""
    lo, hi = X.min(axis=0), X.max(axis=0)
    span = hi - lo
    gain = np.ones(X.shape[1])
    for unit in (slice(0, 3), slice(3, None)):
        widest = float(np.max(span[unit], initial=0.0))
        if widest > 1e-12 * max(1.0, float(np.max(np.abs(hi[unit]), initial=0.0))):
            gain[unit] = 2.0 / np.maximum(span[unit], widest / STRETCH_LIMIT)
    return gain, -0.5 * (lo + hi) * gain


def _solve(F: np.ndarray, T: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of T on [F, 1] with ridge alpha on F's columns: (W, b)."""
    n, p = F.shape
    A = np.concatenate([F, np.ones((n, 1))], axis=1)
    if alpha > 0:
        reg = np.zeros((p, p + 1))
        reg[:, :p] = np.sqrt(alpha * n) * np.eye(p)  # alpha scales with n: per-sample ridge
        A = np.concatenate([A, reg], axis=0)
        T = np.concatenate([T, np.zeros((p, T.shape[1]))], axis=0)
    coef, *_ = np.linalg.lstsq(A, T, rcond=None)
    return coef[:p], coef[p]


def _ridge_path(F: np.ndarray, T: np.ndarray, alphas: Sequence[float]) -> list[tuple[np.ndarray, np.ndarray]]:
    """`_solve` for every alpha from one SVD: with the columns centred, the unpenalised
    constant separates and the ridge solution is V diag(s / (s^2 + alpha n)) U^T T (alpha 0:
    the minimum-norm least squares, singular values below lstsq's cut-off dropped)."""
    n = len(F)
    mean_F, mean_T = F.mean(axis=0), T.mean(axis=0)
    U, s, Vt = np.linalg.svd(F - mean_F, full_matrices=False)
    UtT = U.T @ (T - mean_T)
    cutoff = np.finfo(float).eps * max(F.shape) * (s[0] if s.size else 0.0)
    out = []
    for alpha in alphas:
        if alpha > 0:
            d = s / (s * s + alpha * n)
        else:
            d = np.where(s > cutoff, 1.0 / np.where(s > cutoff, s, 1.0), 0.0)
        W = Vt.T @ (d[:, None] * UtT)
        out.append((W, mean_T - mean_F @ W))
    return out


@dataclass(repr=False, eq=False)
class PMC(BaseCorrector):
    """Polynomial Model Correction: a full quadratic least-squares map per output.

    Parameters
    ----------
    representation : "pos" | "eaa" | "quat" | "R" | "zhou"
    alpha : float or "cv"
        Ridge weight per sample (objective mean squared residual + alpha * |coef|^2, the
        constant unpenalised); 0 = the paper's plain least squares. "cv" picks it from
        ``alpha_grid`` by ``cv_folds``-fold cross-validation (useful for small data sets).
    alpha_grid : sequence of float
    cv_folds : int
    random_state : int, seed of the CV fold assignment.
    degree : 2 (the paper's quadratic) or 1 (affine: the small-table candidate of `auto`).
    """

    representation: str = "zhou"
    alpha: float | str = 0.0
    alpha_grid: Sequence[float] = DEFAULT_ALPHA_GRID
    cv_folds: int = 5
    random_state: int = 0
    degree: int = 2

    method = "pmc"
    shaping = ("representation", "degree")

    def _check_parameters(self) -> None:
        if isinstance(self.degree, bool) or self.degree not in (1, 2):
            raise ValueError(f"degree must be 1 (affine) or 2 (quadratic), got {self.degree!r}")
        if self.alpha != "cv":
            check_parameters(self, {"alpha": Rule(lambda v: v >= 0, ">= 0 or 'cv'")})
            return
        check_parameters(self, {"cv_folds": Rule(lambda v: v >= 2, ">= 2", whole=True)})
        grid = list(self.alpha_grid) if not isinstance(self.alpha_grid, str) else []
        if not grid or not all(finite_number(a) and a >= 0 for a in grid):
            raise ValueError(f"alpha_grid must hold one or more finite numbers >= 0, got {self.alpha_grid!r}")

    def min_rows(self) -> int:
        d = vector_size(self.representation)
        return n_features(d, self.degree) + 1 if self.alpha in (0, 0.0) else 2

    def n_weights(self) -> int:
        d = vector_size(self.representation)
        return (n_features(d, self.degree) + 1) * d

    def _fit_vectors(self, X: np.ndarray, Y: np.ndarray, validation: Validation | None) -> None:
        # validation is ignored: PMC is not iterative.
        gain, offset = column_scaling(X)
        F = np.asarray(quadratic_features(X * gain + offset, self.degree))
        T = Y - X
        if self.alpha == "cv":
            alpha, self.cv_scores_ = self._cross_validate(F, T)
        else:
            alpha = float(self.alpha)
            self.__dict__.pop("cv_scores_", None)   # a refit with a given alpha scored none
        W, b = _solve(F, T, alpha)
        # Fold the identity back in: X = (xs - offset) / gain is linear in the features.
        d = X.shape[1]
        W = W.copy()
        W[np.arange(d), np.arange(d)] += 1.0 / gain
        b = b - offset / gain
        self.alpha_ = alpha
        self.input_gain_, self.input_offset_ = gain, offset
        self.coef_, self.intercept_ = W, b
        self.train_rmse_vector_ = float(np.sqrt(np.mean((self._core(X) - Y) ** 2)))

    def _cross_validate(self, F: np.ndarray, T: np.ndarray) -> tuple[float, dict[float, float]]:
        from .splits import KFold

        n = len(F)
        grid = [float(a) for a in self.alpha_grid]
        sse = np.zeros(len(grid))
        for train, test in KFold(max(2, min(int(self.cv_folds), n))).folds(n, self.random_state):
            for i, (W, b) in enumerate(_ridge_path(F[train], T[train], grid)):
                sse[i] += float(np.sum((F[test] @ W + b - T[test]) ** 2))
        scores = {alpha: float(np.sqrt(e / T.size)) for alpha, e in zip(grid, sse)}
        best = min(scores, key=lambda a: (scores[a], -a))
        return best, scores

    def _core(self, x: Any) -> Any:
        xp = namespace(x)
        xs = x * xp.const(self.input_gain_, x) + xp.const(self.input_offset_, x)
        return xp.linear(quadratic_features(xs, self.degree), self.coef_, self.intercept_)

    def export_info(self) -> dict[str, str]:
        self._check_fitted()
        d = vector_size(self.representation)
        return {"method": "pmc", "representation": self.representation,
                "architecture": f"{'quadratic' if self.degree == 2 else 'affine'}-{d}in-"
                                f"{n_features(d, self.degree) + 1}terms",
                # a penalty chosen by fit's cross-validation is a ridge fit, not plain least squares
                "activation": "none", "trainer": "ridge" if self.alpha_ else "lstsq",
                "ridge_alpha": repr(self.alpha_),
                "n_parameters": str(self.coef_.size + self.intercept_.size),
                "train_rmse_vector": f"{self.train_rmse_vector_:.6g}"}
