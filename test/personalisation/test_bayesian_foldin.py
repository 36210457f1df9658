"""The Bayesian fold-in's math by hand, its prior, its uncertainty and question criterion, and
the prior's round trip through a checkpoint (on the generated data's tiny checkpoint)."""
import logging
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy import stats

from conftest import TINY_CONFIG
from stars_ros import StarsRecommender
from stars_ros.errors import ConfigError
from stars_ros.model.checkpoint import load_checkpoint, read_checkpoint
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.serving import inference_of
from stars_ros.model.training import StarsTrainer, split_rows
from stars_ros.model.predictor import Predictor
from stars_ros.personalisation import prior as prior_module
from stars_ros.personalisation.foldin import FoldIn, Rating, gaussian_posterior, scale_mixture_posterior, solve_ridge
from stars_ros.personalisation.prior import (UserPrior, encode_all, estimate_prior, held_out_mean_weight, ledoit_wolf,
                                             pooled_rows, population)
from stars_ros.personalisation.uncertainty import Uncertainty, log_psi, student_t_quantile


def test_posterior_is_the_textbook_closed_form_on_a_two_dimensional_toy():
    # x = [[1, 0], [1, 1]], y = [1, 2], noise variances [1, 0.5], prior N(0, diag(2, 1)).
    # By hand: XᵀD⁻¹X = [[3, 2], [2, 2]], Λ = [[3.5, 2], [2, 3]], det Λ = 6.5,
    # Λ⁻¹ = [[3, −2], [−2, 3.5]] / 6.5, XᵀD⁻¹y = [5, 4], mean = Λ⁻¹ [5, 4] = [7, 4] / 6.5.
    mean, covariance = gaussian_posterior(np.array([[1.0, 0.0], [1.0, 1.0]]), np.array([1.0, 2.0]),
                                          np.array([1.0, 0.5]), np.zeros(2), np.diag([0.5, 1.0]))
    assert mean == pytest.approx([7 / 6.5, 4 / 6.5], abs=1e-12)
    assert covariance == pytest.approx(np.array([[3.0, -2.0], [-2.0, 3.5]]) / 6.5, abs=1e-12)


def test_a_flat_prior_gives_least_squares_and_a_sharp_one_the_prior_mean():
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(12, 3)), rng.normal(size=12)
    prior_mean = np.array([0.3, -0.2, 0.5])
    flat, _ = gaussian_posterior(x, y, np.ones(12), prior_mean, 1e-10 * np.eye(3))
    assert flat == pytest.approx(np.linalg.lstsq(x, y, rcond=None)[0], abs=1e-7)
    sharp, covariance = gaussian_posterior(x, y, np.ones(12), prior_mean, 1e10 * np.eye(3))
    assert sharp == pytest.approx(prior_mean, abs=1e-8)
    assert np.abs(covariance).max() < 1e-9


def test_the_scale_mixture_is_bayes_rule_over_the_scales_by_hand():
    # Each scale τ: the Gaussian posterior under prior N(m, τΣ), weighted by the evidence
    # N(y; xm, τxΣxᵀ + D) (τ = 0: N(y; xm, D), θ = m); the mixture's mean and covariance.
    x, y, noise = np.array([[1.0, 0.0], [1.0, 1.0]]), np.array([1.0, 2.0]), np.array([1.0, 0.5])
    prior_mean, prior_covariance = np.array([0.2, -0.1]), np.diag([2.0, 1.0])
    scales = (0.0, 0.5, 2.0)
    evidence, means, covariances = [], [], []
    for scale in scales:
        evidence.append(stats.multivariate_normal.pdf(y, x @ prior_mean, scale * x @ prior_covariance @ x.T
                                                      + np.diag(noise)))
        if scale:
            mean, covariance = gaussian_posterior(x, y, noise, prior_mean, np.linalg.inv(scale * prior_covariance))
        else:
            mean, covariance = prior_mean, np.zeros((2, 2))
        means.append(mean)
        covariances.append(covariance)
    weights = np.array(evidence) / np.sum(evidence)
    mean = sum(w * m for w, m in zip(weights, means))
    covariance = sum(w * (c + np.outer(m - mean, m - mean)) for w, m, c in zip(weights, means, covariances))
    got_mean, got_covariance, got_weights = scale_mixture_posterior(
        x, y, noise, prior_mean, np.linalg.inv(prior_covariance), np.log(2.0), scales)
    assert got_weights == pytest.approx(weights, abs=1e-12)
    assert got_mean == pytest.approx(mean, abs=1e-12)
    assert got_covariance == pytest.approx(covariance, abs=1e-12)
    mean_only = scale_mixture_posterior(x, y, noise, prior_mean, np.linalg.inv(prior_covariance), np.log(2.0), scales,
                                        with_covariance=False)
    assert mean_only[0] == pytest.approx(mean, abs=1e-12) and mean_only[1] is None
    assert mean_only[2] == pytest.approx(weights, abs=1e-12)
    none_mean, none_covariance, _ = scale_mixture_posterior(np.zeros((0, 2)), np.zeros(0), np.zeros(0), prior_mean,
                                                            np.linalg.inv(prior_covariance), np.log(2.0), scales)
    assert none_mean == pytest.approx(prior_mean) and none_covariance == pytest.approx(prior_covariance * 2.5 / 3)
    # with prior weights π over the scales: Bayes' rule weighs each evidence by its π
    scale_prior = np.array([0.6, 0.3, 0.1])
    weighted = scale_prior * np.array(evidence) / np.sum(scale_prior * np.array(evidence))
    mean = sum(w * m for w, m in zip(weighted, means))
    covariance = sum(w * (c + np.outer(m - mean, m - mean)) for w, m, c in zip(weighted, means, covariances))
    got_mean, got_covariance, got_weights = scale_mixture_posterior(
        x, y, noise, prior_mean, np.linalg.inv(prior_covariance), np.log(2.0), scales, scale_prior=scale_prior)
    assert got_weights == pytest.approx(weighted, abs=1e-12) and got_mean == pytest.approx(mean, abs=1e-12)
    assert got_covariance == pytest.approx(covariance, abs=1e-12)
    _, none_covariance, none_weights = scale_mixture_posterior(
        np.zeros((0, 2)), np.zeros(0), np.zeros(0), prior_mean, np.linalg.inv(prior_covariance), np.log(2.0), scales,
        scale_prior=scale_prior)
    assert none_weights == pytest.approx(scale_prior) and none_covariance == pytest.approx(prior_covariance * 0.35)


