"""Corrected resampled t-test and Holm adjustment against hand-computed values."""
import math

import numpy as np
import pytest
from scipy import stats as scipy_stats

from stars_ros.evaluation.stats import corrected_resampled_ttest, format_mean_sd, holm, mean_sd


def test_corrected_ttest_matches_hand_computation():
    # d = a - b = 1..5: mean 3, sample variance 2.5, k = 5, n_test/n_train = 1/4:
    # t = 3 / sqrt((1/5 + 1/4) * 2.5) = 3 / sqrt(1.125) = 2 * sqrt(2).
    # Student t with 4 df has CDF 1/2 + (3/8) s (1 - s^2/12) with s = t / sqrt(1 + t^2/4),
    # so two-sided p = 1 - 7 sqrt(6) / 18.
    b = np.array([10.0, 10.0, 10.0, 10.0, 10.0])
    a = b + np.arange(1, 6)
    result = corrected_resampled_ttest(a, b, n_train=800, n_test=200)
    assert result.delta == pytest.approx(3.0)
    assert result.df == 4
    assert result.t == pytest.approx(2 * math.sqrt(2))
    assert result.p == pytest.approx(1 - 7 * math.sqrt(6) / 18)


def test_correction_shrinks_the_plain_paired_t():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=5), rng.normal(size=5)
    plain = scipy_stats.ttest_rel(a, b)
    corrected = corrected_resampled_ttest(a, b, n_train=80, n_test=20)
    assert corrected.t == pytest.approx(plain.statistic * math.sqrt((1 / 5) / (1 / 5 + 20 / 80)))
    assert corrected.p > plain.pvalue


def test_uneven_folds_use_the_mean_ratio():
    a, b = [1.0, 2.0, 4.0], [0.0, 0.0, 0.0]
    uneven = corrected_resampled_ttest(a, b, n_train=[100, 300, 200], n_test=[50, 50, 100])
    ratio = (0.5 + 1 / 6 + 0.5) / 3
    variance = np.var([1.0, 2.0, 4.0], ddof=1)
    assert uneven.t == pytest.approx((7 / 3) / math.sqrt((1 / 3 + ratio) * variance))


def test_zero_variance_and_bad_input():
    same = corrected_resampled_ttest([1.0, 1.0], [1.0, 1.0], 10, 5)
    assert (same.t, same.p) == (0.0, 1.0)
    shifted = corrected_resampled_ttest([2.0, 2.0], [1.0, 1.0], 10, 5)
    assert shifted.t == math.inf and shifted.p == 0.0
    with pytest.raises(ValueError):
        corrected_resampled_ttest([1.0], [2.0], 10, 5)
    with pytest.raises(ValueError):
        corrected_resampled_ttest([1.0, 2.0], [1.0], 10, 5)
    with pytest.raises(ValueError):
        corrected_resampled_ttest([1.0, math.nan], [1.0, 2.0], 10, 5)
    with pytest.raises(ValueError):
        corrected_resampled_ttest([1.0, 2.0], [1.0, 3.0], 10, 0)


def test_holm_matches_hand_computation():
    # sorted: .005*4 = .02, .01*3 = .03, .03*2 = .06, .04*1 = .04 -> monotone .06
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.5, 0.6]) == pytest.approx([1.0, 1.0])
    assert holm([0.02]) == pytest.approx([0.02])


def test_holm_leaves_nan_out_of_the_family():
    adjusted = holm([0.01, math.nan, 0.02])
    assert math.isnan(adjusted[1])
    assert adjusted[[0, 2]] == pytest.approx([0.02, 0.02])
    with pytest.raises(ValueError):
        holm([1.5])


def test_mean_sd_and_format():
    assert mean_sd([1.0, 2.0, 3.0]) == pytest.approx((2.0, 1.0))
    assert mean_sd([4.0]) == (4.0, 0.0)
    assert format_mean_sd([0.018, 0.020, 0.022]) == '0.020 ± 0.002'
    assert format_mean_sd([0.5, math.nan]) == '—'
    with pytest.raises(ValueError):
        mean_sd([])
