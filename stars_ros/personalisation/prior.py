"""The Gaussian prior of a person's θ_u = (p_u, b_u), estimated from a fitted model (empirical Bayes).

With everything but the person fixed, the normalised prediction is linear in θ_u
(``InferenceModel.linear_form``: z = xᵀθ + c), so a Gaussian prior and Gaussian rating noise
give an exact Gaussian posterior after any number of ratings (``foldin``). This module
estimates what that needs from the trained people and their training ratings:

- **Covariance Σ₀**: the spread of the trained rows θ_u, shrunk by Ledoit–Wolf towards a
  scaled identity. With a dozen trained people and d + 1 = 65 dimensions the sample covariance
  has rank ≤ U − 1: most directions would get zero variance, i.e. a certainty no one has.
  Ledoit–Wolf is closed form, needs no tuning, is always positive definite, and fills the
  directions the trained people did not vary in with the average variance. (A diagonal plus
  low-rank fit needs a rank chosen on data this small; Ledoit–Wolf picks its shrinkage from
  the data by a consistent estimate of the optimal one.) b_u is rescaled to the average p
  variance before shrinking and back after, so the identity target fits both.
- **Mean μ₀**: the mean trained row, shrunk towards θ = 0 (the scene-only prediction every
  stranger got before). With held-out ratings of the trained people (``noise_rows``) the
  weight is the one that predicts them best when each person is served the mean of the
  *others* (``held_out_mean_weight``: least squares, clipped to [0, 1]): the mean helps a
  stranger only as far as it carries over to a person it was not fitted on. On SocNav1 the
  James–Stein factor kept 0.82 of a mean that made every held-out person of one fold worse
  (k = 0 MSE 0.0275 against 0.0249 at θ = 0); the held-out weight there is 0. Without
  held-out ratings (``prior_of``'s fallback) the positive-part James–Stein factor shrinks the
  mean as far as its own Σ₀/U error warrants. With held-out ratings (and the fit's
  ``pooled_stranger``) the *pooled row* is the other candidate: the posterior mean, from
  N(0, Σ₀), of one θ fitted to every trained person's training ratings at once, the
  population served as one person (``pooled_rows``). It replaces the others' mean when, each
  person's held-out ratings predicted from a pooled row fitted without them, its squared
  z-error is the lower: chosen by person, as a stranger is met.
- **Noise σ²_a**: per action, the mean squared z-residual of held-out ratings of the trained
  people (``noise_rows``: examples the fit did not see, scored from their trained rows),
  else of the training ratings. Training residuals understate the noise a new person's
  ratings carry (the model has fitted them): the posterior then trusts a person's first
  answers too much, and its intervals are too narrow.
- **Known people**: each trained person starts from their own row with the posterior
  covariance (Σ₀⁻¹ + XᵀD⁻¹X)⁻¹ of their training ratings.
- **Tails ν**: real rating errors are heavier-tailed than the Gaussian (more of them near the
  mean and far out, fewer in between), so the predictive distribution is a Student-t with the
  noise's variance and ν degrees of freedom, ν the maximum-likelihood value on ``NU_GRID`` of
  the same standardised residuals as the noise (ν = ∞: Gaussian).
- **How far a person departs**: Σ₀ describes people on average; some groups deviate from μ₀
  in directions that do not carry over from one scene to the next. The fold-in therefore
  treats a person's scale τ on Σ₀ as unknown, one of ``PRIOR_SCALES`` (E τ = 1.075, so the
  population spread stays about Σ₀), and weighs them by the marginal likelihood of the person's
  own answers (``foldin.scale_mixture_posterior``).
- **How likely each scale is** before a person's first answer: equally (the default), or, with
  ``training.prior_scale_weights`` 'held_out', as the trained people's held-out ratings say
  (``fitted_scale_weights``): each trained person's held-out residuals from the prior's mean,
  weighed as a stranger's would be, tell how far people depart from μ₀ in ratings the fit did
  not see, where the spread of their trained rows (Σ₀) may overstate it (a fitted row also
  fits its person's noise). For a checkpoint that serves strangers its plain encoder, the
  residuals are still those from the prior's mean: that encoder has learnt from the held-out
  ratings too, so its residuals there would understate the departure. With 'held_out_plain'
  they are the residuals from the plain encoder, which then trains without those ratings
  (``StarsRecommender.fit``): a handed-over stranger is served that encoder, so their
  departure is measured from what they are served.
- **The noise without the rows' own error** (``training.prior_noise`` 'less_row_uncertainty'): a
  trained person's held-out residual carries the noise and the error of their fitted row,
  whose variance there is xᵀ C_u x (C_u their posterior covariance, below). Served to a new
  person, the noise adds to their own posterior's xᵀ Cov x, so that row error would be counted
  twice and their intervals would be too wide, the more so the fewer ratings trained people
  have. This option takes it out (``noise_less_row_uncertainty``, a method-of-moments fixed
  point, since C_u depends on the noise) and finds ν on the residuals standardised by the
  whole known-person predictive. The default keeps the plain mean squared residual.
- **How far strangers spread** (``training.prior_spread`` 'held_out_plain'): Σ₀ is the spread of
  the trained rows, which fit each person's noise as well as their taste and may spread further
  than people depart from what a stranger is served. This option serves a new person the
  covariance gΣ₀, g the maximum marginal likelihood of the trained people's held-out residuals
  from the plain encoder (``fitted_spread``; the scales equally likely, so the mixture keeps its
  shape and g sets its size, without the floor a pseudocount puts under the fitted weights).
  Trained people keep their posterior covariances from Σ₀. The default keeps Σ₀.
- **How noisy a stranger's ratings are** (``training.stranger_noise`` 'held_out_plain', with
  ``prior_spread`` 'held_out_plain'): σ²_a is the trained rows' held-out error, which need not
  be a handed-over stranger's: at k = 0 their residual is the plain encoder's. This option
  fits a share s with g, the same marginal likelihood with noise s·σ²_a
  (``fitted_spread(fit_noise=True)``); a stranger's ratings and predictive then carry s·σ²_a
  (``UserPrior.stranger_noise``), trained people keep σ²_a. The default keeps σ²_a for all.

A checkpoint stores the estimate (``to_dict``; model.checkpoint keeps it as data). One
written before has none: ``prior_of`` then estimates Σ₀ and μ₀ from its user rows, assumes
σ²_a = 1 (the z-scale's own variance: a conservative guess) and says so.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from stars_ros.data.splits import held_examples
from stars_ros.errors import ConfigError
from stars_ros.model.serving import inference_of

log = logging.getLogger(__name__)
DEFAULT_NOISE = 1.0  # z-scale noise variance assumed when a checkpoint stores none
NU_GRID = (3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 15.0, 20.0, 30.0, 50.0, 100.0, math.inf)  # candidate degrees of freedom
PRIOR_SCALES = (0.0, 0.3, 1.0, 3.0)  # a person's scale τ on Σ₀, equally likely a priori (mean 1.075)
NOISE_SHARE = 0.1  # share of the examples a default fit holds out for the noise (``held_out_split``)
SCALE_PSEUDOCOUNT = 1.0  # per scale, added to the people that fit the scales' weights (a Dirichlet prior)
SPREAD_BOUNDS = (1e-4, 1e4)  # the range searched for the size g of a stranger's covariance gΣ₀
NOISE_SHARE_BOUNDS = (1e-2, 1e2)  # the range searched for the share s of the noise a stranger's ratings carry
NOISE_FLOOR = 0.1  # share of its plain held-out estimate an action's noise keeps when row error is taken out


@dataclass(frozen=True)
class UserPrior:
    """N(mean, covariance) over θ = (p_u, b_u) [dim+1] (float64), the z-scale noise variance
    per action ``noise`` [actions], and for trained people ``user_covariance``
    [users, dim+1, dim+1] (None: they start from Σ₀ around their row), the predictive's
    degrees of freedom ``nu`` (inf: Gaussian), and ``scale_weights`` [len(PRIOR_SCALES)], how
    likely a new person's scale τ on Σ₀ is to be each one before their first answer (None:
    equally), and ``stranger_noise`` [actions], the noise variance of the ratings of a person the
    model was not trained on (None: ``noise``). ``details`` says how it was estimated."""

    mean: np.ndarray
    covariance: np.ndarray
    noise: np.ndarray
    user_covariance: np.ndarray | None = None
    details: dict = field(default_factory=dict)
    nu: float = math.inf
    scale_weights: np.ndarray | None = None
    stranger_noise: np.ndarray | None = None

    @property
    def scale_prior(self) -> np.ndarray:
        """P(τ) over ``PRIOR_SCALES`` before a person's first answer."""
        if self.scale_weights is None:
            return np.full(len(PRIOR_SCALES), 1 / len(PRIOR_SCALES))
        return self.scale_weights

    def to_dict(self) -> dict:
        """Tensors and plain values, as a weights-only checkpoint holds them."""
        import torch  # a fitted model's: serving reads priors, never writes one

        values = {'mean': torch.from_numpy(self.mean.copy()), 'covariance': torch.from_numpy(self.covariance.copy()),
                  'noise': torch.from_numpy(self.noise.copy()), 'details': dict(self.details),
                  'nu': torch.tensor(float(self.nu), dtype=torch.float64)}
        if self.user_covariance is not None:
            values['user_covariance'] = torch.from_numpy(self.user_covariance.astype(np.float32))
        if self.scale_weights is not None:
            values['scale_weights'] = torch.from_numpy(self.scale_weights.copy())
        if self.stranger_noise is not None:
            values['stranger_noise'] = torch.from_numpy(self.stranger_noise.copy())
        return values

    @classmethod
    def from_dict(cls, values: dict) -> 'UserPrior':
        def array(name):
            return np.asarray(values[name], dtype=np.float64)  # a tensor (a fitted model's) or an array (a file's)
        users = array('user_covariance') if values.get('user_covariance') is not None else None
        nu = float(array('nu')) if values.get('nu') is not None else math.inf  # earlier checkpoints: Gaussian
        scales = array('scale_weights') if values.get('scale_weights') is not None else None  # earlier: equal
        strangers = array('stranger_noise') if values.get('stranger_noise') is not None else None  # earlier: noise
        return cls(array('mean'), array('covariance'), array('noise'), users, dict(values.get('details', {})), nu,
                   scales, strangers)