def test_the_scale_weights_fitted_to_held_out_people_recover_how_far_they_depart():
    """People whose θ − μ₀ is drawn at τ = 0 (70 %) or τ = 3 (30 %) on Σ₀, each rating 40
    scenes: EM over the people's marginal likelihoods finds those shares, with one pseudo-person
    per scale (so every scale keeps a weight); each person's likelihood by hand is N(r; 0, τXΣ₀Xᵀ + D)."""
    rng = np.random.default_rng(7)
    scales, size, people = (0.0, 0.3, 1.0, 3.0), 3, 400
    covariance = np.array([[1.0, 0.3, 0.0], [0.3, 0.5, 0.1], [0.0, 0.1, 0.8]])
    far = rng.random(people) < 0.3
    x, r, who, noise = [], [], [], []
    for person in range(people):
        rows = rng.normal(size=(40, size))
        theta = rng.multivariate_normal(np.zeros(size), (3.0 if far[person] else 0.0) * covariance)
        variance = rng.uniform(0.2, 0.4, 40)
        x.append(rows), r.append(rows @ theta + rng.normal(size=40) * np.sqrt(variance))
        who.append(np.full(40, person)), noise.append(variance)
    x, r, who, noise = map(np.concatenate, (x, r, who, noise))
    weights = prior_module.fitted_scale_weights(x, r, noise, who, covariance, scales)
    assert weights.sum() == pytest.approx(1.0)
    assert weights[0] == pytest.approx(0.7, abs=0.06) and weights[3] == pytest.approx(0.3, abs=0.06)
    assert weights[1] + weights[2] < 0.06 and (weights > 0).all()
    # the fixed point: each weight is the mean responsibility, the pseudo-people counted
    likelihood = np.array([[stats.multivariate_normal.logpdf(r[who == p], np.zeros(40), s * x[who == p] @ covariance
                                                             @ x[who == p].T + np.diag(noise[who == p]))
                            for s in scales] for p in range(people)])
    responsibility = np.exp(likelihood + np.log(weights))
    responsibility /= responsibility.sum(1, keepdims=True)
    assert weights == pytest.approx((responsibility.sum(0) + 1.0) / (people + 4.0), abs=1e-9)


def test_fitted_scale_weights_go_through_the_checkpoint_into_the_fold_in(synthetic, tmp_path):
    """``training.prior_scale_weights`` 'held_out': the prior keeps the fitted weights, a
    checkpoint's dict carries them, and the fold-in starts a new person from them (their
    covariance before any answer is Σ₀ times the weights' mean scale); 'equal' keeps none."""
    train, held = split_rows(synthetic, 0.2, 0)
    config = ExperimentConfig.from_dict(TINY_CONFIG).replace(training={'prior_scale_weights': 'held_out'})
    fitted = StarsTrainer(config).fit(synthetic, train)
    prior = estimate_prior(fitted, synthetic, train, noise_rows=held)
    assert prior.scale_weights.sum() == pytest.approx(1.0) and (prior.scale_weights > 0).all()
    assert prior.details['prior_scale_weights'] == pytest.approx(prior.scale_weights, abs=1e-6)
    restored = UserPrior.from_dict(prior.to_dict())
    assert restored.scale_prior == pytest.approx(prior.scale_weights)
    fitted.user_prior = prior.to_dict()
    foldin = FoldIn(Predictor.from_model(fitted))
    expected = float(prior.scale_weights @ np.array(prior_module.PRIOR_SCALES)) * prior.covariance
    assert foldin.covariance('stranger') == pytest.approx(expected)
    fitted.config = config.replace(training={'prior_scale_weights': 'equal'})
    equal = estimate_prior(fitted, synthetic, train, noise_rows=held)
    assert equal.scale_weights is None and equal.scale_prior == pytest.approx(np.full(4, 0.25))
    assert UserPrior.from_dict(equal.to_dict()).scale_weights is None
    fitted.config = config
    with pytest.raises(ConfigError, match='needs held-out ratings'):
        estimate_prior(fitted, synthetic, train)


