"""rlpipe.stats on numbers checkable by hand: IQM, (stratified) bootstrap intervals, profiles."""

from __future__ import annotations

import numpy as np
import pytest

from rlpipe import stats


def test_iqm_is_the_mean_of_the_middle_half() -> None:
    assert stats.iqm(np.arange(1.0, 9.0)) == 4.5  # mean of 3, 4, 5, 6
    # ten runs: two cut from each end, as scipy's trim_mean(x, 0.25)
    assert stats.iqm(np.array([-100.0, 0, 1, 2, 3, 4, 5, 6, 7, 1000])) == 3.5


def test_a_constant_sample_has_a_zero_width_interval() -> None:
    low, high = stats.pooled_iqm_band([np.full(10, 500.0)])
    assert low == high == 500.0


def test_one_group_is_the_plain_bootstrap() -> None:
    values = np.array([1.0, 2.0, 3.0, 10.0, 20.0])
    low, high = stats.bootstrap_band(values, "iqm", samples=500, seed=3)
    assert stats.pooled_iqm_band([values], samples=500, seed=3) == (low, high)
    assert 1.0 <= low < stats.iqm(values) < high <= 20.0


def test_the_aggregate_resamples_within_each_group() -> None:
    # within-group resamples of constant groups are the groups themselves: every draw pools
    # [1, 1, 3, 3], whose IQM is 2; a bootstrap over the pooled runs would vary
    groups = [np.array([1.0, 1.0]), np.array([3.0, 3.0])]
    assert stats.pooled_iqm(groups) == 2.0
    assert stats.pooled_iqm_band(groups) == (2.0, 2.0)
    pooled = stats.bootstrap_band(np.array([1.0, 1.0, 3.0, 3.0]), "iqm")
    assert pooled[0] < 2.0 < pooled[1]


def test_the_profile_weighs_every_group_the_same() -> None:
    taus = np.array([0.5, 1.0, 1.5])
    # group A: half its runs reach 1; group B (four runs): all of them
    groups = [np.array([0.5, 1.0]), np.array([1.0, 1.0, 1.0, 1.0])]
    assert stats.score_profile(groups, taus).tolist() == [1.0, 0.75, 0.0]
    low, high = stats.score_profile_band(groups, taus, samples=1000)
    assert low.tolist() == [1.0, 0.5, 0.0] and high.tolist() == [1.0, 1.0, 0.0]


@pytest.mark.parametrize("aggregate", ["mean", "iqm"])
def test_bootstrap_band_of_curves_holds_the_aggregate(aggregate: str) -> None:
    curves = np.array([[0.0, 1.0], [1.0, 2.0], [2.0, 3.0], [3.0, 4.0]])
    low, high = stats.bootstrap_band(curves, aggregate)
    middle = stats.AGGREGATES[aggregate](curves)
    assert low.shape == high.shape == (2,)
    assert (low <= middle).all() and (middle <= high).all() and (low < high).all()
