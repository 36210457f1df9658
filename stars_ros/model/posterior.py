"""Posterior means of StARS's factorisation part, by blocked Gibbs sampling over a frozen encoder.

With h_i fixed, the StARS prediction

    ŷ(u, i, a) = (p_u ⊙ (q_i + h_i) + ρ h_i)ᵀ r_a + b_u + b_i + b        (ρ = 1 with the residual)

is linear in each block given the others: in (p_u, b_u) with features ((q_i + h_i) ⊙ r_a, 1),
in (q_i, b_i) with features (p_u ⊙ r_a, 1), in r_a with features p_u ⊙ (q_i + h_i) + ρ h_i,
and in b. So under Gaussian priors every block's conditional is Gaussian, and a Gibbs sweep
draws the prior precisions and the noise precision from their Gamma conditionals, then each
block in turn (one batched Cholesky solve per block: k × k, or m × m in observation form for
scenes with fewer ratings m than weights k), as in BPMF (Salakhutdinov & Mnih 2008)
and myFM. The priors have mean zero (an unseen user or scene is a zero row, the population's)
and a learned precision per group and factor dimension (users' factors, scenes' factors,
actions' factors; one for each offset group), so the shrinkage ``embedding_l2`` sets by hand
during training is learned here; b has a flat prior. Parts a variant holds at zero stay zero.

``posterior_head`` starts the chain at the trained weights, keeps the running mean of every
parameter after ``burn_in`` sweeps and writes those means into the model: one model, served
at today's cost. The h_i entering additively breaks plain MF's rotational symmetry, so the
parameter means are a meaningful model; how far its predictions are from the averaged
predictions is measured on the training rows (``PosteriorSummary.plug_in_gap``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np
import torch

from stars_ros.model.model import StarsModel

#: Shape and rate of the Gamma hyperprior on every prior precision and on the noise
#: precision: weak (myFM's defaults), on z-scored targets.
GAMMA_SHAPE, GAMMA_RATE = 1.0, 1.0
ENCODE_BATCH = 2048


class Observations(NamedTuple):
    """Rated entries, one per (example, action): user, item and action rows [N] (-1 for a
    user or item the tables lack), the example's h [N, dim] and the target z-score [N]."""

    users: torch.Tensor
    items: torch.Tensor
    actions: torch.Tensor
    h: torch.Tensor
    targets: torch.Tensor


class GaussianRows(NamedTuple):
    """Independent Gaussians, one per row of a block, in precision form: means [R, k] and the
    Cholesky factors [R, k, k] of their precisions (for rows with as many observations as weights, or more)."""

    mean: torch.Tensor
    precision_cholesky: torch.Tensor

    @property
    def covariance(self) -> torch.Tensor:
        return torch.cholesky_inverse(self.precision_cholesky)

    def draw(self, rng: np.random.Generator) -> torch.Tensor:
        """One sample of every row: mean + L⁻ᵀ z has covariance (L Lᵀ)⁻¹."""
        noise = torch.from_numpy(rng.standard_normal(self.mean.shape)).unsqueeze(-1)
        return self.mean + torch.linalg.solve_triangular(self.precision_cholesky.mT, noise, upper=True).squeeze(-1)


class ObservedGaussianRows(NamedTuple):
    """The same posteriors in observation form, for rows with fewer observations m than weights
    k (a scene's one or two ratings): prior variances S [R, k], features X [R, m, k], targets
    t [R, m], noise variance σ² and the Cholesky factors of K = σ²I + X S Xᵀ [R, m, m], so
    that everything costs m × m solves (Woodbury; draws by Matheron's rule)."""

    prior_variance: torch.Tensor
    features: torch.Tensor
    targets: torch.Tensor
    noise_variance: torch.Tensor
    gram_cholesky: torch.Tensor

    def _posterior_shift(self, residuals: torch.Tensor) -> torch.Tensor:
        """S Xᵀ K⁻¹ residuals, per row."""
        solved = torch.cholesky_solve(residuals.unsqueeze(-1), self.gram_cholesky)
        return self.prior_variance * (self.features.mT @ solved).squeeze(-1)

    @property
    def mean(self) -> torch.Tensor:
        return self._posterior_shift(self.targets)

    @property
    def covariance(self) -> torch.Tensor:
        scaled = self.features * self.prior_variance.unsqueeze(1)  # X S
        return torch.diag_embed(self.prior_variance) - scaled.mT @ torch.cholesky_solve(scaled, self.gram_cholesky)

    def draw(self, rng: np.random.Generator) -> torch.Tensor:
        """w₀ + S Xᵀ K⁻¹ (t − X w₀ − ε), w₀ ~ N(0, S), ε ~ N(0, σ²I), is a draw of the posterior."""
        prior_draw = torch.from_numpy(rng.standard_normal(self.prior_variance.shape)) * self.prior_variance.sqrt()
        noise = torch.from_numpy(rng.standard_normal(self.targets.shape)) * self.noise_variance.sqrt()
        fitted = (self.features @ prior_draw.unsqueeze(-1)).squeeze(-1)
        return prior_draw + self._posterior_shift(self.targets - fitted - noise)


