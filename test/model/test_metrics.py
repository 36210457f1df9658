"""The regression metrics (stars_ros.model.metrics) on examples worked out by hand."""
import math

import numpy as np
import pytest

from stars_ros.model.metrics import ccc, mse, pearson, regression_report

# ȳ = 2.5, p̄ = 3; deviations (-1.5, -0.5, 0.5, 1.5) and (-1, -1, 1, 1): Σ dy·dp = 4,
# Σ dy² = 5, Σ dp² = 4; squared errors 1, 0, 1, 0
Y, P = [1, 2, 3, 4], [2, 2, 4, 4]


def test_mse_pearson_and_ccc_by_hand():
    assert mse(Y, P) == pytest.approx(0.5)
    assert pearson(Y, P) == pytest.approx(4 / math.sqrt(5 * 4))
    # CCC = 2 cov / (var_y + var_p + (ȳ - p̄)²) with population moments: 2·1 / (1.25 + 1 + 0.25)
    assert ccc(Y, P) == pytest.approx(0.8)


def test_ccc_charges_an_offset_that_pearson_ignores():
    y = [1.0, 2.0, 3.0]
    assert pearson(y, [2.0, 3.0, 4.0]) == pytest.approx(1.0)
    assert ccc(y, [2.0, 3.0, 4.0]) == pytest.approx((4 / 3) / (2 / 3 + 2 / 3 + 1))  # = 4/7
    assert ccc(y, y) == pytest.approx(1.0) and mse(y, y) == 0.0
    assert pearson(y, [3.0, 2.0, 1.0]) == pytest.approx(-1.0) and ccc(y, [3.0, 2.0, 1.0]) == pytest.approx(-1.0)


def test_constant_sides_are_undefined_or_zero_as_the_formulas_say():
    assert math.isnan(pearson([1, 2, 3], [5, 5, 5]))  # r needs variance on both sides
    assert math.isnan(ccc([2, 2], [2, 2]))  # nothing varies and nothing is off: 0 / 0
    assert ccc([1, 2, 3], [2, 2, 2]) == 0.0  # no covariance, a positive denominator


def test_report_averages_each_metric_over_actions():
    """Action 0: Y, P above; action 1: y (0, 1), p (0, 3): MSE 2, r 1, CCC 1.5 / 3.5. The
    rows interleave the actions: grouping goes by action, not by position."""
    y = np.array([1, 0, 2, 3, 1, 4], float)
    p = np.array([2, 0, 2, 4, 3, 4], float)
    actions = np.array([0, 1, 0, 0, 1, 0])
    report = regression_report(y, p, actions)
    assert report['mse'] == pytest.approx((0.5 + 2.0) / 2)
    assert report['rmse'] == pytest.approx((math.sqrt(0.5) + math.sqrt(2.0)) / 2)  # not √1.25
    assert report['pearson_r'] == pytest.approx((4 / math.sqrt(20) + 1.0) / 2)
    assert report['ccc'] == pytest.approx((0.8 + 1.5 / 3.5) / 2)
    assert report['n'] == 6


def test_report_without_actions_is_one_action():
    report = regression_report(Y, P)
    assert report == {'mse': pytest.approx(0.5), 'rmse': pytest.approx(math.sqrt(0.5)),
                      'pearson_r': pytest.approx(pearson(Y, P)), 'ccc': pytest.approx(0.8), 'n': 4}
