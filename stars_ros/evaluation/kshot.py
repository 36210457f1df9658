"""The k-shot design: held-out people, their revealable examples, the order in which they are
asked (random, uncertainty, active), and the Bayesian fold-in from what they answered.

Library side of ``offline_training.kshot`` (which trains the models and writes the tables).
Everything is dealt by example (one person's ratings of one scene, every action), as the rows
protocol deals its folds: a person's pool holds examples, a question reveals one whole
example, and the test rows are the person's other examples, the same for every k and every
strategy, so the curves compare. A person with fewer than two examples is left out (counted);
one with fewer than ``pool + 1`` gets a smaller pool and covers only the k it allows.

Strategies choose the next question from the person's unrevealed pool examples, given the
posterior after the answers so far:

- ``random``: k pool examples drawn at random, what unprompted feedback gives; its metrics are
  the mean over ``random_sets``: every set of k pool examples where there are at most
  ``EXACT_SETS`` of them (the exact expectation over the draw), else that many seeded sets
  (a few seeded orders are too noisy an estimate to tell a small gain from a loss);
- ``uncertainty``: the example whose ratings have the largest summed predictive variance (the
  node's criterion);
- ``active``: the example whose answer most reduces the summed predictive variance over the
  whole pool (``Uncertainty.variance_reduction``: the A-optimal criterion);
- ``decision``: the example whose answer is expected to improve the choices made on the pool
  most (``Uncertainty.log_decision_value``): each pool example's actions are one decision, or,
  where the data have a single action, the pool's scenes are ranked as one set of candidates.

Neither looks at a test row or at an answer before it is given.
"""
from __future__ import annotations

import itertools
import math
import zlib
from dataclasses import dataclass

import numpy as np

from stars_ros.data.splits import held_examples
from stars_ros.errors import StarsError
from stars_ros.model.scoring import served_encodings, served_plain_scores
from stars_ros.personalisation.foldin import solve_ridge
from stars_ros.personalisation.prior import rows_design
from stars_ros.personalisation.stack import serving_stack
from stars_ros.personalisation.uncertainty import student_t_quantile

STRATEGIES = ('random', 'uncertainty', 'active', 'decision')
NODE_STRATEGY = 'uncertainty'  # the criterion the node's stars/question_request uses (node.questions)
LEVELS = (0.5, 0.8, 0.9, 0.95)  # central predictive intervals whose coverage is measured


EXACT_SETS = 1140  # the most sets of k pool examples enumerated whole (every 3 of 20)


def random_sets(person: 'Person', name: str, k: int, count: int, seed: int) -> list:
    """The sets of k of ``person``'s pool examples whose mean stands for a random draw:
    every one when there are at most ``EXACT_SETS`` (the first is the pool's first k), else
    the pool's first k and ``count`` − 1 seeded draws."""
    size = len(person.pool)
    k = min(k, size)
    if math.comb(size, k) <= EXACT_SETS:
        return [list(chosen) for chosen in itertools.combinations(range(size), k)]
    rng = np.random.default_rng([seed, k, zlib.crc32(name.encode())])
    return [list(range(k))] + [sorted(int(e) for e in rng.choice(size, k, replace=False)) for _ in range(count - 1)]


def annotator_folds(users: np.ndarray, k: int, seed: int) -> list:
    """Annotators shuffled with ``seed`` and dealt into ``k`` groups (sorted names)."""
    names = sorted(set(users.tolist()))
    if not 2 <= k <= len(names):
        raise StarsError(f'cannot deal {len(names)} annotators into {k} folds')
    order = np.random.default_rng(seed).permutation(names)
    return [sorted(part.tolist()) for part in np.array_split(order, k)]


@dataclass(frozen=True)
class Person:
    """A held-out person: their pool examples in the seeded random order (each the array of
    its rows) and their test rows."""

    pool: tuple
    test: np.ndarray

    def rows(self, examples) -> np.ndarray:
        """The rows of pool examples ``examples`` (indices into ``pool``)."""
        return np.concatenate([self.pool[e] for e in examples]) if len(examples) else np.zeros(0, dtype=np.int64)


def reveal_pools(data, people, pool: int, seed: int) -> tuple[dict, dict]:
    """({person: Person}, {person left out: their example count}); seeded per person."""
    examples = data.examples
    pools, left_out = {}, {}
    for name in people:
        rows = np.flatnonzero(data.users == name)
        ids = np.unique(examples[rows])
        size = min(pool, len(ids) - 1)
        if size < 1:
            left_out[name] = int(len(ids))
            continue
        order = np.random.default_rng([seed, sum(map(ord, name))]).permutation(ids)
        chosen = [rows[examples[rows] == e] for e in order[:size]]
        pools[name] = Person(tuple(chosen), np.sort(rows[~np.isin(examples[rows], order[:size])]))
    return pools, left_out


