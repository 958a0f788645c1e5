"""Friedman / Dunn-Sidak (MATLAB friedman + multcompare) and the tier list."""
from __future__ import annotations

import math

import numpy as np
import pytest

scipy_stats = pytest.importorskip("scipy.stats")

from posecorr.train import stats  # noqa: E402


def test_dunn_sidak_halfwidth_k16_n30_is_table_a1s():
    assert stats.sidak_halfwidth(16, 30) == pytest.approx(4.330, abs=1e-3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_friedman_statistic_equals_scipy_with_and_without_ties(seed):
    rng = np.random.default_rng(seed)
    data = rng.normal(size=(30, 6)) + np.arange(6) * 0.3
    if seed == 2:
        data = np.round(data, 0)  # many ties
    res = stats.friedman(data)
    ref = scipy_stats.friedmanchisquare(*data.T)
    assert res.statistic == pytest.approx(ref.statistic, rel=1e-12)
    assert res.p_value == pytest.approx(ref.pvalue, rel=1e-9)
    assert res.mean_ranks.sum() == pytest.approx(6 * 7 / 2)


def test_multcompare_reproduces_table_a1_rows():
    # k = 16 methods, n = 30 runs, no ties: sigma = sqrt(k(k+1)/12) (MATLAB's stats.sigma)
    k, n = 16, 30
    mean_ranks = np.full(k, 8.5)
    # ea-pmc vs ea-radb-16-2: diff -2.767 -> CI [-7.097, 1.564], p 0.948
    # ea-pmc vs quat-pmc:     diff  4.400 -> CI [ 0.070, 8.730], p 0.040
    mean_ranks[0], mean_ranks[1], mean_ranks[2] = 10.0, 10.0 + 2.767, 10.0 - 4.400
    res = stats.FriedmanResult(0.0, 1.0, k - 1, mean_ranks, math.sqrt(k * (k + 1) / 12), n, k)
    rows = {(c.i, c.j): c for c in stats.multcompare(res)}
    c01, c02 = rows[(0, 1)], rows[(0, 2)]
    assert (c01.lower, c01.diff, c01.upper) == pytest.approx((-7.097, -2.767, 1.564), abs=2e-3)
    assert c01.p_value == pytest.approx(0.948, abs=2e-3) and not c01.significant
    assert (c02.lower, c02.diff, c02.upper) == pytest.approx((0.070, 4.400, 8.730), abs=2e-3)
    assert c02.p_value == pytest.approx(0.040, abs=2e-3) and c02.significant
    assert len(rows) == k * (k - 1) // 2


def test_tier_list_separates_clear_groups_and_keeps_ties_together():
    rng = np.random.default_rng(3)
    n = 30
    # three groups of methods with very different RMSE levels, equal within a group
    levels = [1.0, 1.0, 1.0, 5.0, 5.0, 25.0]
    data = np.array(levels)[None, :] * (1 + 0.05 * rng.normal(size=(n, len(levels))))
    res = stats.friedman(data)
    comps = stats.multcompare(res)
    tiers = stats.tier_list(res.mean_ranks, comps)
    assert [sorted(t) for t in tiers.tiers] == [[0, 1, 2], [3, 4], [5]]
    assert res.p_value < 1e-6
    # nothing inside a tier is significantly different
    sig = {(c.i, c.j): c.significant for c in comps}
    for t in tiers.tiers:
        for a in t:
            for b in t:
                if a < b:
                    assert not sig[(a, b)]
