"""Significance of paired cross-validation differences and summaries over folds.

Folds of one cross-validation share most of their training rows, so their scores are not
independent and the plain paired t-test is too liberal. The corrected resampled t-test
(Nadeau & Bengio 2003; Bouckaert & Frank 2004) inflates the variance of the mean
difference by the training-set overlap:

    t = mean(d) / sqrt((1/k + n_test/n_train) · σ²),    df = k − 1

with d the per-fold differences, σ² their sample variance (ddof 1) and k the number of
folds. Several tests in one family are Holm-adjusted (step-down, controls the
family-wise error rate).
"""
from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np
from scipy import stats as scipy_stats


class PairedTest(NamedTuple):
    """Result of a corrected resampled paired t-test; ``delta`` is mean(a − b)."""

    delta: float
    t: float
    df: int
    p: float


def corrected_resampled_ttest(a: Sequence[float], b: Sequence[float],
                              n_train, n_test) -> PairedTest:
    """Bouckaert–Frank corrected resampled paired t-test of per-fold scores ``a`` vs ``b``.

    Args:
        a, b (sequence of float): one score per fold, paired by position.
        n_train, n_test (int or sequence of int): training and test rows of each fold;
            when folds differ in size (grouped folds), the mean ratio n_test/n_train is used.

    A zero variance gives t = ±inf and p = 0 when the mean difference is non-zero, and
    t = 0, p = 1 when every difference is zero.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f'a and b must be 1-D and of equal length, got {a.shape} and {b.shape}')
    k = len(a)
    if k < 2:
        raise ValueError(f'the test needs at least 2 folds, got {k}')
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError('scores must be finite')
    n_train = np.broadcast_to(np.asarray(n_train, float), (k,))
    n_test = np.broadcast_to(np.asarray(n_test, float), (k,))
    if (n_train <= 0).any() or (n_test <= 0).any():
        raise ValueError('n_train and n_test must be positive')
    d = a - b
    delta = float(d.mean())
    variance = float(d.var(ddof=1))
    df = k - 1
    if variance == 0.0:
        if delta == 0.0:
            return PairedTest(delta, 0.0, df, 1.0)
        return PairedTest(delta, math.copysign(math.inf, delta), df, 0.0)
    ratio = float((n_test / n_train).mean())
    t = delta / math.sqrt((1.0 / k + ratio) * variance)
    p = float(2.0 * scipy_stats.t.sf(abs(t), df))
    return PairedTest(delta, float(t), df, p)


def holm(pvalues: Sequence[float]) -> np.ndarray:
    """Holm step-down adjusted p-values, in the order given.

    Sorted ascending, the j-th smallest (j from 1) becomes max over i ≤ j of
    min(1, (m − i + 1) · p_(i)). NaN entries stay NaN and do not count in m.
    """
    p = np.asarray(pvalues, float)
    if p.ndim != 1:
        raise ValueError('pvalues must be 1-D')
    if ((p < 0) | (p > 1)).any():
        raise ValueError('p-values must lie in [0, 1]')
    adjusted = np.full(len(p), np.nan)
    valid = np.flatnonzero(~np.isnan(p))
    m = len(valid)
    order = valid[np.argsort(p[valid], kind='stable')]
    running = 0.0
    for rank, index in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[index]))
        adjusted[index] = running
    return adjusted


def mean_sd(values: Sequence[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof 1; 0 for one value); NaN if any is NaN."""
    v = np.asarray(values, float)
    if len(v) == 0:
        raise ValueError('mean_sd of no values')
    if np.isnan(v).any():
        return math.nan, math.nan
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0


def format_mean_sd(values: Sequence[float], digits: int = 3) -> str:
    """``'0.018 ± 0.002'``; ``'—'`` when undefined (e.g. Pearson r of a constant predictor)."""
    mean, sd = mean_sd(values)
    if math.isnan(mean):
        return '—'
    return f'{mean:.{digits}f} ± {sd:.{digits}f}'