def ledoit_wolf(rows: np.ndarray) -> tuple[np.ndarray, float]:
    """(covariance, shrinkage) of ``rows`` [n, p] by Ledoit & Wolf (2004): the sample
    covariance (1/n) shrunk towards μI, μ its mean variance, by the estimated optimal weight."""
    x = rows - rows.mean(0)
    n, p = x.shape
    sample = x.T @ x / n
    mu = np.trace(sample) / p
    x2 = x ** 2
    beta = (np.sum(x2.T @ x2) / n - np.sum(sample ** 2)) / (p * n)
    delta = np.sum((sample - mu * np.eye(p)) ** 2) / p
    shrinkage = 0.0 if delta == 0 else float(np.clip(beta / delta, 0.0, 1.0))
    return (1 - shrinkage) * sample + shrinkage * mu * np.eye(p), shrinkage


def student_t_nu(standardised: np.ndarray) -> float:
    """The ν of ``NU_GRID`` under which unit-variance Student-t errors best explain
    ``standardised`` residuals (maximum likelihood; inf: the Gaussian)."""
    if len(standardised) < 20:  # too few to tell tails from chance
        return math.inf
    from scipy import stats  # estimation only: serving imports this module, not scipy.stats

    def log_likelihood(nu):
        if math.isinf(nu):
            return float(stats.norm.logpdf(standardised).sum())
        return float(stats.t.logpdf(standardised, nu, scale=math.sqrt((nu - 2) / nu)).sum())
    return max(NU_GRID, key=log_likelihood)


