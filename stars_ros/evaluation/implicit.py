"""What implicit outcomes are worth: a simulation on held-out people's real ratings.

For a held-out person (``kshot.reveal_pools``: a seeded pool of their ratings, the rest are
test rows) the robot acts in the pool's scenes, cycling through them from one drawn at random
(``starts``: each pool example's first rating, equally likely), and observes one outcome per
action with the **stated noisy model**

    P(stayed) = ε / 2 + (1 − ε) · (y − L) / (H − L),

``y`` the person's true rating of that scene and action, ``L``, ``H`` the rating scale's
ends, ``ε`` the share of outcomes that are coin flips, unrelated to the action (people leave
for their own reasons). A stayed outcome is the score H, a disengagement L, folded in as the
node folds implicit feedback in (``FoldIn.noise_of``: the rating noise plus the Bernoulli
bound (H − L)² / 4). The fold-in's model is exact for ε = 0 and misspecified for ε > 0.

Against it, ``k`` explicit ratings: k pool ratings in the same turn, their true scores,
folded in as feedback, averaged over every start. Both are scored by MSE on the person's test
rows (clipped as served); n = 0 (k = 0) is the population prior's mean, what the node serves a
stranger: the unpersonalised model.
The exchange rate at k is the number of implicit outcomes whose MSE equals that of k explicit
ratings (interpolated linearly in log2 n between measured n), None when the measured range
never reaches it.
"""
from __future__ import annotations

import itertools
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

    def p_stayed(self, scores: np.ndarray, scale: tuple) -> np.ndarray:
        """P(stayed) of each true score."""
        low, high = scale
        p = np.clip((np.asarray(scores, dtype=np.float64) - low) / (high - low), 0.0, 1.0)
        return self.flip / 2 + (1.0 - self.flip) * p

    def stayed(self, rng: np.random.Generator, scores: np.ndarray, scale: tuple) -> np.ndarray:
        p = self.p_stayed(scores, scale)
        return rng.random(len(p)) < p


def starts(person: Person) -> np.ndarray:
    """Where in the pool's ratings the robot may start acting: each pool example's first."""
    return np.cumsum([0] + [len(example) for example in person.pool[:-1]])


def mse_explicit(design: Design, person: Person, k: int) -> np.ndarray:
    """Squared errors on the test rows after ``k`` pool ratings in turn, their expectation
    over the start (at k = 0 every start sees nothing: ``unpersonalised_errors``)."""
    if k == 0:
        return unpersonalised_errors(design, person)
    return np.mean([_errors(design, person, design.posterior(_acted_on(person, k, start))[0])
                    for start in starts(person)], axis=0)


def mse_implicit(design: Design, person: Person, n: int, model: OutcomeModel, rng: np.random.Generator,
                 scale: tuple) -> np.ndarray:
    """Squared errors on the test rows after ``n`` implicit outcomes drawn on the pool's
    ratings in turn from a start drawn by ``rng`` (a fresh draw each time)."""
    if n == 0:
        return unpersonalised_errors(design, person)
    rows = _acted_on(person, n, int(rng.choice(starts(person))))
    return _errors_after(design, person, rows, model.stayed(rng, design.data.scores[rows], scale), scale)


def expected_mse_implicit(design: Design, person: Person, n: int, model: OutcomeModel, scale: tuple) -> np.ndarray:
    """The expectation of ``mse_implicit``'s squared errors over the start and the outcomes
    of ``n`` actions: every start, and every one of the 2ⁿ outcome sequences weighted by its
    probability (exact, no draws; for small n, where one outcome moves the posterior most)."""
    if n == 0:
        return unpersonalised_errors(design, person)
    expected, begins = 0.0, starts(person)
    for start in begins:
        rows = _acted_on(person, n, start)
        p = model.p_stayed(design.data.scores[rows], scale)
        for stayed in itertools.product((False, True), repeat=n):
            stayed = np.array(stayed)
            expected = expected + np.prod(np.where(stayed, p, 1.0 - p)) * _errors_after(design, person, rows, stayed,
                                                                                          scale)
    return expected / len(begins)


def unpersonalised_errors(design: Design, person: Person) -> np.ndarray:
    """Squared errors on the test rows before any feedback: the one starting point that the
    explicit (k = 0) and implicit (n = 0) curves share, computed once so that they agree to
    the bit rather than up to the order of a sum."""
    return _errors(design, person, design.foldin.prior_distribution(None)[0])


def _acted_on(person: Person, n: int, start: int) -> np.ndarray:
    """The pool's rows the robot acts on, in turn from row ``start``, for ``n`` outcomes."""
    pool = person.rows(range(len(person.pool)))
    return pool[(start + np.arange(n)) % len(pool)]


def _errors_after(design: Design, person: Person, rows: np.ndarray, stayed: np.ndarray, scale: tuple) -> np.ndarray:
    """Squared errors on the test rows once the outcomes ``stayed`` of ``rows`` are folded in."""
    foldin = design.foldin
    x, c, _, actions = design.rows(rows)
    z = foldin.to_z(np.where(stayed, scale[1], scale[0]), actions)
    theta, _ = foldin.posterior(x, z - c, actions, None, np.ones(len(rows), dtype=bool))  # as the node folds them in
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