RowPosteriors = GaussianRows | ObservedGaussianRows


class Layout(NamedTuple):
    """Observations grouped by the row they update: indices [rows, most per row] and which
    of them are real (1.0) rather than padding (0.0)."""

    index: torch.Tensor
    present: torch.Tensor

    @classmethod
    def of(cls, rows: torch.Tensor, n_rows: int) -> 'Layout':
        order = torch.argsort(rows, stable=True)
        counts = torch.bincount(rows, minlength=n_rows)
        starts = torch.cumsum(counts, 0) - counts
        position = torch.arange(len(rows)) - starts[rows[order]]
        index = torch.zeros(n_rows, max(int(counts.max()), 1), dtype=torch.long)
        present = torch.zeros(index.shape, dtype=torch.float64)
        index[rows[order], position] = order
        present[rows[order], position] = 1.0
        return cls(index, present)


def gaussian_rows(features: torch.Tensor, targets: torch.Tensor, layout: Layout,
                  prior_precision: torch.Tensor, noise_precision: torch.Tensor) -> RowPosteriors:
    """The posterior of each row's weights w_r in targets ≈ features · w_row, noise precision τ,
    prior w_r ~ N(0, diag(prior_precision)⁻¹): precision Λ + τ XᵀX, mean its inverse times τ Xᵀt.
    With observations laid out per row, each row is one batched product; in observation form
    (``ObservedGaussianRows``) when rows have fewer observations than weights. Padding has
    zero features and targets, so it changes neither form."""
    x = features[layout.index] * layout.present.unsqueeze(-1)
    t = targets[layout.index] * layout.present
    rows, most, width = x.shape
    if most < width:
        prior_variance = (1 / prior_precision).expand(rows, -1)
        noise_variance = 1 / noise_precision
        gram = noise_variance * torch.eye(most, dtype=x.dtype) + (x * prior_variance.unsqueeze(1)) @ x.mT
        return ObservedGaussianRows(prior_variance, x, t, noise_variance, torch.linalg.cholesky(gram))
    precision = torch.diag_embed(prior_precision.expand(rows, -1)) + noise_precision * x.mT @ x
    cholesky = torch.linalg.cholesky(precision)
    mean = torch.cholesky_solve(noise_precision * (x.mT @ t.unsqueeze(-1)), cholesky).squeeze(-1)
    return GaussianRows(mean, cholesky)


@dataclass
class Factors:
    """The factorisation part of a StARS model, float64: p [U, dim], b_u [U], q [I, dim],
    b_i [I], r [A, dim] and b []."""

    p: torch.Tensor
    user_bias: torch.Tensor
    q: torch.Tensor
    scene_bias: torch.Tensor
    r: torch.Tensor
    bias: torch.Tensor

    @classmethod
    def of(cls, model: StarsModel) -> 'Factors':
        with torch.no_grad():
            return cls(model.user_embedding.weight.double().clone(), model.user_bias.weight[:, 0].double().clone(),
                       model.scene_embedding.weight.double().clone(), model.scene_bias.weight[:, 0].double().clone(),
                       model.action_embedding.double().clone(), model.bias[0].double().clone())

    @torch.no_grad()
    def write_to(self, model: StarsModel) -> None:
        model.user_embedding.weight.copy_(self.p)
        model.user_bias.weight.copy_(self.user_bias.unsqueeze(1))
        model.scene_embedding.weight.copy_(self.q)
        model.scene_bias.weight.copy_(self.scene_bias.unsqueeze(1))
        model.action_embedding.copy_(self.r)
        model.bias.fill_(float(self.bias))

    def scaled(self, factor: float) -> 'Factors':
        return Factors(*(getattr(self, f.name) * factor for f in fields(self)))

    def plus(self, other: 'Factors') -> 'Factors':
        return Factors(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))