def test_the_noise_less_row_uncertainty_recovers_the_true_noise_from_bayesian_rows():
    """People θ ~ N(0, Σ₀), two actions with noise 0.5 and 2.0: each trained row is the exact
    posterior mean from 6 training ratings, so a held-out residual has variance σ²_a + xᵀC_u x.
    Its plain mean square overstates σ²_a; taking the row variance out recovers it, and the
    result is the fixed point σ²_a = mean(residual² − xᵀC_u(σ²)x) by hand."""
    rng = np.random.default_rng(11)
    size, people, train, held = 4, 600, 6, 8
    covariance = np.diag([1.0, 0.6, 0.4, 0.8])
    precision = np.linalg.inv(covariance)
    truth = np.array([0.5, 2.0])
    train_x, train_a, train_who, held_x, held_a, held_who, residual = [], [], [], [], [], [], []
    for person in range(people):
        theta = rng.multivariate_normal(np.zeros(size), covariance)
        xs, acts = rng.normal(size=(train, size)), rng.integers(0, 2, train)
        ys = xs @ theta + rng.normal(size=train) * np.sqrt(truth[acts])
        row_covariance = np.linalg.inv(precision + (xs / truth[acts, None]).T @ xs)
        row = row_covariance @ (xs / truth[acts, None]).T @ ys
        hx, ha = rng.normal(size=(held, size)), rng.integers(0, 2, held)
        residual.append(hx @ theta + rng.normal(size=held) * np.sqrt(truth[ha]) - hx @ row)
        train_x.append(xs), train_a.append(acts), train_who.append(np.full(train, person))
        held_x.append(hx), held_a.append(ha), held_who.append(np.full(held, person))
    train_x, train_a, train_who, held_x, held_a, held_who, residual = map(
        np.concatenate, (train_x, train_a, train_who, held_x, held_a, held_who, residual))
    plain = np.array([np.mean(residual[held_a == a] ** 2) for a in (0, 1)])
    noise, row_variance = prior_module.noise_less_row_uncertainty(
        residual, held_a, held_x, held_who, plain,
        lambda candidate: prior_module.known_covariances(precision, train_x, train_a, train_who, candidate, people))
    assert (plain > truth * 1.15).all()  # the row's error inflates the plain estimate
    assert noise == pytest.approx(truth, rel=0.08)
    rows = prior_module.known_covariances(precision, train_x, train_a, train_who, noise, people)
    by_hand = np.array([held_x[i] @ rows[held_who[i]] @ held_x[i] for i in range(len(residual))])
    assert row_variance == pytest.approx(by_hand, rel=1e-6)
    assert noise == pytest.approx([np.mean(residual[held_a == a] ** 2 - by_hand[held_a == a]) for a in (0, 1)],
                                  rel=1e-6)


def test_the_noise_less_row_uncertainty_keeps_its_floor_and_goes_through_the_fit(synthetic):
    """An action whose row variance exceeds its residuals keeps ``NOISE_FLOOR`` of its plain
    estimate; on a fit, the option lowers the noise below the plain held-out one, says so, and
    needs held-out ratings."""
    x = np.ones((4, 1))
    noise, _ = prior_module.noise_less_row_uncertainty(
        np.full(4, 0.1), np.zeros(4, dtype=int), x, np.zeros(4, dtype=int), np.array([0.01]),
        lambda candidate: np.ones((1, 1, 1)))
    assert noise == pytest.approx([0.1 * 0.01])
    train, held = split_rows(synthetic, 0.2, 0)
    config = ExperimentConfig.from_dict(TINY_CONFIG).replace(training={'prior_noise': 'less_row_uncertainty'})
    fitted = StarsTrainer(config).fit(synthetic, train)
    less = estimate_prior(fitted, synthetic, train, noise_rows=held)
    assert less.noise[0] < less.details['noise_held_out_residual'][0] and 'posterior variance' in less.details['noise']
    fitted.config = config.replace(training={'prior_noise': 'held_out_residual'})
    plain = estimate_prior(fitted, synthetic, train, noise_rows=held)
    assert plain.noise[0] == pytest.approx(less.details['noise_held_out_residual'][0], rel=1e-5)
    fitted.config = config
    with pytest.raises(ConfigError, match='prior_noise'):
        estimate_prior(fitted, synthetic, train)


def assert_the_plain_encoder_trains_without_the_held_out_ratings(config, data, rows, monkeypatch):
    """The front door's ``fit`` with ``config`` trains the plain encoder on the rows StARS
    trains on: ``rows`` less the held-out share the prior's residuals come from."""
    fitted_rows = []
    original = StarsTrainer.fit
    monkeypatch.setattr(StarsTrainer, 'fit', lambda self, data, rows, **kw: (fitted_rows.append(np.asarray(rows)),
                                                                              original(self, data, rows, **kw))[1])
    StarsRecommender(config.to_dict()).fit(data, rows)
    plain_rows, stars_rows = fitted_rows
    assert np.array_equal(plain_rows, stars_rows) and len(plain_rows) < len(rows)


def test_scale_weights_from_the_plain_encoder_weigh_its_residuals_where_it_did_not_train(synthetic, monkeypatch):
    """``training.prior_scale_weights`` 'held_out_plain': the weights are EM's over each trained
    person's held-out residuals from the plain encoder (scored here by its torch head), which
    the front door then trains without those ratings; without a plain encoder it is refused."""
    train, held = split_rows(synthetic, 0.2, 0)
    config = ExperimentConfig.from_dict(TINY_CONFIG).replace(model={'strangers': 'base_encoder'},
                                                             training={'prior_scale_weights': 'held_out_plain'})
    fitted = StarsTrainer(config).fit(synthetic, train)
    with pytest.raises(ConfigError, match='plain encoder'):
        estimate_prior(fitted, synthetic, train, noise_rows=held)
    fitted.stranger_model = plain = StarsTrainer(config.stranger_encoder()).fit(synthetic, train).model
    prior = estimate_prior(fitted, synthetic, train, noise_rows=held)
    assert 'plain encoder' in prior.details['prior_scale_weights_from']
    inference = inference_of(fitted.require_model())
    known = held[fitted.user_vocabulary.rows(list(synthetic.users[held])) >= 0]
    people = fitted.user_vocabulary.rows(list(synthetic.users[known]))
    actions = synthetic.actions[known]
    with torch.no_grad():
        h = plain.encode(synthetic.store.batch(torch.from_numpy(synthetic.scenes[known])))
        served = plain.to_rating_scale(plain.head(h)).double().numpy()[np.arange(len(known)), actions]
    x, c, z = prior_module.rows_design(fitted, inference, synthetic, known, encode_all(fitted, synthetic))
    residual = z - inference.to_z(served, actions)
    expected = prior_module.fitted_scale_weights(x, residual, prior.noise[actions], people, prior.covariance)
    assert prior.scale_weights == pytest.approx(expected, abs=1e-6)
    assert_the_plain_encoder_trains_without_the_held_out_ratings(config, synthetic, train, monkeypatch)


DEPARTURE_COVARIANCE = np.array([[1.0, 0.3, 0.0], [0.3, 0.5, 0.1], [0.0, 0.1, 0.8]])  # Σ₀ of the simulated people
EQUAL_SCALES = np.full(len(prior_module.PRIOR_SCALES), 1 / len(prior_module.PRIOR_SCALES))


