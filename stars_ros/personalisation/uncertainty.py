"""How sure a score is, and which question to ask a person next, from the Gaussian over θ_u.

A score's normalised prediction is z = xᵀθ + c (``InferenceModel.linear_form``) and θ_u is
Gaussian (``foldin``: N(m, Σ) — the posterior after a person's feedback, their trained row's
for a person the checkpoint knows, else the population prior). So

- **score_sd**: the predictive standard deviation of the person's rating, on the rating
  scale: σ_a · sqrt(xᵀΣx + σ²_a(noise)), σ_a the action's training standard deviation and
  σ²_a(noise) the rating noise (``UserPrior.noise``).
  Clipping the served score to the rating scale does not change it: it describes the
  unclipped predictive, whose mean the clipped score is.
- **intervals**: the predictive is a Student-t with that standard deviation and the prior's
  ν degrees of freedom (``prior.student_t_nu``; ν = ∞ is the Gaussian): the central
  ``level`` interval is score ± ``student_t_quantile(0.5 + level / 2, ν)`` · score_sd. Real rating
  errors crowd the mean more than a Gaussian of their variance says, so its 50 % interval is
  narrower and its 95 % one a little wider.
- **p_first_is_best**: the probability that the first entry's expected score is truly the
  highest of the ranking's, under the uncertainty of θ (noise excluded: it concerns what the
  person would rate on average). For more than two entries it has no closed form, so it is
  estimated from ``SAMPLES`` draws of θ with one fixed set of standard normals, drawn once:
  the same model and scene always give the same figure.
- **expected variance reduction** (``variance_reduction``): asking the person to rate
  candidate (scene, action) rows X_c reduces the summed predictive variance over a target set
  T (rating scale) by
      Σ_t σ_t² k_tᵀ (X_c Σ X_cᵀ + D_c)⁻¹ k_t,   k_t = X_c Σ x_t,
  whatever they answer (a Gaussian posterior's covariance does not depend on y): the
  A-optimal criterion of transductive experimental design. The node reports it for the
  question it asks; it asks the one of largest predictive variance (``node.questions``),
  which did better on held-out people.
- **decision value** (``log_decision_value``): what the robot is asked is to choose, not to
  predict. Each decision is a set of entries ranked together (one scene's actions, or
  candidate scenes under one action); its incumbent is the entry ranked first now. For each
  other entry a, the score gap d_a to the incumbent is Gaussian, N(μ_a, g_aᵀΣg_a); a question
  with rows X_c moves its posterior mean by a draw of N(0, s_a²),
      s_a² = (X_c Σ g_a)ᵀ (X_c Σ X_cᵀ + D_c)⁻¹ (X_c Σ g_a),
  and the expected gain of re-choosing after the answer is s_a ψ(|μ_a| / s_a),
  ψ(z) = φ(z) − z(1 − Φ(z)) (the expected value of sample information of a choice between
  two Gaussian options: Raiffa & Schlaifer 1961; the knowledge gradient of Frazier et al.
  2008). The criterion sums it over every challenger of every decision: a question is worth
  what it is expected to change in the choices, so it spends nothing on entries far from
  first place or on decisions already clear.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import math

import numpy as np
from scipy import special

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
        return float(special.ndtri(probability))
    return float(special.stdtrit(nu, probability) * math.sqrt((nu - 2) / nu))  # scipy.stats' t.ppf, without
    # importing scipy.stats (most of a second) into the serving process


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

    def spread(self, predictor, user_id, h: np.ndarray, scene_rows: np.ndarray, actions: Sequence[int],
               served_z: np.ndarray | None = None) -> Spread:
        """The ``Spread`` of entries scored from h [n, dim] (their scenes' encodings), the
        trained scene rows ``scene_rows`` [n] (UNKNOWN: none) and action columns ``actions``,
        for ``user_id`` as ``predictor`` serves them. ``served_z`` [n]: the normalised scores a
        stranger is served by the plain encoder; the spread is then centred on them (a person's
        deviation from the population, as the prior says, around the plain encoder's prediction)."""
        actions = np.asarray(actions, dtype=np.int64)
        x, c = self.inference.linear_form(np.asarray(h, dtype=np.float64), scene_rows, actions)
        covariance = self.covariance(user_id, predictor.user_model(user_id))
        theta = predictor.user_theta(user_id)
        if served_z is not None:
            c = np.asarray(served_z, dtype=np.float64) - x @ theta
        return Spread(self, x, c, actions, theta, covariance, self.rating_sd(x, actions, covariance))

    def rating_sd(self, x: np.ndarray, actions: np.ndarray, covariance: np.ndarray) -> np.ndarray:
        """Predictive sd on the rating scale [R] of rows x [R, dim+1] of ``actions`` [R]."""
        variance = np.einsum('rd,rd->r', x @ covariance, x) + self.foldin.noise[actions]  # one product, then rows
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

    def log_decision_value(self, blocks: Sequence[tuple], decisions: Sequence[tuple], mean: np.ndarray,
                           covariance: np.ndarray) -> np.ndarray:
        """log of the expected gain in the rating-scale score of the entry chosen first, summed
        over ``decisions`` (each (x [n, dim+1], c [n], actions [n]): entries ranked together),
        from each candidate question in ``blocks`` (x_c [m, dim+1], actions_c [m]), with θ ~
        N(``mean``, ``covariance``); see the module docstring. In logs because clear choices
        give gains far below the smallest float, and the questions must still be told apart;
        −inf: the question changes no choice."""
        gaps, offsets = [], []
        for x, c, actions in decisions:
            if len(x) < 2:
                continue
            std = self.inference.target_std[actions]
            rows = x * std[:, None]  # rating-scale rows: score = rows·θ + const
            score = rows @ mean + c * std + self.inference.target_mean[actions]
            first = int(np.argmax(score))
            others = np.arange(len(x)) != first
            gaps.append(rows[first] - rows[others])
            offsets.append(score[first] - score[others])
        values = np.full(len(blocks), -np.inf)
        if not gaps:
            return values
        gap_rows, gap_means = np.concatenate(gaps), np.abs(np.concatenate(offsets))
        for k, (x, actions) in enumerate(blocks):
            projected = x @ covariance
            innovation = projected @ x.T + np.diag(self.foldin.noise[actions])
            cross = projected @ gap_rows.T  # [m, gaps]
            spread = np.sqrt(np.maximum(np.sum(cross * np.linalg.solve(innovation, cross), axis=0), 0.0))
            moved = spread > 0
            if moved.any():
                values[k] = float(special.logsumexp(np.log(spread[moved]) + log_psi(gap_means[moved] / spread[moved])))
        return values


def log_psi(z: np.ndarray) -> np.ndarray:
    """log ψ(z), ψ(z) = φ(z) − z(1 − Φ(z)) for z ≥ 0 (the expected shortfall of a unit normal
    below −z), without underflow: ψ(z) = e^(−z²/2) (1/√(2π) − z erfcx(z/√2) / 2)."""
    z = np.asarray(z, dtype=np.float64)
    bracket = 1 / math.sqrt(2 * math.pi) - z * special.erfcx(z / math.sqrt(2)) / 2
    asymptotic = 1 / (math.sqrt(2 * math.pi) * (z * z + 2))  # where the difference has lost its digits
    return -z * z / 2 + np.log(np.where(z > 1e3, asymptotic, bracket))