def _rows(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Rows of ``table`` for ``index``, zeros where it is -1 (a user or scene the tables lack)."""
    known = index >= 0
    rows = table[index.clamp(min=0)]
    return rows * (known.unsqueeze(-1) if rows.dim() > 1 else known)


class Chain:
    """A Gibbs chain over ``model``'s factorisation part on fixed ``observations``; its state
    (``factors``, ``precisions``) starts at the model's weights and moves with ``sweep``.

    ``precisions`` holds, by part, the prior precision of each group (per factor dimension for
    p, q and r; one for each offset group b_u, b_i) and the noise precision (``noise``); the
    first sweep draws them afresh from the start, so their initial values only matter to a
    caller of the conditionals."""

    def __init__(self, model: StarsModel, observations: Observations, seed: int):
        self.parts = model.parts
        self.residual = 1.0 if model.residual else 0.0
        self.factors = Factors.of(model)
        self.observations = observations
        self.rng = np.random.default_rng(seed)
        dim = self.factors.r.shape[1]
        sizes = {'p': dim, 'q': dim, 'r': dim, 'b_u': 1, 'b_i': 1, 'noise': ()}
        self.precisions = {part: torch.ones(size, dtype=torch.float64) for part, size in sizes.items()}
        self.layouts = {'users': Layout.of(observations.users, len(self.factors.p)),
                        'scenes': Layout.of(observations.items, len(self.factors.q)),
                        'actions': Layout.of(observations.actions, len(self.factors.r))}

    def predict(self, observations: Observations | None = None, factors: Factors | None = None) -> torch.Tensor:
        """z-scores of ``observations`` (the chain's own by default) under ``factors`` (the current ones)."""
        o = self.observations if observations is None else observations
        f = self.factors if factors is None else factors
        interaction = _rows(f.p, o.users) * (_rows(f.q, o.items) + o.h) + self.residual * o.h
        return ((interaction * f.r[o.actions]).sum(1) + _rows(f.user_bias, o.users)
                + _rows(f.scene_bias, o.items) + f.bias)

    # -- the conditionals of the blocks -------------------------------------------------
    def user_conditional(self) -> RowPosteriors:
        """(p_u, b_u) for each user: features ((q_i + h_i) ⊙ r_a, 1), the parts the variant has."""
        o, f = self.observations, self.factors
        return self._conditional('users', [('p', (f.q[o.items] + o.h) * f.r[o.actions], f.p),
                                           ('b_u', torch.ones(len(o.users), 1, dtype=torch.float64),
                                            f.user_bias.unsqueeze(1))])

    def scene_conditional(self) -> RowPosteriors:
        """(q_i, b_i) for each scene: features (p_u ⊙ r_a, 1), the parts the variant has."""
        o, f = self.observations, self.factors
        return self._conditional('scenes', [('q', f.p[o.users] * f.r[o.actions], f.q),
                                            ('b_i', torch.ones(len(o.users), 1, dtype=torch.float64),
                                             f.scene_bias.unsqueeze(1))])

    def action_conditional(self) -> RowPosteriors:
        """r_a for each action: features p_u ⊙ (q_i + h_i) + ρ h_i."""
        o, f = self.observations, self.factors
        return self._conditional('actions', [('r', f.p[o.users] * (f.q[o.items] + o.h) + self.residual * o.h, f.r)])

    def _conditional(self, group: str, columns: list) -> RowPosteriors:
        """The block of ``columns`` (part, features [N, k], current weights [rows, k]) that the
        variant has, given everything else: its targets are y minus the rest of ŷ."""
        rows = {'users': self.observations.users, 'scenes': self.observations.items,
                'actions': self.observations.actions}[group]
        kept = [(part, x, w) for part, x, w in columns if part in self.parts or part == 'r']  # r: asked when it acts
        features = torch.cat([x for _, x, _ in kept], 1)
        weights = torch.cat([w for _, _, w in kept], 1)
        targets = self.observations.targets - self.predict() + (features * weights[rows]).sum(1)
        precision = torch.cat([self.precisions[part] for part, _, _ in kept])
        return gaussian_rows(features, targets, self.layouts[group], precision, self.precisions['noise'])

    # -- one sweep ----------------------------------------------------------------------
    def sweep(self) -> None:
        """Precisions given the weights, then b, (p, b_u), (q, b_i) and r, each given the rest."""
        self._draw_precisions()
        f, o = self.factors, self.observations
        residual = o.targets - self.predict() + f.bias
        f.bias = residual.mean() + self.rng.standard_normal() / torch.sqrt(self.precisions['noise'] * len(residual))
        if self.parts & {'p', 'b_u'}:
            f.p, f.user_bias = self._split(self.user_conditional().draw(self.rng), 'p', 'b_u', f.p, f.user_bias)
        if self.parts & {'q', 'b_i'}:
            f.q, f.scene_bias = self._split(self.scene_conditional().draw(self.rng), 'q', 'b_i', f.q, f.scene_bias)
        if self.acts:
            f.r = self.action_conditional().draw(self.rng)

    @property
    def acts(self) -> bool:
        """Whether r_a enters a prediction at all (through p_u or the h_i residual)."""
        return 'p' in self.parts or bool(self.residual)

    def _split(self, drawn, factor_part, bias_part, factor, bias):
        """The new (factor, offset) from a block's draw: the columns of the parts it holds."""
        if factor_part in self.parts:
            factor, drawn = drawn[:, :factor.shape[1]], drawn[:, factor.shape[1]:]
        if bias_part in self.parts:
            bias = drawn[:, 0]
        return factor, bias

    def _draw_precisions(self) -> None:
        """Each group's prior precision and the noise precision from their Gamma conditionals."""
        f = self.factors
        for part, weights in (('p', f.p), ('q', f.q), ('r', f.r), ('b_u', f.user_bias.unsqueeze(1)),
                              ('b_i', f.scene_bias.unsqueeze(1))):
            if part in self.parts or (part == 'r' and self.acts):
                self.precisions[part] = self._gamma(len(weights) / 2, weights.pow(2).sum(0) / 2)
        errors = self.observations.targets - self.predict()
        self.precisions['noise'] = self._gamma(len(errors) / 2, errors.pow(2).sum() / 2)

    def _gamma(self, shape_gain: float, rate_gain: torch.Tensor) -> torch.Tensor:
        scale = 1 / (GAMMA_RATE + rate_gain.numpy())
        return torch.as_tensor(self.rng.gamma(GAMMA_SHAPE + shape_gain, scale), dtype=torch.float64)


class PosteriorSummary(NamedTuple):
    """What ``posterior_head`` did: sweeps run and kept, seconds, the posterior mean of the
    noise precision (z-scale), the RMS gap (z-scale) between the plug-in means' predictions
    and the averaged predictions on the training entries, and the averaged predictions of
    the queries (None without queries)."""

    sweeps: int
    kept: int
    seconds: float
    noise_precision: float
    plug_in_gap: float
    averaged_queries: torch.Tensor | None


def posterior_head(model: StarsModel, observations: Observations, sweeps: int, burn_in: int, seed: int,
                   queries: Observations | None = None) -> PosteriorSummary:
    """Run the chain ``sweeps`` sweeps from ``model``'s weights and set its factorisation part
    to the mean of the draws after ``burn_in``; ``queries`` (their targets unused) also get
    the mean of their predictions over those draws."""
    if not 0 <= burn_in < sweeps:
        raise ValueError(f'burn_in must be in [0, sweeps), got {burn_in} of {sweeps}')
    started = time.perf_counter()
    chain = Chain(model, observations, seed)
    total, predicted, queried, noise = None, 0.0, 0.0, 0.0
    for sweep in range(sweeps):
        chain.sweep()
        if sweep >= burn_in:
            total = chain.factors if total is None else total.plus(chain.factors)
            predicted = predicted + chain.predict()
            if queries is not None:
                queried = queried + chain.predict(queries)
            noise += float(chain.precisions['noise'])
    kept = sweeps - burn_in
    means = total.scaled(1 / kept)
    means.write_to(model)
    gap = float((chain.predict(factors=means) - predicted / kept).pow(2).mean().sqrt())
    return PosteriorSummary(sweeps, kept, time.perf_counter() - started, noise / kept, gap,
                            queried / kept if queries is not None else None)


@torch.no_grad()
def encoded(model: StarsModel, store, scenes: torch.Tensor) -> torch.Tensor:
    """h (float64) for each of ``scenes`` (rows of the scene ``store``), each distinct scene encoded once."""
    model.eval()
    distinct, inverse = torch.unique(scenes, return_inverse=True)
    h = torch.cat([model.encode(store.batch(distinct[start:start + ENCODE_BATCH]).to(model.device)).cpu()
                   for start in range(0, len(distinct), ENCODE_BATCH)])
    return h.double()[inverse]


def training_observations(model: StarsModel, store, examples) -> Observations:
    """The rated entries of ``examples`` (a ``training.TrainingSet``), with h from ``model``'s encoder."""
    example, action = examples.rated.cpu().nonzero(as_tuple=True)
    h = encoded(model, store, examples.scenes)
    return Observations(examples.users.cpu()[example], examples.items.cpu()[example], action, h[example],
                        examples.targets.cpu()[example, action].double())
