"""Friedman test, Dunn-Sidak multiple comparison of mean ranks, and the tier list.

As MATLAB's ``[p, tbl, stats] = friedman(X, 1)`` followed by
``multcompare(stats, "CType", "dunn-sidak")`` (paper section 3.3, table A1, table 5).

X is (n runs) x (k methods) of total RMSE; within each run the methods are ranked,
1 = the lowest RMSE (ties get the average rank). With mean ranks Rbar_j:

* sigma^2 = sum_ij (r_ij - (k+1)/2)^2 / (n (k-1))  (= k(k+1)/12 without ties; with ties it
  is the tie-corrected rank variance, MATLAB's ``stats.sigma``);
* Friedman chi^2 = n sum_j (Rbar_j - (k+1)/2)^2 / sigma^2 with k - 1 degrees of freedom
  (equals ``scipy.stats.friedmanchisquare``, tie correction included);
* pairwise differences of mean ranks have the standard error se = sigma sqrt(2 / n); the
  Dunn-Sidak interval is diff +- z se with z = Phi^-1(1 - a/2), a = 1 - (1 - alpha)^(1/m),
  m = k(k-1)/2 comparisons; the adjusted p-value is 1 - (1 - 2 Phi(-|diff| / se))^m.
  For k = 16, n = 30, alpha = 0.05: half-width 4.330 (table A1).

Tier list (table 5), the algorithm: sort the methods by mean rank (best first). A tier
starts at the best method not yet placed and takes every following method (in rank order)
whose difference to the tier's first method is NOT significant; the first method that is
significantly worse than the tier's leader opens the next tier. Because all pairs share
one interval width, the leader has the largest difference to every member, so no two
methods inside a tier differ significantly. Whether every method of tier i is significantly
better than every method of tier i+1 is not guaranteed by ranks alone; ``tier_list``
reports the pairs where it fails in ``overlaps`` (empty when the tiers separate cleanly).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np


@dataclass
class FriedmanResult:
    statistic: float
    p_value: float
    df: int
    mean_ranks: np.ndarray
    sigma: float
    n: int
    k: int


@dataclass
class Comparison:
    i: int
    j: int
    lower: float
    diff: float        # mean_rank[i] - mean_rank[j]
    upper: float
    p_value: float

    @property
    def significant(self) -> bool:
        return self.lower > 0 or self.upper < 0


@dataclass
class Tiers:
    tiers: list[list[int]]
    overlaps: list[tuple[int, int]] = field(default_factory=list)


def rank_rows(data: np.ndarray) -> np.ndarray:
    """Ranks within each row (1 = smallest value), ties averaged."""
    from scipy.stats import rankdata

    return rankdata(np.asarray(data, float), axis=1)


def friedman(data: np.ndarray) -> FriedmanResult:
    """Friedman test on an (n runs, k methods) array (MATLAB ``friedman(X, 1)``)."""
    from scipy.stats import chi2

    data = np.asarray(data, float)
    if data.ndim != 2 or data.shape[0] < 2 or data.shape[1] < 2:
        raise ValueError(f"friedman needs an (n >= 2 runs, k >= 2 methods) array, got {data.shape}")
    n, k = data.shape
    r = rank_rows(data)
    mean_ranks = r.mean(axis=0)
    centre = (k + 1) / 2.0
    sigma2 = float(np.sum((r - centre) ** 2) / (n * (k - 1)))
    if sigma2 == 0:  # every run ties every method
        return FriedmanResult(0.0, 1.0, k - 1, mean_ranks, 0.0, n, k)
    stat = n * float(np.sum((mean_ranks - centre) ** 2)) / sigma2
    return FriedmanResult(stat, float(chi2.sf(stat, k - 1)), k - 1, mean_ranks, math.sqrt(sigma2), n, k)


def sidak_halfwidth(k: int, n: int, alpha: float = 0.05, sigma: float | None = None) -> float:
    """Half-width of the Dunn-Sidak interval on mean-rank differences (no ties: sigma^2 = k(k+1)/12)."""
    from scipy.stats import norm

    if sigma is None:
        sigma = math.sqrt(k * (k + 1) / 12.0)
    m = k * (k - 1) / 2.0
    a = 1.0 - (1.0 - alpha) ** (1.0 / m)
    return float(norm.isf(a / 2.0)) * sigma * math.sqrt(2.0 / n)


def multcompare(result: FriedmanResult, alpha: float = 0.05) -> list[Comparison]:
    """All pairs i < j, as the rows of MATLAB ``multcompare(..., 'dunn-sidak')``."""
    from scipy.stats import norm

    k, n = result.k, result.n
    m = k * (k - 1) / 2.0
    se = result.sigma * math.sqrt(2.0 / n)
    half = sidak_halfwidth(k, n, alpha, result.sigma)
    rows = []
    for i in range(k):
        for j in range(i + 1, k):
            d = float(result.mean_ranks[i] - result.mean_ranks[j])
            if se > 0:
                p_single = 2.0 * float(norm.sf(abs(d) / se))
                p = 1.0 - (1.0 - p_single) ** m
            else:
                p = 1.0
            rows.append(Comparison(i, j, d - half, d, d + half, float(min(1.0, max(0.0, p)))))
    return rows


def tier_list(mean_ranks: Sequence[float], comparisons: Sequence[Comparison]) -> Tiers:
    """Tiers of method indices (best tier first), see the module docstring."""
    mean_ranks = np.asarray(mean_ranks, float)
    sig = {}
    for c in comparisons:
        sig[(c.i, c.j)] = sig[(c.j, c.i)] = c.significant
    order = list(np.argsort(mean_ranks, kind="stable"))
    tiers: list[list[int]] = []
    current: list[int] = []
    for idx in order:
        if current and sig.get((current[0], idx), False):
            tiers.append(current)
            current = []
        current.append(int(idx))
    if current:
        tiers.append(current)
    overlaps = []
    for t in range(len(tiers) - 1):
        for a in tiers[t]:
            for b in tiers[t + 1]:
                if not sig.get((a, b), False):
                    overlaps.append((a, b))
    return Tiers(tiers, overlaps)
