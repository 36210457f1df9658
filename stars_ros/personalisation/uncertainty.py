"""How sure a score is, and which question to ask a person next, from the Gaussian over θ_u.

A score's normalised prediction is z = xᵀθ + c (``InferenceModel.linear_form``) and θ_u is
Gaussian (``foldin``: N(m, Σ) — the posterior after a person's feedback, their trained row's
for a person the checkpoint knows, else the population prior). So

- **score_sd**: the predictive standard deviation of the person's rating, on the rating
  scale: σ_a · sqrt(xᵀΣx + σ²_a(noise)), σ_a the action's training standard deviation.
  Clipping the served score to the rating scale does not change it: it describes the
  unclipped predictive, whose mean the clipped score is.
- **intervals**: the predictive is a Student-t with that standard deviation and the prior's
  ν degrees of freedom (``prior.student_t_nu``; ν = ∞ is the Gaussian): the central
  ``level`` interval is score ± ``student_t_quantile(0.5 + level / 2, ν)`` · score_sd. Real rating errors crowd the mean more than a Gaussian of
  their variance says, so its 50 % interval is narrower and its 95 % one a little wider.
- **p_first_is_best**: the probability that the first entry's expected score is truly the
  highest of the ranking's, under the uncertainty of θ (noise excluded: it concerns what the
  person would rate on average). For more than two entries it has no closed form, so it is
  estimated from ``SAMPLES`` draws of θ with one fixed set of standard normals, drawn once:
  the same model and scene always give the same figure.
- **question choice**: asking the person to rate candidate (scene, action) rows X_c reduces
  the summed predictive variance over a target set T (rating scale) by
      Σ_t σ_t² k_tᵀ (X_c Σ X_cᵀ + D_c)⁻¹ k_t,   k_t = X_c Σ x_t,
  whatever they answer (a Gaussian posterior's covariance does not depend on y). This is the
  A-optimal (expected-variance) criterion of transductive experimental design. It is chosen
  over information gain on θ (D-optimal) because the robot needs better predictions on the
  scenes it will meet, not a better θ: directions of θ those scenes never load on would pull
  a D-optimal question towards them for nothing.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import math

import numpy as np
from scipy import stats

from stars_ros.state import loaded

SAMPLES = 512  # draws of θ for p_first_is_best (fixed seed)


@dataclass(frozen=True)
class Spread:
    """The Gaussian of one ranking's entries for one person: their rows x [n, dim+1], offsets
    c [n] and ``actions`` [n], θ's mean and covariance, and each entry's ``sd`` [n]."""

    uncertainty: 'Uncertainty'
    x: np.ndarray
    c: np.ndarray
    actions: np.ndarray
    theta: np.ndarray
    covariance: np.ndarray
    sd: np.ndarray

    def p_first_is_best(self, first: int) -> float:
        """P(entry ``first`` truly has the highest expected score of these entries)."""
        return self.uncertainty.p_first_is_best(self.x, self.c, self.actions, self.theta, self.covariance, first)


def student_t_quantile(probability: float, nu: float) -> float:
    """The ``probability`` quantile of the unit-variance Student-t with ``nu`` degrees of
    freedom (the standard normal's for ν = ∞)."""
    if math.isinf(nu):
        return float(stats.norm.ppf(probability))
    return float(stats.t.ppf(probability, nu) * math.sqrt((nu - 2) / nu))


class Uncertainty:
    """Predictive spread and question choice against one ``FoldIn`` (its model, prior, noise)."""

    def __init__(self, foldin):
        self.foldin = foldin
        self.inference = foldin.inference
        self._normals = np.random.default_rng(0).standard_normal((SAMPLES, foldin.dim + 1))

    def covariance(self, user_id, model=None) -> np.ndarray:
        """Cov θ serving ``user_id``: their folded-in ``model``'s posterior when it has one,
        else their prior (trained row's, or the population's)."""
        if model is not None and model.covariance is not None:
            return loaded(model.covariance)
        return self.foldin.covariance(user_id)

    def spread(self, predictor, user_id, h: np.ndarray, scene_rows: np.ndarray, actions: Sequence[int]) -> Spread:
        """The ``Spread`` of entries scored from h [n, dim] (their scenes' encodings), the
        trained scene rows ``scene_rows`` [n] (UNKNOWN: none) and action columns ``actions``,
        for ``user_id`` as ``predictor`` serves them."""
        actions = np.asarray(actions, dtype=np.int64)
        x, c = self.inference.linear_form(np.asarray(h, dtype=np.float64), scene_rows, actions)
        covariance = self.covariance(user_id, predictor.user_model(user_id))
        return Spread(self, x, c, actions, predictor.user_theta(user_id), covariance,
                      self.rating_sd(x, actions, covariance))

    def rating_sd(self, x: np.ndarray, actions: np.ndarray, covariance: np.ndarray) -> np.ndarray:
        """Predictive sd on the rating scale [R] of rows x [R, dim+1] of ``actions`` [R]."""
        variance = np.einsum('rd,de,re->r', x, covariance, x) + self.foldin.noise[actions]
        return np.sqrt(np.maximum(variance, 0.0)) * self.inference.target_std[actions]

    def p_first_is_best(self, x: np.ndarray, c: np.ndarray, actions: np.ndarray, mean: np.ndarray,
                        covariance: np.ndarray, first: int) -> float:
        """P(entry ``first`` has the highest expected rating-scale score among rows x [R, dim+1])."""
        if len(x) == 1:
            return 1.0
        factor = np.linalg.cholesky(covariance + 1e-12 * np.eye(len(mean)))
        thetas = mean + self._normals @ factor.T
        scores = (thetas @ x.T + c) * self.inference.target_std[actions] + self.inference.target_mean[actions]
        return float(np.mean(np.argmax(scores, axis=1) == first))

    def variance_reduction(self, blocks: Sequence[tuple], targets: tuple, covariance: np.ndarray) -> np.ndarray:
        """Expected drop of the summed rating-scale predictive variance over ``targets``
        (x_T [T, dim+1], actions_T [T]) for each candidate question in ``blocks``, each
        (x_c [m, dim+1], actions_c [m]): the rows a person's answer would rate."""
        target_x, target_actions = targets
        weight = self.inference.target_std[target_actions] ** 2
        gains = np.empty(len(blocks))
        for k, (x, actions) in enumerate(blocks):
            projected = x @ covariance  # [m, dim+1]
            innovation = projected @ x.T + np.diag(self.foldin.noise[actions])
            cross = projected @ target_x.T  # [m, T]
            gains[k] = float(np.sum(weight * np.sum(cross * np.linalg.solve(innovation, cross), axis=0)))
        return gains