def departing_people(rng, noise_share: float, people: int = 300, n: int = 30) -> tuple:
    """(x, r, who, noise) of ``people`` simulated strangers, ``n`` ratings each: θ − μ₀ drawn
    from the equal scale mixture on 0.4·Σ₀, ratings whose noise is ``noise_share`` times the
    stated variance ``noise``."""
    x, r, who, noise = [], [], [], []
    for person in range(people):
        rows = rng.normal(size=(n, 3))
        scale = prior_module.PRIOR_SCALES[rng.integers(len(prior_module.PRIOR_SCALES))]
        theta = rng.multivariate_normal(np.zeros(3), 0.4 * scale * DEPARTURE_COVARIANCE)
        variance = rng.uniform(0.2, 0.4, n)
        x.append(rows), r.append(rows @ theta + rng.normal(size=n) * np.sqrt(noise_share * variance))
        who.append(np.full(n, person)), noise.append(variance)
    return tuple(map(np.concatenate, (x, r, who, noise)))


def marginal_likelihood_by_hand(x, r, who, noise, people: int, g: float, s: float = 1.0) -> float:
    """Σ over the first ``people`` of log mean_τ N(r; 0, gτXΣ₀Xᵀ + sD) by scipy's multivariate normal."""
    total = 0.0
    for person in range(people):
        mine = who == person
        per_scale = [stats.multivariate_normal.logpdf(r[mine], np.zeros(mine.sum()),
                                                      g * t * x[mine] @ DEPARTURE_COVARIANCE @ x[mine].T
                                                      + s * np.diag(noise[mine])) for t in prior_module.PRIOR_SCALES]
        total += np.log(np.mean(np.exp(per_scale)))
    return total


def test_the_fitted_spread_recovers_the_size_of_the_covariance_people_depart_by():
    """People whose θ − μ₀ is drawn from the equal scale mixture on 0.4·Σ₀, 30 ratings each:
    the maximum marginal likelihood g is near 0.4, its likelihood by hand (scipy's multivariate
    normal, mixed over the scales) is no lower there than a little either side, and ratings
    that carry only noise send g to the bottom of its range."""
    rng = np.random.default_rng(5)
    x, r, who, noise = departing_people(rng, 1.0)
    spread, share = prior_module.fitted_spread(x, r, noise, who, DEPARTURE_COVARIANCE, EQUAL_SCALES)
    assert spread == pytest.approx(0.4, rel=0.2) and share == 1.0  # the noise's share is not fitted here
    by_hand = [marginal_likelihood_by_hand(x, r, who, noise, 300, g) for g in (spread, spread * 0.97, spread * 1.03)]
    assert by_hand[0] >= max(by_hand[1:])
    quiet = rng.normal(size=len(r)) * np.sqrt(noise)
    assert prior_module.fitted_spread(x, quiet, noise, who, DEPARTURE_COVARIANCE, EQUAL_SCALES)[0] < 0.05


def test_the_spread_and_the_noise_share_fitted_together_recover_both():
    """People at 0.4·Σ₀ (the equal scale mixture) whose ratings carry 1.12 times the stated
    noise (beside the search grid's point s = 1, where a search can stick), 30 ratings each:
    fitted together, g is near 0.4 and s near 1.12; the likelihood by hand (scipy's multivariate
    normal, mixed over the scales) is no lower there than a little either side in each;
    residuals with no departure send g to the bottom of its range and keep s."""
    rng = np.random.default_rng(6)
    x, r, who, noise = departing_people(rng, 1.12)
    spread, share = prior_module.fitted_spread(x, r, noise, who, DEPARTURE_COVARIANCE, EQUAL_SCALES, fit_noise=True)
    assert spread == pytest.approx(0.4, rel=0.2) and share == pytest.approx(1.12, rel=0.05)
    few = who < 60  # a fifth of the people: enough to place the optimum of their own sum
    g, s = prior_module.fitted_spread(x[few], r[few], noise[few], who[few], DEPARTURE_COVARIANCE, EQUAL_SCALES,
                                      fit_noise=True)
    by_hand = [marginal_likelihood_by_hand(x, r, who, noise, 60, *point)
               for point in ((g, s), (g * 0.97, s), (g * 1.03, s), (g, s * 0.97), (g, s * 1.03))]
    assert by_hand[0] >= max(by_hand[1:])
    quiet = rng.normal(size=len(r)) * np.sqrt(2.0 * noise)
    g, s = prior_module.fitted_spread(x, quiet, noise, who, DEPARTURE_COVARIANCE, EQUAL_SCALES, fit_noise=True)
    assert g < 0.05 and s == pytest.approx(2.0, rel=0.1)