def people_spectra(x: np.ndarray, r: np.ndarray, noise: np.ndarray, people: np.ndarray,
                   covariance: np.ndarray) -> tuple:
    """What the marginal likelihood of each person's residuals r [n] (rows x [n, dim+1] with
    noise variances ``noise`` [n], of ``people`` [n]) needs for any covariance cΣ₀ (Σ₀
    ``covariance``), people in ``np.unique(people)`` order: the eigenvalues λ of each one's
    D^-½XΣ₀XᵀD^-½ (D their noise) and their whitened residuals squared in that eigenbasis
    (both [n], one person after another), where each person starts in them [people], and
    each one's constant part [people]."""
    eigenvalues, squared, starts, constants = [], [], [], []
    for person in np.unique(people):
        mine = people == person
        weight = 1.0 / np.sqrt(noise[mine])
        whitened = x[mine] * weight[:, None]
        values, vectors = np.linalg.eigh(whitened @ covariance @ whitened.T)
        starts.append(sum(map(len, eigenvalues)))
        eigenvalues.append(np.clip(values, 0.0, None))
        squared.append((vectors.T @ (r[mine] * weight)) ** 2)
        constants.append(-0.5 * (np.sum(np.log(noise[mine])) + mine.sum() * math.log(2 * math.pi)))
    return np.concatenate(eigenvalues), np.concatenate(squared), np.array(starts), np.array(constants)


