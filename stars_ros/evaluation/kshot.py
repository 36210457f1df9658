"""The k-shot design: held-out annotators, their revealable ratings, and fold-in from them.

Library side of ``offline_training.kshot`` (which trains the models and writes the tables):
annotators dealt into leave-out folds, a seeded pool of revealable ratings per held-out
annotator (the rest are test rows, the same for every k), the fold-in design of dataset rows
under one fitted model, and the choice of the fold-in λ on the revealable pools alone, so no
test row takes part in it.
"""
from __future__ import annotations

import numpy as np
import torch

from stars_ros.errors import StarsError
from stars_ros.personalisation.foldin import FoldIn
from stars_ros.model.predictor import Predictor

PRIORS = {'fold-in': 'population', 'fold-in (zero prior)': 'zero'}
LAMBDA_GRID = (0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)


def annotator_folds(users: np.ndarray, k: int, seed: int) -> list:
    """Annotators shuffled with ``seed`` and dealt into ``k`` groups (sorted names)."""
    names = sorted(set(users.tolist()))
    if not 2 <= k <= len(names):
        raise StarsError(f'cannot deal {len(names)} annotators into {k} folds')
    order = np.random.default_rng(seed).permutation(names)
    return [sorted(part.tolist()) for part in np.array_split(order, k)]


def reveal_pools(data, annotators, pool: int, seed: int) -> dict:
    """annotator -> (revealable rows in reveal order, test rows); seeded per annotator."""
    pools = {}
    for name in annotators:
        rows = np.flatnonzero(data.users == name)
        rng = np.random.default_rng([seed, sum(map(ord, name))])
        order = rng.permutation(rows)
        if len(order) <= pool:
            raise StarsError(f'annotator {name} has {len(order)} ratings, needs more than --pool {pool}')
        pools[name] = (order[:pool], np.sort(order[pool:]))
    return pools


def encode_all(recommender, data) -> np.ndarray:
    """h_i of every scene in ``data`` [n_scenes, dim] under the fitted model."""
    rows = []
    with torch.no_grad():
        for start in range(0, len(data.scene_keys), 512):
            index = torch.arange(start, min(start + 512, len(data.scene_keys)))
            rows.append(recommender.model.encode(data.store.batch(index)).double().numpy())
    return np.concatenate(rows)


class Design:
    """Fold-in designs of dataset rows under one fitted model (h encoded once)."""

    def __init__(self, recommender, data):
        self.foldin = FoldIn(Predictor(recommender, {}, ''))
        self.data = data
        self.h = encode_all(recommender, data)

    def rows(self, rows: np.ndarray) -> tuple:
        data = self.data
        x, c = self.foldin.design_from_h(self.h[data.scenes[rows]], [data.scene_keys[s] for s in data.scenes[rows]],
                                         data.actions[rows])
        return x, c, self.foldin.to_z(data.scores[rows], data.actions[rows])

    def predict(self, rows: np.ndarray, theta: np.ndarray | None) -> np.ndarray:
        x, c, _ = self.rows(rows)
        z = c if theta is None else x @ theta + c
        return self.foldin.to_rating_scale(z, self.data.actions[rows])

    def fold_in(self, rows: np.ndarray, regularisation: float, prior: str) -> np.ndarray:
        theta = self.foldin.population.copy() if prior == 'population' else np.zeros(self.foldin.dim + 1)
        return theta if len(rows) == 0 else self.foldin.solve(*self.rows(rows), theta, regularisation)


def choose_regularisation(design: Design, pools: dict, ks, prior: str) -> tuple:
    """λ of LAMBDA_GRID with the lowest mean MSE on the revealable pools alone: fold in
    from the first k of each pool, score the rest of that pool (0 < k < pool size)."""
    data = design.data
    scores = {}
    for regularisation in LAMBDA_GRID:
        errors = []
        for revealed, _ in pools.values():
            for k in [k for k in ks if 0 < k < len(revealed)] or [len(revealed) // 2]:
                rest = revealed[k:]
                predicted = design.predict(rest, design.fold_in(revealed[:k], regularisation, prior))
                errors.append(np.mean((predicted - data.scores[rest]) ** 2))
        scores[regularisation] = float(np.mean(errors))
    return min(scores, key=scores.get), scores