def test_the_fitted_spread_goes_through_the_fit_and_serves_strangers_g_times_the_trained_spread(synthetic,
                                                                                               monkeypatch):
    """``training.prior_spread`` 'held_out_plain': a stranger's covariance is g times the trained
    rows' Σ₀, g ``fitted_spread`` of the held-out residuals from the plain encoder (here one
    off by an offset per person, 0.7 noise sd, so that g is inside its range: the tiny model's own plain
    encoder leaves residuals the noise explains); trained people keep their covariances from
    Σ₀; the front door trains that encoder without those ratings; the config refuses it
    without a plain encoder or with fitted scale weights."""
    train, held = split_rows(synthetic, 0.2, 0)
    config = ExperimentConfig.from_dict(TINY_CONFIG).replace(model={'strangers': 'base_encoder'},
                                                             training={'prior_spread': 'held_out_plain'})
    fitted = StarsTrainer(config).fit(synthetic, train)
    fitted.stranger_model = StarsTrainer(config.stranger_encoder()).fit(synthetic, train).model
    fitted.config = config.replace(training={'prior_spread': 'trained_rows'})
    rows = estimate_prior(fitted, synthetic, train, noise_rows=held)
    inference = inference_of(fitted.require_model())
    known = held[fitted.user_vocabulary.rows(list(synthetic.users[held])) >= 0]
    people = fitted.user_vocabulary.rows(list(synthetic.users[known]))
    actions = synthetic.actions[known]
    x = prior_module.rows_design(fitted, inference, synthetic, known, encode_all(fitted, synthetic))[0]
    offset = np.random.default_rng(3).normal(0.0, 0.7 * np.sqrt(rows.noise.mean()), len(fitted.user_vocabulary))

    def plain_off_by_an_offset(fitted, inference, data, rows):
        z = prior_module.rows_design(fitted, inference, data, rows, encode_all(fitted, data))[2]
        return z - offset[fitted.user_vocabulary.rows(list(data.users[rows]))]
    monkeypatch.setattr(prior_module, 'plain_z', plain_off_by_an_offset)
    fitted.config = config
    spread = estimate_prior(fitted, synthetic, train, noise_rows=held)
    g = spread.details['prior_spread']
    assert prior_module.SPREAD_BOUNDS[0] < g < prior_module.SPREAD_BOUNDS[1]
    assert 'plain encoder' in spread.details['prior_spread_from'] and 'prior_spread' not in rows.details
    assert spread.covariance == pytest.approx(g * rows.covariance, rel=1e-5)
    assert spread.user_covariance == pytest.approx(rows.user_covariance)
    expected = prior_module.fitted_spread(x, offset[people], rows.noise[actions], people, rows.covariance,
                                          np.full(4, 0.25))
    assert (g, 1.0) == pytest.approx(expected, rel=1e-5)
    assert spread.stranger_noise is None and 'stranger_noise_share' not in spread.details
    fitted.config = config.replace(training={'stranger_noise': 'held_out_plain'})
    noisy = estimate_prior(fitted, synthetic, train, noise_rows=held)
    g, share = prior_module.fitted_spread(x, offset[people], rows.noise[actions], people, rows.covariance,
                                          np.full(4, 0.25), fit_noise=True)
    assert noisy.details['prior_spread'] == pytest.approx(g, rel=1e-5)
    assert noisy.details['stranger_noise_share'] == pytest.approx(share, rel=1e-5)
    assert noisy.covariance == pytest.approx(g * rows.covariance, rel=1e-5)
    assert noisy.stranger_noise == pytest.approx(share * rows.noise, rel=1e-5)
    assert noisy.noise == pytest.approx(rows.noise) and noisy.user_covariance == pytest.approx(rows.user_covariance)
    assert_the_plain_encoder_trains_without_the_held_out_ratings(config, synthetic, train, monkeypatch)
    with pytest.raises(ConfigError, match="prior_spread .held_out_plain. fits residuals from the plain encoder"):
        config.replace(model={'strangers': 'prior_mean'})
    with pytest.raises(ConfigError, match="needs training.prior_scale_weights .equal."):
        config.replace(training={'prior_scale_weights': 'held_out_plain'})
    with pytest.raises(ConfigError, match="stranger_noise .held_out_plain. is fitted together with the prior's spread"):
        config.replace(training={'prior_spread': 'trained_rows', 'stranger_noise': 'held_out_plain'})


def test_a_strangers_own_noise_goes_through_the_checkpoint_into_their_fold_in_and_score_sd(synthetic,
                                                                                          synthetic_scenes):
    """``UserPrior.stranger_noise``: a checkpoint's dict carries it (one without it gives
    strangers the trained people's noise); a stranger's posterior weighs their ratings by it
    and their score_sd adds it, while a trained person keeps the trained people's noise."""
    train, _ = split_rows(synthetic, 0.2, 0)
    fitted = StarsTrainer(ExperimentConfig.from_dict(TINY_CONFIG)).fit(synthetic, train)
    prior = estimate_prior(fitted, synthetic, train)
    assert UserPrior.from_dict(prior.to_dict()).stranger_noise is None
    quieter = UserPrior(prior.mean, prior.covariance, prior.noise, prior.user_covariance, prior.details, prior.nu,
                        None, 0.3 * prior.noise)
    restored = UserPrior.from_dict(quieter.to_dict())
    assert restored.stranger_noise == pytest.approx(0.3 * prior.noise)
    fitted.user_prior = quieter.to_dict()
    predictor = Predictor.from_model(fitted)
    foldin, known = FoldIn(predictor), predictor.users[0]
    assert foldin.noise_for('stranger') == pytest.approx(0.3 * prior.noise)
    assert foldin.noise_for(known) == pytest.approx(prior.noise)
    ratings = ratings_of(synthetic_scenes, 5)
    model = foldin.fit(ratings, 'stranger')
    x, y = foldin.regression(ratings)
    mean, covariance, precision = foldin.prior_distribution('stranger')
    expected, expected_covariance, _ = scale_mixture_posterior(x, y, 0.3 * prior.noise[np.zeros(5, dtype=int)], mean,
                                                               precision, np.linalg.slogdet(covariance)[1])
    assert np.append(model.p, model.b) == pytest.approx(expected)
    assert model.covariance == pytest.approx(expected_covariance)
    trained = foldin.fit(ratings, known, hand_over=False)
    mean, _, precision = foldin.prior_distribution(known)
    expected = gaussian_posterior(x, y, prior.noise[np.zeros(5, dtype=int)], mean, precision)[0]
    assert np.append(trained.p, trained.b) == pytest.approx(expected)
    uncertainty = Uncertainty(foldin)
    h = predictor.encode(synthetic_scenes[20:21]).astype(np.float64)
    x, _ = predictor.inference.linear_form(h, np.array([-1]), np.array([0]))
    sd = uncertainty.spread(predictor, 'stranger', h, np.array([-1]), [0]).sd[0]
    by_hand = np.sqrt(x[0] @ foldin.covariance('stranger') @ x[0] + 0.3 * prior.noise[0])
    assert sd == pytest.approx(by_hand * predictor.inference.target_std[0])
    known_sd = uncertainty.spread(predictor, known, h, np.array([-1]), [0]).sd[0]
    by_hand = np.sqrt(x[0] @ foldin.covariance(known) @ x[0] + prior.noise[0])
    assert known_sd == pytest.approx(by_hand * predictor.inference.target_std[0])


