"""Regression metrics, macro-averaged over actions (each action weighs the same)."""
from __future__ import annotations

import numpy as np


def mse(y, p) -> float:
    return float(np.mean((np.asarray(y, float) - np.asarray(p, float)) ** 2))


def pearson(y, p) -> float:
    """Pearson r; NaN when either side is constant (r is undefined there)."""
    y, p = np.asarray(y, float), np.asarray(p, float)
    dy, dp = y - y.mean(), p - p.mean()
    denominator = np.sqrt((dy ** 2).sum() * (dp ** 2).sum())
    return float((dy * dp).sum() / denominator) if denominator > 0 else float('nan')


def ccc(y, p) -> float:
    """Lin's concordance correlation: 2 cov / (var_y + var_p + (mean_y - mean_p)²)."""
    y, p = np.asarray(y, float), np.asarray(p, float)
    covariance = np.mean((y - y.mean()) * (p - p.mean()))
    denominator = y.var() + p.var() + (y.mean() - p.mean()) ** 2
    return float(2 * covariance / denominator) if denominator > 0 else float('nan')


def regression_report(y, p, actions=None) -> dict:
    """MSE, RMSE, Pearson r and CCC, each computed per action then averaged.

    RMSE is the mean of per-action RMSEs (not the root of the mean MSE), as tables
    on 1-5 scales report it.
    """
    y, p = np.asarray(y, float), np.asarray(p, float)
    actions = np.zeros(len(y), int) if actions is None else np.asarray(actions)
    per_action = []
    for action in np.unique(actions):
        mask = actions == action
        m = mse(y[mask], p[mask])
        per_action.append((m, np.sqrt(m), pearson(y[mask], p[mask]), ccc(y[mask], p[mask])))
    values = np.array(per_action)
    return {'mse': float(values[:, 0].mean()), 'rmse': float(values[:, 1].mean()),
            'pearson_r': float(values[:, 2].mean()), 'ccc': float(values[:, 3].mean()),
            'n': int(len(y))}


def normalised_rmse(y, p, actions, target_mean, target_std) -> float:
    """RMSE of z-scores (per-action mean/std of the training split), macro over actions."""
    y, p, actions = np.asarray(y, float), np.asarray(p, float), np.asarray(actions)
    errors = (p - y) / np.asarray(target_std, float)[actions]
    return float(np.mean([np.sqrt(np.mean(errors[actions == a] ** 2)) for a in np.unique(actions)]))
