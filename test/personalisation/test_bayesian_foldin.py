"""The Bayesian fold-in's math by hand, its prior, its uncertainty and question criterion, and
the prior's round trip through a checkpoint (on the generated data's tiny checkpoint)."""
import logging
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy import stats

from conftest import TINY_CONFIG
from stars_ros.model.checkpoint import load_checkpoint, read_checkpoint, stored_prior
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.scoring import served_encodings
from stars_ros.model.training import StarsTrainer, split_rows
from stars_ros.model.predictor import Predictor
from stars_ros.personalisation import prior as prior_module
from stars_ros.personalisation.foldin import FoldIn, Rating, gaussian_posterior, scale_mixture_posterior, solve_ridge
from stars_ros.personalisation.prior import (UserPrior, estimate_prior, held_out_mean_weight, held_out_residuals,
                                             ledoit_wolf, population)
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


def test_a_population_mean_that_points_against_held_out_people_is_not_used(synthetic):
    train, held = split_rows(synthetic, 0.2, 0)
    fitted = StarsTrainer(ExperimentConfig.from_dict(TINY_CONFIG)).fit(synthetic, train)
    predictor = Predictor.from_model(fitted)
    x, c, z = prior_module.rows_design(predictor, synthetic, held, served_encodings(predictor, synthetic))
    # every trained person moved alike along p's first coordinate, against what their held-out ratings say
    # (x does not depend on θ): a mean far beyond its own error, which James–Stein keeps
    shift = np.zeros(fitted.config.model.dim)
    shift[0] = -5.0 * np.sign(np.sum(x[:, 0] * (z - c)))
    fitted.require_model().user_embedding.weight.data += torch.from_numpy(shift).float()
    prior = estimate_prior(fitted, synthetic, train, held_out_residuals(fitted, synthetic, held))
    assert prior.details['james_stein_weight'] > 0.9
    assert prior.details['mean_weight'] == 0.0 and not prior.mean.any()
    assert 'held-out' in prior.details['mean']


def test_the_noise_comes_from_held_out_ratings_when_given(synthetic):
    train, held = split_rows(synthetic, 0.2, 0)
    fitted = StarsTrainer(ExperimentConfig.from_dict(TINY_CONFIG)).fit(synthetic, train)
    prior = estimate_prior(fitted, synthetic, train, held_out_residuals(fitted, synthetic, held))
    # by the served scoring (not the linear form the estimate uses): trained rows, unclipped
    predictor = Predictor.from_model(fitted)
    inference = predictor.inference
    users = fitted.user_vocabulary.rows(list(synthetic.users[held]))
    known, users = held[users >= 0], users[users >= 0]
    items = synthetic.item_keys(fitted.config.model.item_key)
    scenes = fitted.scene_vocabulary.rows([items[s] for s in synthetic.scenes[known]])
    h = served_encodings(predictor, synthetic, synthetic.scenes[known]).astype(np.float32)
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


def test_a_prior_of_an_unshipped_experiment_loads_with_equal_scales_and_one_noise(tiny_checkpoint, caplog):
    """A prior written with fitted scale weights or a stranger's own noise (options that did not
    ship) still loads: the fold-in weighs the scales equally and gives everyone the trained
    people's noise, and says so."""
    stored = stored_prior(read_checkpoint(tiny_checkpoint))
    plain = UserPrior.from_dict(stored)
    older = {**stored, 'scale_weights': np.array([0.7, 0.1, 0.1, 0.1]),
             'strangers_own_noise': 0.3 * plain.noise}
    with caplog.at_level(logging.WARNING, logger=prior_module.__name__):
        restored = UserPrior.from_dict(older)
    assert 'scale_weights, strangers_own_noise' in caplog.text
    assert restored.noise == pytest.approx(plain.noise) and restored.mean == pytest.approx(plain.mean)
    assert set(restored.to_dict()) == set(plain.to_dict())


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
    before = uncertainty.rating_sd(x, np.array([0]), uncertainty.covariance('newcomer'))[0]
    model = foldin.fit(ratings_of(synthetic_scenes, 10), 'newcomer')
    after = uncertainty.rating_sd(x, np.array([0]), uncertainty.covariance('newcomer', model))[0]
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
    gains = uncertainty.variance_reduction([along, across], targets, covariance)
    # by hand: asking x = e₀: k_t = 4 for both targets, innovation 4 + 0.5; 2 · 4 · 16 / 4.5; across: k_t = 0
    assert gains == pytest.approx([2 * 4 * 16 / 4.5, 0.0])


def test_the_decision_value_is_the_expected_gain_of_re_choosing_by_hand():
    uncertainty = one_action_uncertainty(noise=0.5, std=2.0)
    covariance, mean = np.diag([4.0, 0.25]), np.array([0.3, 0.0])
    # one decision of two entries: scores 2·θ₀ and 2·θ₁ (rating scale), now 0.6 against 0: the first leads
    decision = (np.array([[1.0, 0.0], [0.0, 1.0]]), np.zeros(2), np.zeros(2, dtype=int))
    along, far = (np.array([[1.0, 0.0]]), np.zeros(1, dtype=int)), (np.array([[0.0, 0.0]]), np.zeros(1, dtype=int))
    values = uncertainty.log_decision_value([along, far], [decision], mean, covariance)
    # by hand: the gap's row g = 2·(1, −1), its mean 0.6; asking x = e₀: X Σ g = 8, innovation 4 + 0.5,
    # s² = 64 / 4.5; the gain s·ψ(0.6 / s), ψ(z) = φ(z) − z(1 − Φ(z)); a question loading on nothing gains 0
    s = np.sqrt(64 / 4.5)
    z = 0.6 / s
    assert np.exp(values) == pytest.approx([s * (stats.norm.pdf(z) - z * stats.norm.sf(z)), 0.0])
    clear, far_clear = uncertainty.log_decision_value([along], [decision], np.array([30.0, 0.0]), covariance)[0], \
        uncertainty.log_decision_value([along], [decision], np.array([300.0, 0.0]), covariance)[0]
    assert values[0] - 10 > clear > far_clear > -np.inf  # a clear choice is worth little, yet still ordered
    single = (decision[0][:1], decision[1][:1], decision[2][:1])
    assert uncertainty.log_decision_value([along], [single], mean, covariance)[0] == -np.inf  # nothing to choose


def test_log_psi_is_the_expected_shortfall_and_keeps_its_digits_far_out():
    z = np.array([0.0, 0.5, 2.0, 8.0])
    assert np.exp(log_psi(z)) == pytest.approx(stats.norm.pdf(z) - z * stats.norm.sf(z), rel=1e-9)
    far = log_psi(np.array([50.0, 5e3, 5e5]))
    assert np.all(np.isfinite(far)) and np.all(np.diff(far) < 0)
    # the asymptotic series ψ(z) = φ(z) / z² · (1 − 3 / z² + ...)
    assert far[0] == pytest.approx(stats.norm.logpdf(50.0) - 2 * np.log(50.0) + np.log1p(-3 / 50.0 ** 2), abs=1e-5)