def test_the_student_t_tails_are_found_and_its_intervals_have_unit_variance():
    rng = np.random.default_rng(4)
    gaussian = rng.standard_normal(4000)
    heavy = rng.standard_t(4, 4000) / np.sqrt(2)  # unit variance, ν = 4
    assert prior_module.student_t_nu(gaussian) >= 30
    assert prior_module.student_t_nu(heavy) <= 6
    assert student_t_quantile(0.975, np.inf) == pytest.approx(1.959964, abs=1e-6)
    # t₄ scaled to unit variance: its 75 % quantile 0.7407 · sqrt(2/4) = 0.5238, inside the normal's 0.6745
    assert student_t_quantile(0.75, 4.0) == pytest.approx(0.740697 * np.sqrt(0.5), abs=1e-6)


def test_ledoit_wolf_keeps_the_trace_and_is_positive_definite_with_fewer_rows_than_dimensions():
    rows = np.random.default_rng(1).normal(size=(8, 20)) * np.linspace(0.5, 2.0, 20)
    covariance, shrinkage = ledoit_wolf(rows)
    sample = np.cov(rows, rowvar=False, bias=True)
    assert 0 < shrinkage <= 1
    assert np.trace(covariance) == pytest.approx(np.trace(sample))
    assert np.linalg.eigvalsh(sample).min() < 1e-10 < np.linalg.eigvalsh(covariance).min()


def test_two_people_or_rows_that_do_not_spread_still_give_an_invertible_prior():
    """Two rows give Ledoit–Wolf nothing to shrink with (a rank-one sample, shrinkage 0):
    the covariance becomes its trace spread evenly; rows all alike give the identity."""
    two = np.array([[0.0, 1.0, 0.2], [0.4, 0.0, 0.2]])
    _, covariance, _ = population(two)
    trace = np.trace(np.cov(two * [1, 1, 1], rowvar=False, bias=True))
    assert np.linalg.eigvalsh(covariance).min() > 0
    assert np.trace(covariance) == pytest.approx(trace)
    mean, covariance, details = population(np.ones((4, 3)))
    assert (covariance == np.eye(3)).all() and not mean.any() and 'do not spread' in details['covariance']


def test_the_population_mean_is_shrunk_towards_zero_as_far_as_its_own_error_warrants():
    rng = np.random.default_rng(2)
    far = rng.normal(size=(10, 6)) * 0.1 + 5.0  # a mean far beyond its error: kept
    assert population(far)[2]['mean_weight'] > 0.99
    centred = rng.normal(size=(10, 6))
    centred -= centred.mean(0) - 0.01  # a mean well within its error: shrunk away
    mean, _, details = population(centred)
    assert details['mean_weight'] == 0 and not mean.any()


def test_the_held_out_mean_weight_is_least_squares_against_the_others_mean_by_hand():
    trained = np.array([[1.0, 0.0], [3.0, 0.0], [2.0, 6.0]])
    people = np.array([0, 1, 2])
    x = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    # leave-one-out means: (2.5, 3), (1.5, 3), (2, 0); so a = x · mean = 2.5, 1.5, 0
    r = np.array([1.0, 0.6, 5.0])
    assert held_out_mean_weight(trained, people, x, r) == pytest.approx((2.5 * 1.0 + 1.5 * 0.6) / (2.5 ** 2 + 1.5 ** 2))
    assert held_out_mean_weight(trained, people, x, -r) == 0.0  # a mean that points away from people: not used
    assert held_out_mean_weight(trained, people, x, 10 * r) == 1.0  # never beyond the mean itself
    assert held_out_mean_weight(trained[:1], people[:1], x[:1], r[:1]) is None  # one person: no one else to ask


def test_the_pooled_row_is_the_posterior_of_everyone_as_one_person_and_of_the_others_without_each():
    rng = np.random.default_rng(4)
    x, r, weights = rng.normal(size=(30, 3)), rng.normal(size=30), rng.uniform(0.5, 2.0, size=30)
    people, precision = np.repeat([0, 1, 2], 10), np.diag([1.0, 2.0, 3.0])

    def by_hand(keep):  # least squares of the weighted rows stacked on the prior's square root
        design = np.vstack([x[keep] * np.sqrt(weights[keep])[:, None], np.linalg.cholesky(precision).T])
        return np.linalg.lstsq(design, np.concatenate([r[keep] * np.sqrt(weights[keep]), np.zeros(3)]), rcond=None)[0]
    pooled, without = pooled_rows(x, r, weights, people, 3, precision)
    assert pooled == pytest.approx(by_hand(np.ones(30, dtype=bool)))
    for person in range(3):
        assert without[person] == pytest.approx(by_hand(people != person))


def test_the_stranger_row_is_the_candidate_that_predicts_held_out_people_better(synthetic):
    """Each trained person's held-out ratings, predicted from rows fitted without them, choose
    between the pooled row and the others' mean; ``pooled_stranger`` False keeps the mean."""
    train, held = split_rows(synthetic, 0.2, 0)
    config = ExperimentConfig.from_dict(TINY_CONFIG)
    fitted = StarsTrainer(config).fit(synthetic, train)
    prior = estimate_prior(fitted, synthetic, train, noise_rows=held)
    errors = prior.details['held_out_squared_z_error']
    assert prior.details['mean'].startswith('pooled') == (errors['pooled'] < errors['others_mean'])
    fitted.config = config.replace(training={'pooled_stranger': False})
    kept = estimate_prior(fitted, synthetic, train, noise_rows=held)
    assert 'held_out_squared_z_error' not in kept.details and not kept.details['mean'].startswith('pooled')
    if prior.details['mean'].startswith('pooled'):
        assert not np.allclose(prior.mean, kept.mean)
    else:
        assert prior.mean == pytest.approx(kept.mean)


