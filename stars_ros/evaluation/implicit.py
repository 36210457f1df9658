"""What implicit outcomes are worth: a simulation on held-out people's real ratings.

For a held-out person (``kshot.reveal_pools``: a seeded pool of their ratings, the rest are
test rows) the robot acts in the pool's scenes, cycling through them, and observes one
outcome per action with the **stated noisy model**

    P(stayed) = ε / 2 + (1 − ε) · (y − L) / (H − L),

``y`` the person's true rating of that scene and action, ``L``, ``H`` the rating scale's
ends, ``ε`` the share of outcomes that are coin flips, unrelated to the action (people leave
for their own reasons). A stayed outcome is the score H, a disengagement L, folded in as the
node folds implicit feedback in (``FoldIn.noise_of``: the rating noise plus the Bernoulli
bound (H − L)² / 4). The fold-in's model is exact for ε = 0 and misspecified for ε > 0.

Against it, ``k`` explicit ratings: the first k pool ratings, their true scores, folded in as
feedback. Both are scored by MSE on the person's test rows (clipped as served); n = 0 (k = 0)
is the population prior's mean, what the node serves a stranger: the unpersonalised model.
The exchange rate at k is the number of implicit outcomes whose MSE equals that of k explicit
ratings (interpolated linearly in log2 n between measured n), None when the measured range
never reaches it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stars_ros.evaluation.kshot import Design, Person


@dataclass(frozen=True)
class OutcomeModel:
    """The stated noisy model: ``flip`` = ε, the share of outcomes that are coin flips."""

    flip: float = 0.0

    def __post_init__(self):
        if not 0.0 <= self.flip <= 1.0:
            raise ValueError(f'flip must be in [0, 1], got {self.flip}')

    def stayed(self, rng: np.random.Generator, scores: np.ndarray, scale: tuple) -> np.ndarray:
        low, high = scale
        p = np.clip((np.asarray(scores, dtype=np.float64) - low) / (high - low), 0.0, 1.0)
        return rng.random(len(p)) < self.flip / 2 + (1.0 - self.flip) * p


def mse_explicit(design: Design, person: Person, k: int) -> tuple:
    """(squared errors on the test rows, rows) after the first ``k`` pool ratings."""
    pool = person.rows(range(len(person.pool)))
    theta, _ = design.posterior(pool[:k])
    return _errors(design, person, theta)


def mse_implicit(design: Design, person: Person, n: int, model: OutcomeModel, rng: np.random.Generator,
                 scale: tuple) -> tuple:
    """(squared errors on the test rows, rows) after ``n`` implicit outcomes drawn on the
    pool's ratings in turn (a fresh draw each time)."""
    foldin = design.foldin
    if n == 0:
        return _errors(design, person, foldin.prior_distribution(None)[0])
    pool = person.rows(range(len(person.pool)))
    rows = pool[np.arange(n) % len(pool)]
    x, c, _, actions = design.rows(rows)
    stayed = model.stayed(rng, design.data.scores[rows], scale)
    z = foldin.to_z(np.where(stayed, scale[1], scale[0]), actions)
    theta, _ = foldin.posterior(x, z - c, actions, None, np.ones(n, dtype=bool))  # as the node folds them in
    return _errors(design, person, theta)


def _errors(design: Design, person: Person, theta: np.ndarray) -> np.ndarray:
    predicted = design.predict(person.test, theta)
    return (predicted - design.data.scores[person.test]) ** 2


def exchange_rate(ns, implicit_mse, target: float) -> float | None:
    """Implicit outcomes whose MSE equals ``target``: the first crossing of the measured curve,
    linear in log2 n (n = 0 is placed at log2 n = −1); None if it never gets there."""
    xs = [math.log2(n) if n > 0 else -1.0 for n in ns]
    for (x0, m0), (x1, m1) in zip(zip(xs, implicit_mse), zip(xs[1:], implicit_mse[1:])):
        if m0 >= target >= m1 and m0 != m1:
            x = x0 + (m0 - target) / (m0 - m1) * (x1 - x0)
            return 0.0 if x <= -1.0 else 2.0 ** x
        if m0 <= target:
            return 0.0 if x0 <= -1.0 else 2.0 ** x0
    return None