def known_split(data, rows: np.ndarray, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(training rows, held-out rows) of ``rows``: a seeded ``fraction`` of their examples held
    out, so that known people's calibration is measured on ratings the model did not fit."""
    examples = data.examples[rows]
    out = held_examples(examples, int(round(fraction * len(np.unique(examples)))), np.random.default_rng([seed, 7]))
    return rows[~out], rows[out]


class Design:
    """Fold-in and predictive distributions of dataset rows under one fitted model (every
    scene encoded once). A new person's rows are as the node serves them: around the plain
    encoder where the model keeps one for strangers (``FoldIn.hand_over_shift``)."""

    def __init__(self, fitted, data):
        self.data = data
        stack = serving_stack(fitted)  # the served form, as the node folds people in
        self.predictor, self.foldin, self.uncertainty = stack.predictor, stack.require_foldin(), stack.uncertainty
        self.inference = self.foldin.inference
        self.h = served_encodings(self.predictor, data)
        self._plain = None  # a new person is served around the plain encoder, where the model keeps one
        if self.predictor.stranger_inference is not None:
            self._plain = served_plain_scores(self.predictor, data)

    def rows(self, rows: np.ndarray, user_id=None) -> tuple:
        """(x, c, z, actions) of dataset ``rows`` as ``user_id`` is served (None: a new person)."""
        x, c, z = rows_design(self.predictor, self.data, rows, self.h)
        actions = self.data.actions[rows]
        if self._plain is not None and self.predictor.hands_over(user_id):
            plain = self._plain[self.data.scenes[rows], actions]
            c = c + self.foldin.shift(self.inference.to_z(plain, actions), x, c)
        return x, c, z, actions

    def posterior(self, rows: np.ndarray, user_id=None, regularisation: float | None = None) -> tuple:
        """(θ mean, covariance) after the ratings of ``rows`` (none: the prior of ``user_id``,
        the population's for a new person), by ``FoldIn.posterior`` as the node solves it; a
        positive ``regularisation``: the ridge solve."""
        x, c, z, actions = self.rows(rows, user_id)
        if regularisation and len(rows):
            theta = solve_ridge(x, z - c, self.foldin.prior(user_id), regularisation)
            return theta, float(self.foldin.noise.mean()) * np.linalg.inv(x.T @ x + regularisation * np.eye(len(theta)))
        return self.foldin.posterior(x, z - c, actions, user_id)

    def predict(self, rows: np.ndarray, theta: np.ndarray | None) -> np.ndarray:
        """Rating-scale predictions of a new person's ``rows``, clipped as served; θ None: the
        scene-only model (p_u = 0, b_u = 0, the model's own offsets)."""
        if theta is None:
            x, c, z = rows_design(self.predictor, self.data, rows, self.h)
            return self.predict_design((x, c, z, self.data.actions[rows]), None)
        return self.predict_design(self.rows(rows), theta)

    def predict_design(self, design: tuple, theta: np.ndarray | None) -> np.ndarray:
        """``predict`` of rows whose ``rows(...)`` is ``design`` (computed once, for many θ)."""
        x, c, _, actions = design
        z = c if theta is None else x @ theta + c
        return self.predictor.clip(self.inference.to_rating_scale(z, actions))

    def posterior_design(self, design: tuple, with_covariance: bool = True) -> tuple:
        """``posterior`` of a new person from rows whose ``rows(...)`` is ``design`` (covariance
        None unless ``with_covariance``)."""
        x, c, z, actions = design
        return self.foldin.posterior(x, z - c, actions, with_covariance=with_covariance)

    def predictive(self, rows: np.ndarray, theta: np.ndarray, covariance: np.ndarray, user_id=None) -> tuple:
        """(mean, sd) of the predictive distribution of ``user_id``'s ``rows`` on the rating
        scale (unclipped)."""
        return self.predictive_design(self.rows(rows, user_id), theta, covariance)

    def predictive_design(self, design: tuple, theta: np.ndarray, covariance: np.ndarray) -> tuple:
        """``predictive`` of rows whose ``rows(...)`` is ``design``."""
        x, c, _, actions = design
        return self.inference.to_rating_scale(x @ theta + c, actions), self.uncertainty.rating_sd(x, actions,
                                                                                                  covariance)

    def reveal_order(self, person: Person, strategy: str, count: int) -> list:
        """The first ``count`` pool examples ``strategy`` asks about, in order."""
        if strategy == 'random':
            return list(range(min(count, len(person.pool))))
        if strategy not in STRATEGIES:
            raise StarsError(f"unknown strategy '{strategy}'; choose from {list(STRATEGIES)}")
        blocks = [self.rows(rows) for rows in person.pool]
        targets = (np.concatenate([b[0] for b in blocks]), np.concatenate([b[3] for b in blocks]))
        decisions = [(b[0], b[1], b[3]) for b in blocks]
        if all(len(b[0]) == 1 for b in blocks):
            decisions = [(targets[0], np.concatenate([b[1] for b in blocks]), targets[1])]
        asked = []
        while len(asked) < min(count, len(person.pool)):
            theta, covariance = self.posterior(person.rows(asked))
            remaining = [e for e in range(len(person.pool)) if e not in asked]
            if strategy == 'uncertainty':
                gains = [np.sum(self.uncertainty.rating_sd(blocks[e][0], blocks[e][3], covariance) ** 2)
                         for e in remaining]
            elif strategy == 'decision':
                gains = self.uncertainty.log_decision_value([(blocks[e][0], blocks[e][3]) for e in remaining],
                                                            decisions, theta, covariance)
            else:
                gains = self.uncertainty.variance_reduction([(blocks[e][0], blocks[e][3]) for e in remaining], targets,
                                                            covariance)
            asked.append(remaining[int(np.argmax(gains))])
        return asked


def coverage(y: np.ndarray, mean: np.ndarray, sd: np.ndarray, nu: float = math.inf) -> dict:
    """{level: share of ``y`` inside the central interval of the predictive with ``mean``,
    standard deviation ``sd`` and ν = ``nu`` (Student-t; inf: Gaussian)} for ``LEVELS``."""
    return {str(level): float(np.mean(np.abs(y - mean) <= student_t_quantile(0.5 + level / 2, nu) * sd))
            for level in LEVELS}