def test_a_population_mean_that_points_against_held_out_people_is_not_used(synthetic):
    train, held = split_rows(synthetic, 0.2, 0)
    fitted = StarsTrainer(ExperimentConfig.from_dict(TINY_CONFIG)).fit(synthetic, train)
    inference = inference_of(fitted.require_model())
    x, c, z = prior_module.rows_design(fitted, inference, synthetic, held, encode_all(fitted, synthetic))
    # every trained person moved alike along p's first coordinate, against what their held-out ratings say
    # (x does not depend on θ): a mean far beyond its own error, which James–Stein keeps
    shift = np.zeros(fitted.config.model.dim)
    shift[0] = -5.0 * np.sign(np.sum(x[:, 0] * (z - c)))
    fitted.require_model().user_embedding.weight.data += torch.from_numpy(shift).float()
    prior = estimate_prior(fitted, synthetic, train, noise_rows=held)
    assert prior.details['james_stein_weight'] > 0.9
    assert prior.details['mean_weight'] == 0.0 and not prior.mean.any()
    assert 'held-out' in prior.details['mean']


def test_the_noise_comes_from_held_out_ratings_when_given(synthetic):
    train, held = split_rows(synthetic, 0.2, 0)
    fitted = StarsTrainer(ExperimentConfig.from_dict(TINY_CONFIG)).fit(synthetic, train)
    prior = estimate_prior(fitted, synthetic, train, noise_rows=held)
    # by the model's own scoring (not the linear form the estimate uses): trained rows, unclipped
    inference = inference_of(fitted.require_model())
    users = fitted.user_vocabulary.rows(list(synthetic.users[held]))
    known, users = held[users >= 0], users[users >= 0]
    items = synthetic.item_keys(fitted.config.model.item_key)
    scenes = fitted.scene_vocabulary.rows([items[s] for s in synthetic.scenes[known]])
    h = encode_all(fitted, synthetic)[synthetic.scenes[known]].astype(np.float32)
    actions = synthetic.actions[known]
    scores = inference.scores(h, (inference.user_rows[users], inference.user_offsets[users]), scenes)
    errors = (synthetic.scores[known] - scores[np.arange(len(known)), actions]) / inference.target_std[actions]
    assert prior.noise[0] == pytest.approx(np.mean(errors ** 2), rel=1e-4)
    assert 'held-out' in prior.details['noise']
    assert estimate_prior(fitted, synthetic, train).noise[0] < prior.noise[0]  # training residuals understate it


@pytest.fixture(scope='module')
def predictor(tiny_checkpoint):
    return Predictor.load(tiny_checkpoint)


def test_the_checkpoint_keeps_the_prior_and_the_fold_in_uses_it(tiny_checkpoint, predictor):
    content = read_checkpoint(tiny_checkpoint)
    assert set(content['user_prior']) >= {'mean', 'covariance', 'noise', 'user_covariance'}
    assert content['metadata']['user_prior']['covariance'] == 'ledoit-wolf'
    foldin = FoldIn(predictor)
    stored = UserPrior.from_dict(content['user_prior'])
    assert foldin.population == pytest.approx(stored.mean)
    assert (foldin.noise > 0).all()
    known = predictor.users[0]
    assert foldin.covariance(known) == pytest.approx(stored.user_covariance[0])
    assert np.trace(foldin.covariance(known)) < np.trace(foldin.covariance('stranger'))


def test_an_older_checkpoint_without_a_prior_still_loads_and_says_so(tiny_checkpoint, caplog):
    recommender, _ = load_checkpoint(tiny_checkpoint)
    recommender.user_prior = None  # what a checkpoint written before the prior was kept gives
    with caplog.at_level(logging.WARNING, logger=prior_module.__name__):
        foldin = FoldIn(Predictor.from_model(recommender))
    assert 'stores no personalisation prior' in caplog.text
    assert (foldin.noise == prior_module.DEFAULT_NOISE).all()


def ratings_of(scenes, count):
    return [Rating(scene, 'navigate', 0.1 + 0.08 * k, scene['identifier']) for k, scene in enumerate(scenes[:count])]


def test_fold_in_is_the_posterior_of_its_design_and_ridge_stays_an_override(predictor, synthetic_scenes):
    foldin = FoldIn(predictor)
    ratings = ratings_of(synthetic_scenes, 5)
    model = foldin.fit(ratings, 'newcomer')
    x, y = foldin.regression(ratings)
    mean, covariance, precision = foldin.prior_distribution('newcomer')
    expected, expected_covariance, _ = scale_mixture_posterior(x, y, foldin.noise[np.zeros(5, dtype=int)], mean,
                                                               precision, np.linalg.slogdet(covariance)[1])
    assert np.append(model.p, model.b) == pytest.approx(expected)
    assert model.covariance == pytest.approx(expected_covariance)
    assert model.regularisation == 0
    ridge = foldin.fit(ratings, 'newcomer', regularisation=3.0)
    assert np.append(ridge.p, ridge.b) == pytest.approx(solve_ridge(x, y, mean, 3.0))
    empty = foldin.fit([], 'newcomer')
    assert np.append(empty.p, empty.b) == pytest.approx(mean) and empty.n_ratings == 0


def test_robots_holding_the_same_ratings_serve_bit_identical_posteriors(tiny_checkpoint, synthetic_scenes):
    ratings = ratings_of(synthetic_scenes, 6)
    first = FoldIn(Predictor.load(tiny_checkpoint), scene_by_scene=True).fit(ratings, 'shared')
    second = FoldIn(Predictor.load(tiny_checkpoint), scene_by_scene=True).fit(ratings, 'shared')
    assert np.array_equal(first.p, second.p) and first.b == second.b
    assert np.array_equal(first.covariance, second.covariance)


