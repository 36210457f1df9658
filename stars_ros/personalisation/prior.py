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
  stranger got before). With held-out ratings of the trained people (``HeldOut``) the
  weight is the one that predicts them best when each person is served the mean of the
  *others* (``held_out_mean_weight``: least squares, clipped to [0, 1]): the mean helps a
  stranger only as far as it carries over to a person it was not fitted on. On SocNav1 the
  James–Stein factor kept 0.82 of a mean that made every held-out person of one fold worse
  (k = 0 MSE 0.0275 against 0.0249 at θ = 0); the held-out weight there is 0. Without
  held-out ratings (``prior_of``'s fallback) the positive-part James–Stein factor shrinks the
  mean as far as its own Σ₀/U error warrants.
- **Noise σ²_a**: per action, the mean squared z-residual of held-out ratings of the trained
  people (``held_out_residuals``: examples a fit did not see, scored in its served form from
  their rows of that fit; ``personalisation.recipe`` makes that fit on the rows less those examples and
  the shipped model on every row), else of the training ratings. Training residuals understate
  the noise a new person's ratings carry (the model has fitted them): the posterior then trusts
  a person's first answers too much, and its intervals are too narrow.
- **Known people**: each trained person starts from their own row with the posterior
  covariance (Σ₀⁻¹ + XᵀD⁻¹X)⁻¹ of their training ratings.
- **Tails ν**: real rating errors are heavier-tailed than the Gaussian (more of them near the
  mean and far out, fewer in between), so the predictive distribution is a Student-t with the
  noise's variance and ν degrees of freedom, ν the maximum-likelihood value on ``NU_GRID`` of
  the same standardised residuals as the noise (ν = ∞: Gaussian).
- **How far a person departs**: Σ₀ describes people on average; some groups deviate from μ₀
  in directions that do not carry over from one scene to the next. The fold-in therefore
  treats a person's scale τ on Σ₀ as unknown, one of ``PRIOR_SCALES`` (E τ = 1.075, so the
  population spread stays about Σ₀), equally likely before a person's first answer, and weighs
  them by the marginal likelihood of the person's own answers (``foldin.scale_mixture_posterior``).

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

log = logging.getLogger(__name__)
DEFAULT_NOISE = 1.0  # z-scale noise variance assumed when a checkpoint stores none
NU_GRID = (3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 15.0, 20.0, 30.0, 50.0, 100.0, math.inf)  # candidate degrees of freedom
PRIOR_SCALES = (0.0, 0.3, 1.0, 3.0)  # a person's scale τ on Σ₀, equally likely a priori (mean 1.075)
NOISE_SHARE = 0.1  # share of the examples the hold-out fit leaves out for the noise (``held_out_split``)


@dataclass(frozen=True)
class UserPrior:
    """N(mean, covariance) over θ = (p_u, b_u) [dim+1] (float64), the z-scale noise variance
    per action ``noise`` [actions], and for trained people ``user_covariance``
    [users, dim+1, dim+1] (None: they start from Σ₀ around their row), and the predictive's
    degrees of freedom ``nu`` (inf: Gaussian). ``details`` says how it was estimated."""

    mean: np.ndarray
    covariance: np.ndarray
    noise: np.ndarray
    user_covariance: np.ndarray | None = None
    details: dict = field(default_factory=dict)
    nu: float = math.inf

    def to_dict(self) -> dict:
        """Tensors and plain values, as a weights-only checkpoint holds them."""
        import torch  # a fitted model's: serving reads priors, never writes one

        values = {'mean': torch.from_numpy(self.mean.copy()), 'covariance': torch.from_numpy(self.covariance.copy()),
                  'noise': torch.from_numpy(self.noise.copy()), 'details': dict(self.details),
                  'nu': torch.tensor(float(self.nu), dtype=torch.float64)}
        if self.user_covariance is not None:
            values['user_covariance'] = torch.from_numpy(self.user_covariance.astype(np.float32))
        return values

    @classmethod
    def from_dict(cls, values: dict) -> 'UserPrior':
        def array(name):
            return np.asarray(values[name], dtype=np.float64)  # a tensor (a fitted model's) or an array (a file's)
        users = array('user_covariance') if values.get('user_covariance') is not None else None
        nu = float(array('nu')) if values.get('nu') is not None else math.inf  # earlier checkpoints: Gaussian
        unread = sorted(set(values) - {'mean', 'covariance', 'noise', 'user_covariance', 'details', 'nu'})
        if unread:  # e.g. an unshipped experiment's fitted scale weights: the scales stay equally likely
            log.warning(f"this checkpoint's prior holds {', '.join(unread)}, which this version does "
                        'not read (experiments that did not ship): the fold-in serves without them')
        return cls(array('mean'), array('covariance'), array('noise'), users, dict(values.get('details', {})), nu)


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
                                            'mean': 'james-stein towards 0', 'mean_weight': round(float(mean_weight),
                                                                                                  6),
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