def scale_log_likelihoods(spectra: tuple, sizes: np.ndarray, noise_share: float = 1.0) -> np.ndarray:
    """log N(r; 0, cXΣ₀Xᵀ + sD) [people, sizes] for each person of ``people_spectra``, each c of
    ``sizes`` and s ``noise_share``: −½ Σ (w²/(s + cλ) + log(s + cλ)) plus the constant, O(n) per c."""
    eigenvalues, squared, starts, constants = spectra
    spread = noise_share + np.asarray(sizes, dtype=np.float64)[:, None] * eigenvalues[None, :]  # [sizes, n]
    return constants[:, None] - 0.5 * np.add.reduceat(squared / spread + np.log(spread), starts, axis=1).T


def fitted_scale_weights(x: np.ndarray, r: np.ndarray, noise: np.ndarray, people: np.ndarray,
                         covariance: np.ndarray, scales=PRIOR_SCALES,
                         pseudocount: float = SCALE_PSEUDOCOUNT) -> np.ndarray:
    """P(τ) over ``scales``: the weights under which each person's residuals r [n] (rows x
    [n, dim+1] with noise variances ``noise`` [n], of ``people`` [n]) are most likely as a
    stranger's, r = x(θ − μ₀) + ε with θ − μ₀ ~ N(0, τΣ₀) (``covariance``) and one τ per
    person drawn from the weights: EM for a mixture's weights (each person's responsibilities,
    then their mean), with ``pseudocount`` people added to every scale, so that no scale's
    weight reaches 0 (a new person could then never be found to be there)."""
    log_likelihood = scale_log_likelihoods(people_spectra(x, r, noise, people, covariance), scales)
    weights = np.full(len(scales), 1 / len(scales))
    for _ in range(10_000):
        joint = log_likelihood + np.log(weights)
        responsibility = np.exp(joint - joint.max(1, keepdims=True))
        responsibility /= responsibility.sum(1, keepdims=True)
        updated = (responsibility.sum(0) + pseudocount) / (len(responsibility) + pseudocount * len(scales))
        if np.max(np.abs(updated - weights)) < 1e-12:
            return updated
        weights = updated
    return weights


def fitted_spread(x: np.ndarray, r: np.ndarray, noise: np.ndarray, people: np.ndarray, covariance: np.ndarray,
                  scale_prior: np.ndarray, scales=PRIOR_SCALES, bounds=SPREAD_BOUNDS,
                  fit_noise: bool = False) -> tuple[float, float]:
    """(g, s): the g in ``bounds`` under which each person's residuals r [n] (rows x [n, dim+1]
    with noise variances ``noise`` [n], of ``people`` [n]) are most likely as a stranger's,
    r = x(θ − μ₀) + ε with θ − μ₀ ~ N(0, gτΣ₀) (Σ₀ ``covariance``), ε ~ N(0, s·noise) and one τ
    per person drawn from ``scale_prior`` over ``scales``; s = 1 unless ``fit_noise``, else the
    noise's share fitted with g (in ``NOISE_SHARE_BOUNDS``). Maximum marginal likelihood over
    log g (and log s): a grid (61 points, × 41), then bounded Nelder–Mead from its best point
    (``scale_log_likelihoods`` of gτ, mixed over τ)."""
    from scipy.optimize import minimize  # estimation only: serving never fits a prior
    from scipy.special import logsumexp

    spectra = people_spectra(x, r, noise, people, covariance)
    log_prior = np.log(np.asarray(scale_prior, dtype=np.float64))
    scales = np.asarray(scales, dtype=np.float64)
    limits = [bounds] + ([NOISE_SHARE_BOUNDS] if fit_noise else [])  # log g (and log s)
    limits = np.log(np.array(limits, dtype=np.float64))

    def negative_log_likelihood(point: np.ndarray) -> float:
        share = math.exp(point[1]) if fit_noise else 1.0
        likelihood = scale_log_likelihoods(spectra, math.exp(point[0]) * scales, share)
        return -float(logsumexp(likelihood + log_prior, axis=1).sum())

    grids = [np.linspace(low, high, size) for (low, high), size in zip(limits, (61, 41))]
    points = np.stack(np.meshgrid(*grids, indexing='ij'), axis=-1).reshape(-1, len(grids))
    start = points[int(np.argmin([negative_log_likelihood(point) for point in points]))]
    steps = np.array([grid[1] - grid[0] for grid in grids])  # a simplex one grid cell wide, inwards: scipy's
    steps = np.diag(np.where(start + steps > limits[:, 1], -steps, steps))  # default moves a coordinate at 0
    # (s = 1, a grid point) by 0.00025 and can stop there
    found = minimize(negative_log_likelihood, start, method='Nelder-Mead', bounds=limits,
                     options={'xatol': 1e-8, 'fatol': 1e-10, 'maxiter': 2000,
                              'initial_simplex': np.vstack([start, start + steps])})
    best = np.exp(found.x if found.fun <= negative_log_likelihood(start) else start)
    return float(best[0]), float(best[1]) if fit_noise else 1.0