def test_score_sd_shrinks_with_feedback_and_is_the_hand_formula(predictor, synthetic_scenes):
    foldin = FoldIn(predictor)
    uncertainty = Uncertainty(foldin)
    h = predictor.encode(synthetic_scenes[20:21]).astype(np.float64)
    x, _ = predictor.inference.linear_form(h, np.array([-1]), np.array([0]))
    before = uncertainty.rating_sd(x, np.array([0]), uncertainty.covariance('newcomer'), uncertainty.noise('newcomer'))[0]
    model = foldin.fit(ratings_of(synthetic_scenes, 10), 'newcomer')
    after = uncertainty.rating_sd(x, np.array([0]), uncertainty.covariance('newcomer', model),
                                  uncertainty.noise('newcomer'))[0]
    by_hand = np.sqrt(x[0] @ model.covariance @ x[0] + foldin.noise[0]) * predictor.inference.target_std[0]
    assert after == pytest.approx(by_hand)
    assert after < before
    floor = np.sqrt(foldin.noise[0]) * predictor.inference.target_std[0]  # the rating noise stays
    assert after > floor


def one_action_uncertainty(noise: float, std: float) -> Uncertainty:
    """``Uncertainty`` over θ of dimension 2 for one action with z-noise ``noise`` and rating
    scale ``std`` (mean 0), from a stand-in for the fold-in and its InferenceModel."""
    foldin = SimpleNamespace(dim=1, noise=np.array([noise]),
                             inference=SimpleNamespace(target_std=np.array([std]), target_mean=np.array([0.0])))
    return Uncertainty(foldin)


def test_p_first_is_best_is_one_for_a_sure_gap_and_a_half_for_a_tie():
    uncertainty = one_action_uncertainty(noise=0.1, std=1.0)
    x = np.array([[1.0, 0.0], [0.0, 1.0]])
    actions = np.zeros(2, dtype=int)
    sure = uncertainty.p_first_is_best(x, np.array([0.0, 0.0]), actions, np.array([5.0, 0.0]), 0.01 * np.eye(2), 0)
    tie = uncertainty.p_first_is_best(x, np.array([0.0, 0.0]), actions, np.array([1.0, 1.0]), np.eye(2), 0)
    assert sure == 1.0
    assert tie == pytest.approx(0.5, abs=0.06)


def test_the_question_that_teaches_most_is_the_one_along_the_targets_uncertainty():
    uncertainty = one_action_uncertainty(noise=0.5, std=2.0)
    covariance = np.diag([4.0, 0.25])
    targets = (np.array([[1.0, 0.0], [1.0, 0.0]]), np.zeros(2, dtype=int))  # both load on θ₀ only
    along, across = (np.array([[1.0, 0.0]]), np.zeros(1, dtype=int)), (np.array([[0.0, 1.0]]), np.zeros(1, dtype=int))
    gains = uncertainty.variance_reduction([along, across], targets, covariance, uncertainty.foldin.noise)
    # by hand: asking x = e₀: k_t = 4 for both targets, innovation 4 + 0.5; 2 · 4 · 16 / 4.5; across: k_t = 0
    assert gains == pytest.approx([2 * 4 * 16 / 4.5, 0.0])


def test_the_decision_value_is_the_expected_gain_of_re_choosing_by_hand():
    uncertainty = one_action_uncertainty(noise=0.5, std=2.0)
    covariance, mean = np.diag([4.0, 0.25]), np.array([0.3, 0.0])
    # one decision of two entries: scores 2·θ₀ and 2·θ₁ (rating scale), now 0.6 against 0: the first leads
    decision = (np.array([[1.0, 0.0], [0.0, 1.0]]), np.zeros(2), np.zeros(2, dtype=int))
    along, far = (np.array([[1.0, 0.0]]), np.zeros(1, dtype=int)), (np.array([[0.0, 0.0]]), np.zeros(1, dtype=int))
    noise = uncertainty.foldin.noise
    values = uncertainty.log_decision_value([along, far], [decision], mean, covariance, noise)
    # by hand: the gap's row g = 2·(1, −1), its mean 0.6; asking x = e₀: X Σ g = 8, innovation 4 + 0.5,
    # s² = 64 / 4.5; the gain s·ψ(0.6 / s), ψ(z) = φ(z) − z(1 − Φ(z)); a question loading on nothing gains 0
    s = np.sqrt(64 / 4.5)
    z = 0.6 / s
    assert np.exp(values) == pytest.approx([s * (stats.norm.pdf(z) - z * stats.norm.sf(z)), 0.0])
    clear, far_clear = uncertainty.log_decision_value([along], [decision], np.array([30.0, 0.0]), covariance, noise)[0], \
        uncertainty.log_decision_value([along], [decision], np.array([300.0, 0.0]), covariance, noise)[0]
    assert values[0] - 10 > clear > far_clear > -np.inf  # a clear choice is worth little, yet still ordered
    single = (decision[0][:1], decision[1][:1], decision[2][:1])
    assert uncertainty.log_decision_value([along], [single], mean, covariance, noise)[0] == -np.inf  # nothing to choose


def test_log_psi_is_the_expected_shortfall_and_keeps_its_digits_far_out():
    z = np.array([0.0, 0.5, 2.0, 8.0])
    assert np.exp(log_psi(z)) == pytest.approx(stats.norm.pdf(z) - z * stats.norm.sf(z), rel=1e-9)
    far = log_psi(np.array([50.0, 5e3, 5e5]))
    assert np.all(np.isfinite(far)) and np.all(np.diff(far) < 0)
    # the asymptotic series ψ(z) = φ(z) / z² · (1 − 3 / z² + ...)
    assert far[0] == pytest.approx(stats.norm.logpdf(50.0) - 2 * np.log(50.0) + np.log1p(-3 / 50.0 ** 2), abs=1e-5)