def user_rows(inference) -> np.ndarray:
    """θ = (p_u, b_u) [users, dim+1] (float64) of a model's trained people."""
    return np.concatenate([inference.user_rows, inference.user_offsets[:, None]], axis=1).astype(np.float64)


def rows_design(predictor, data, rows: np.ndarray, h: np.ndarray) -> tuple:
    """(x [n, dim+1], c [n], z [n]) of ``rows`` of ``data`` as ``predictor`` serves them: the
    linear form of each rating's normalised prediction in θ (``InferenceModel.linear_form``)
    and its z-scored score; ``h``: every scene's, ``scoring.served_encodings``'."""
    items = data.item_keys(predictor.served.config.model.item_key)
    scenes, actions = data.scenes[rows], data.actions[rows]
    inference = predictor.inference
    x, c = inference.linear_form(h[scenes], predictor.scene_rows([items[s] for s in scenes]), actions)
    return x, c, inference.to_z(data.scores[rows], actions)


@dataclass(frozen=True)
class HeldOut:
    """What ratings a model was not fitted on say of its people (``held_out_residuals``):
    each rating's z-residual from its person's trained row [n] and action [n], and the weight
    of the trained rows' mean that best predicts each person from the others' (None: untold)."""

    residual: np.ndarray
    actions: np.ndarray
    mean_weight: float | None


def served(fitted):
    """The ``Predictor`` of ``fitted``: its served form, as its checkpoint would be served."""
    from stars_ros.model.predictor import Predictor  # the served form of the fitted model
    return Predictor.from_model(fitted)


def held_out_residuals(fitted, data, rows: np.ndarray) -> HeldOut:
    """``HeldOut`` of ``rows`` of ``data``, ratings of trained people that ``fitted``
    (``model.fitted.FittedModel``) was not fitted on, scored in its served form (ratings of
    anyone else are left out)."""
    from stars_ros.model.scoring import served_encodings

    predictor = served(fitted)
    h = served_encodings(predictor, data)
    rows = np.asarray(rows, dtype=np.int64)
    people = np.array([predictor.trained_row(user) for user in data.users[rows]], dtype=np.int64)
    rows, people = rows[people >= 0], people[people >= 0]
    trained = user_rows(predictor.inference)
    x, c, z = rows_design(predictor, data, rows, h)
    residual = z - (np.einsum('nd,nd->n', x, trained[people]) + c)
    return HeldOut(residual, data.actions[rows], held_out_mean_weight(trained, people, x, z - c))


def estimate_prior(fitted, data, rows: np.ndarray, held_out: HeldOut | None = None) -> UserPrior:
    """The prior of a model ``fitted`` (``model.fitted.FittedModel``) on its training ``rows``
    of ``data`` (RatingData), computed in its served form: Σ₀ and the known people's
    covariances from its trained rows and ``rows``; the noise, tails and the mean's weight from
    ``held_out`` (ratings the model, or a fit of it on less, did not see: ``personalisation.recipe``),
    else from the training ratings. See the module docstring."""
    from stars_ros.model.scoring import served_encodings

    predictor = served(fitted)
    inference = predictor.inference
    trained = user_rows(inference)
    mean, covariance, details = population(trained)
    rows = np.asarray(rows, dtype=np.int64)
    x, c, z = rows_design(predictor, data, rows, served_encodings(predictor, data))
    users, actions = np.array([predictor.trained_row(u) for u in data.users[rows]]), data.actions[rows]
    if held_out is not None and len(held_out.residual):
        residual, residual_actions = held_out.residual, held_out.actions
        source = f'{len(residual)} held-out ratings of the trained people'
        if held_out.mean_weight is not None:
            mean = held_out.mean_weight * trained.mean(0)
            details = {**details, 'mean': "weight from held-out ratings, each person against the others' mean",
                       'mean_weight': round(held_out.mean_weight, 6),
                       'james_stein_weight': details.get('mean_weight')}
    else:
        residual, residual_actions = z - (np.einsum('nd,nd->n', x, trained[users]) + c), actions
        source = 'the training ratings'
    noise = np.ones(len(inference.target_mean))
    for a in range(len(noise)):
        if (residual_actions == a).any():
            noise[a] = float(np.mean(residual[residual_actions == a] ** 2))
    nu = student_t_nu(residual / np.sqrt(noise[residual_actions]))
    user_covariance = known_covariances(np.linalg.inv(covariance), x, actions, users, noise, len(trained))
    details = {**details, 'noise': f'mean squared z-residual of {source}, per action', 'ratings': int(len(rows)),
               'nu': f'maximum likelihood on {source}', 'prior_scales': list(PRIOR_SCALES)}
    return UserPrior(mean, covariance, noise, user_covariance, details, nu)


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