def known_covariances(precision: np.ndarray, x: np.ndarray, actions: np.ndarray, people: np.ndarray,
                      noise: np.ndarray, users: int) -> np.ndarray:
    """C_u = (Σ₀⁻¹ + XᵀD⁻¹X)⁻¹ [users, dim+1, dim+1]: each trained person's posterior covariance
    from their training ratings, rows x [n, dim+1] of ``people`` [n] (D: ``noise`` of each
    rating's action [n] ``actions``), Σ₀⁻¹ ``precision``."""
    covariance = np.empty((users, len(precision), len(precision)))
    for person in range(users):
        mine = people == person
        covariance[person] = np.linalg.inv(precision + (x[mine] / noise[actions[mine], None]).T @ x[mine])
    return covariance


def noise_less_row_uncertainty(residual: np.ndarray, actions: np.ndarray, x: np.ndarray, people: np.ndarray,
                               plain: np.ndarray, covariances, tolerance: float = 1e-9,
                               sweeps: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """(σ²_a [actions], the row variance xᵀ C_u x of each residual [n]): per action, the mean of
    residual² − xᵀ C_u x over held-out ratings (``residual`` [n] of rows x [n, dim+1] of
    ``people`` [n], ``actions`` [n]), never below ``NOISE_FLOOR`` of its plain estimate
    ``plain`` [actions]. C_u = ``covariances(σ²)`` [users, dim+1, dim+1] depends on the noise,
    so the two are iterated to their fixed point, starting from ``plain``."""
    noise, floor = plain.copy(), NOISE_FLOOR * plain
    for _ in range(sweeps):
        covariance = covariances(noise)
        row_variance = np.empty(len(residual))
        for person in np.unique(people):
            mine = people == person
            row_variance[mine] = np.einsum('nd,de,ne->n', x[mine], covariance[person], x[mine])
        updated = plain.copy()
        for a in np.unique(actions):
            mine = actions == a
            updated[a] = max(float(np.mean(residual[mine] ** 2 - row_variance[mine])), floor[a])
        converged = np.max(np.abs(updated - noise) / plain) < tolerance
        noise = updated
        if converged:
            break
    return noise, row_variance


def held_out_split(data, rows: np.ndarray, share: float = NOISE_SHARE, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(training rows, noise rows): a seeded ``share`` of each person's examples (never their
    only one) held out, so the prior's noise and tails come from ratings the fit did not see,
    as a new person's are."""
    rows = np.asarray(rows, dtype=np.int64)
    users, examples = data.users[rows], data.examples[rows]
    rng = np.random.default_rng(seed)
    held = np.zeros(len(rows), dtype=bool)
    for name in sorted(set(users.tolist())):
        mine = users == name
        distinct = len(np.unique(examples[mine]))
        held[mine] = held_examples(examples[mine], min(int(round(share * distinct)), distinct - 1), rng)
    return rows[~held], rows[held]


def population(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """(μ₀, Σ₀, details) from trained rows θ_u [users, dim+1]; see the module docstring."""
    users, size = rows.shape
    if users < 2:  # no spread to estimate: unit variance on the z-scale in every coordinate
        return np.zeros(size), np.eye(size), {'covariance': 'identity (fewer than 2 trained users)',
                                              'mean': 'zero', 'users': int(users)}
    p_var = rows[:, :-1].var(0).mean()
    b_var = rows[:, -1].var()
    scale = np.ones(size)
    if b_var > 0 and p_var > 0:
        scale[-1] = np.sqrt(p_var / b_var)
    covariance, shrinkage = ledoit_wolf(rows * scale)
    covariance = covariance / np.outer(scale, scale)
    if not np.trace(covariance) > 0:  # every trained row alike (a model barely trained): no spread either
        return np.zeros(size), np.eye(size), {'covariance': 'identity (the trained rows do not spread)',
                                              'mean': 'zero', 'users': int(users)}
    if np.linalg.eigvalsh(covariance)[0] <= 1e-12 * np.trace(covariance):  # too few rows to shrink from (two)
        covariance, shrinkage = np.eye(size) * (np.trace(covariance) / size), 1.0
    mean = rows.mean(0)
    spread = np.trace(covariance) / size / users  # variance of each coordinate of the mean estimate
    norm = float(mean @ mean)
    mean_weight = 1.0 if size <= 2 or norm == 0 else max(0.0, 1.0 - (size - 2) * spread / norm)
    return mean * mean_weight, covariance, {'covariance': 'ledoit-wolf', 'shrinkage': round(float(shrinkage), 6),
                                            'mean': 'james-stein towards 0', 'mean_weight': round(float(mean_weight), 6),
                                            'users': int(users)}


def held_out_mean_weight(trained: np.ndarray, people: np.ndarray, x: np.ndarray, r: np.ndarray) -> float | None:
    """The w in [0, 1] for which θ = w · (mean of the other trained rows) best predicts each
    trained person's held-out ratings: rows x [n, dim+1] of ``people`` [n] (rows of ``trained``
    [users, dim+1]) with targets r = z − c [n]; None when it cannot be told (fewer than two
    people, or rows the others' mean does not load on)."""
    users = len(trained)
    if users < 2 or len(r) == 0:
        return None
    others = (trained.sum(0) - trained[people]) / (users - 1)  # [n, dim+1]: each row's leave-one-out mean
    a = np.einsum('nd,nd->n', x, others)
    energy = float(a @ a)
    if energy <= 0:
        return None
    return float(np.clip(a @ r / energy, 0.0, 1.0))


def pooled_rows(x: np.ndarray, r: np.ndarray, weights: np.ndarray, people: np.ndarray, users: int,
                precision: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(θ_pop [dim+1], θ_pop without each person [users, dim+1]): the posterior mean, from
    N(0, Σ₀) (``precision`` Σ₀⁻¹), of one θ that gave every rating x [n, dim+1], r = z − c [n]
    of ``people`` [n] (rows of the trained people), each weighted by ``weights`` (1/σ²_a): the
    population as one person, and the same without each person's ratings."""
    size = x.shape[1]
    gram, moment = np.zeros((users, size, size)), np.zeros((users, size))
    for person in range(users):
        mine = people == person
        weighted = x[mine] * weights[mine, None]
        gram[person], moment[person] = weighted.T @ x[mine], weighted.T @ r[mine]
    total_gram, total_moment = gram.sum(0) + precision, moment.sum(0)
    without = np.stack([np.linalg.solve(total_gram - gram[person], total_moment - moment[person])
                        for person in range(users)])
    return np.linalg.solve(total_gram, total_moment), without


def user_rows(inference) -> np.ndarray:
    """θ = (p_u, b_u) [users, dim+1] (float64) of a model's trained people."""
    return np.concatenate([inference.user_rows, inference.user_offsets[:, None]], axis=1).astype(np.float64)


def encode_all(fitted, data, model=None) -> np.ndarray:
    """h_i of every scene of ``data`` [n_scenes, dim] (float64) under ``fitted``'s encoder (or
    ``model``'s, e.g. its ``stranger_model``)."""
    import torch  # training's form

    model = fitted.require_model() if model is None else model
    parts = []
    with torch.no_grad():
        for start in range(0, len(data.scene_keys), 512):
            index = torch.arange(start, min(start + 512, len(data.scene_keys)))
            parts.append(model.encode(data.store.batch(index).to(model.device)).double().cpu().numpy())
    return np.concatenate(parts)


def rows_design(fitted, inference, data, rows: np.ndarray, h: np.ndarray) -> tuple:
    """(x [n, dim+1], c [n], z [n]) of ``rows`` of ``data``: the linear form of each rating's
    normalised prediction in θ (``InferenceModel.linear_form``) and its z-scored score; ``h``
    is ``encode_all``'s."""
    items = data.item_keys(fitted.config.model.item_key)
    scenes, actions = data.scenes[rows], data.actions[rows]
    x, c = inference.linear_form(h[scenes], fitted.scene_vocabulary.rows([items[s] for s in scenes]), actions)
    return x, c, inference.to_z(data.scores[rows], actions)


def plain_z(fitted, inference, data, rows: np.ndarray) -> np.ndarray:
    """The plain encoder's normalised predictions [n] of ``rows`` of ``data`` (``fitted``'s
    ``stranger_model``, what a stranger is served), on the z-scale of ``inference``."""
    if fitted.stranger_model is None:
        raise ConfigError("training.prior_scale_weights 'held_out_plain' needs a plain encoder for strangers "
                          "(model.strangers 'base_encoder')")
    h = encode_all(fitted, data, fitted.stranger_model)[data.scenes[rows]]
    actions = data.actions[rows]
    scores = inference_of(fitted.stranger_model).scores(h, None, None)
    return inference.to_z(scores[np.arange(len(rows)), actions], actions)


def estimate_prior(fitted, data, rows: np.ndarray, h: np.ndarray | None = None,
                   noise_rows: np.ndarray | None = None) -> UserPrior:
    """The prior of a model ``fitted`` (``stars_ros.model.training``'s training class) on
    ``rows`` of ``data`` (RatingData); the noise from ``noise_rows`` (held-out ratings of the
    trained people) when given. See the module docstring. ``h``: ``encode_all``'s, if
    already computed."""
    inference = inference_of(fitted.require_model())
    trained = user_rows(inference)
    mean, covariance, details = population(trained)
    rows = np.asarray(rows)
    h = encode_all(fitted, data) if h is None else h
    x, c, z = rows_design(fitted, inference, data, rows, h)
    users, actions = fitted.user_vocabulary.rows(list(data.users[rows])), data.actions[rows]
    held_out = noise_rows is not None and len(noise_rows) > 0
    if held_out:
        noise_rows = np.asarray(noise_rows)
        known = fitted.user_vocabulary.rows(list(data.users[noise_rows]))
        noise_rows, known = noise_rows[known >= 0], known[known >= 0]
        noise_x, noise_c, noise_z = rows_design(fitted, inference, data, noise_rows, h)
        residual, residual_actions = noise_z - (np.einsum('nd,nd->n', noise_x, trained[known]) + noise_c), \
            data.actions[noise_rows]
        weight = held_out_mean_weight(trained, known, noise_x, noise_z - noise_c)
        if weight is not None:
            mean = weight * trained.mean(0)
            details = {**details, 'mean': 'weight from held-out ratings, each person against the others\' mean',
                       'mean_weight': round(weight, 6), 'james_stein_weight': details.get('mean_weight')}
    else:
        residual, residual_actions = z - (np.einsum('nd,nd->n', x, trained[users]) + c), actions
    noise = np.ones(len(inference.target_mean))
    for a in range(len(noise)):
        if (residual_actions == a).any():
            noise[a] = float(np.mean(residual[residual_actions == a] ** 2))
    precision = np.linalg.inv(covariance)
    predictive_variance = noise[residual_actions]
    if fitted.config.training.prior_noise == 'less_row_uncertainty':
        if not held_out:
            raise ConfigError("training.prior_noise 'less_row_uncertainty' needs held-out ratings of the trained "
                              'people (noise_rows)')
        plain_noise = noise
        noise, row_variance = noise_less_row_uncertainty(
            residual, residual_actions, noise_x, known, plain_noise,
            lambda candidate: known_covariances(precision, x, actions, users, candidate, len(trained)))
        predictive_variance = noise[residual_actions] + row_variance
        details = {**details, 'noise_less_row_uncertainty': True,
                   'noise_held_out_residual': [round(float(v), 6) for v in plain_noise]}
    nu = student_t_nu(residual / np.sqrt(predictive_variance))
    if held_out and weight is not None and fitted.config.training.pooled_stranger:
        mean, details = _pooled_if_better(mean, details, trained, x, z - c, 1.0 / noise[actions], users,
                                          precision, (known, noise_x, noise_z - noise_c, weight))
    scale_weights = None
    weights_from, spread_from = fitted.config.training.prior_scale_weights, fitted.config.training.prior_spread
    for setting, value in (('prior_scale_weights', weights_from), ('prior_spread', spread_from)):
        if value not in ('equal', 'trained_rows') and not held_out:
            raise ConfigError(f"training.{setting} '{value}' needs held-out ratings of the trained people (noise_rows)")
    if 'held_out_plain' in (weights_from, spread_from):  # as a stranger served the plain encoder
        plain_residual = noise_z - plain_z(fitted, inference, data, noise_rows)
    if weights_from != 'equal':
        stranger_residual = (plain_residual if weights_from == 'held_out_plain'
                             else noise_z - noise_c - noise_x @ mean)  # as a stranger served the prior's mean
        scale_weights = fitted_scale_weights(noise_x, stranger_residual, noise[residual_actions], known, covariance)
        served = 'the plain encoder' if weights_from == 'held_out_plain' else "the prior's mean"
        details = {**details, 'prior_scale_weights': [round(float(w), 6) for w in scale_weights],
                   'prior_scale_weights_from': f'held-out ratings of {len(np.unique(known))} trained people, '
                                               f'residuals from {served}, '
                                               f'{SCALE_PSEUDOCOUNT:g} pseudo-person per scale'}
    user_covariance, stranger_noise = known_covariances(precision, x, actions, users, noise, len(trained)), None
    if spread_from == 'held_out_plain':  # a stranger's covariance gΣ₀; trained people keep theirs from Σ₀
        with_noise = fitted.config.training.stranger_noise == 'held_out_plain'
        spread, noise_share = fitted_spread(noise_x, plain_residual, noise[residual_actions], known, covariance,
                                            np.full(len(PRIOR_SCALES), 1 / len(PRIOR_SCALES)), fit_noise=with_noise)
        covariance = spread * covariance
        fitted_from = (f'maximum marginal likelihood of held-out ratings of {len(np.unique(known))} trained people, '
                       'residuals from the plain encoder')
        details = {**details, 'prior_spread': round(spread, 6), 'prior_spread_from': fitted_from}
        if with_noise:  # a stranger's ratings carry s·σ²_a, s fitted with g; trained people keep σ²_a
            stranger_noise = noise_share * noise
            details = {**details, 'stranger_noise_share': round(noise_share, 6),
                       'stranger_noise_from': f'{fitted_from}, fitted with prior_spread'}
    source = f'{len(residual)} held-out ratings of the trained people' if held_out else 'the training ratings'
    less = (", less each trained row's posterior variance there"
            if fitted.config.training.prior_noise == 'less_row_uncertainty' else '')
    details = {**details, 'noise': f'mean squared z-residual of {source}{less}, per action', 'ratings': int(len(rows)),
               'nu': f'maximum likelihood on {source}', 'prior_scales': list(PRIOR_SCALES)}
    return UserPrior(mean, covariance, noise, user_covariance, details, nu, scale_weights, stranger_noise)


def _pooled_if_better(mean: np.ndarray, details: dict, trained: np.ndarray, x: np.ndarray, r: np.ndarray,
                      weights: np.ndarray, people: np.ndarray, precision: np.ndarray, held_out: tuple) -> tuple:
    """(mean, details): the pooled row (``pooled_rows``) in place of the others' mean when,
    each trained person's held-out ratings ``held_out`` (people, x, r, the mean's weight)
    predicted from a row fitted without that person, its squared z-error is the lower."""
    known, held_x, held_r, weight = held_out
    pooled, pooled_without = pooled_rows(x, r, weights, people, len(trained), precision)
    others = (trained.sum(0) - trained[known]) / (len(trained) - 1)
    errors = {'pooled': float(np.sum((held_r - np.einsum('nd,nd->n', held_x, pooled_without[known])) ** 2)),
              'others_mean': float(np.sum((held_r - weight * np.einsum('nd,nd->n', held_x, others)) ** 2))}
    details = {**details, 'held_out_squared_z_error': {k: round(v, 4) for k, v in errors.items()}}
    if errors['pooled'] < errors['others_mean']:
        return pooled, {**details, 'mean': "pooled: one θ fitted to every trained person's ratings "
                                           "(held-out ratings of each person predicted better than by the others' mean)"}
    return mean, details


def prior_of(recommender, inference) -> UserPrior:
    """The prior a checkpoint stores, else one estimated from its user rows (with a warning)."""
    stored = getattr(recommender, 'user_prior', None)
    if stored is not None:
        return UserPrior.from_dict(stored)
    mean, covariance, details = population(user_rows(inference))
    log.warning('this checkpoint stores no personalisation prior: its population prior is estimated from the '
                f'trained user rows and the rating noise assumed to be {DEFAULT_NOISE} on the z-scale; '
                'score_sd is conservative until the model is trained again')
    noise = np.full(len(inference.target_mean), DEFAULT_NOISE)
    return UserPrior(mean, covariance, noise, None, {**details, 'noise': f'assumed {DEFAULT_NOISE} (not stored)'})
