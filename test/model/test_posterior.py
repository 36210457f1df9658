"""The Bayesian head (``model.posterior``, ``training.posterior_sweeps``): off it is today's fit,
it never reads a test row, its conditionals are the hand-derived Gaussians, and on data made
by the StARS form it does no worse than the point estimate it starts from."""
import dataclasses

import numpy as np
import pytest
import torch

from stars_ros.data.ratings import load_dataset
from stars_ros.errors import ConfigError
from stars_ros.evaluation.executors import FitTask, run_fit
from stars_ros.evaluation.protocol import ProtocolConfig
from stars_ros.model.checkpoint import load_checkpoint, save_checkpoint
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.fitted import build_model
from stars_ros.model.posterior import Chain, Layout, Observations, gaussian_rows, training_observations
from stars_ros.model.training import StarsTrainer, split_rows
from conftest import served_report, served_rows

from generic_data import write_generic_data

SMALL = {'encoder': {'name': 'gcn', 'hidden': 16, 'layers': 1}, 'model': {'dim': 16},
         'training': {'pretrain_epochs': 2, 'joint_epochs': 4, 'lr': 3e-3, 'batch_size': 128, 'threads': 1}}
SAMPLED = {'posterior_sweeps': 40, 'posterior_burn_in': 10}


@pytest.fixture(scope='module')
def rows(synthetic):
    train, test = split_rows(synthetic, 0.2, 0)
    return train[:800], test[:300]


def test_switched_off_it_is_todays_fit_weight_for_weight(synthetic, rows):
    train, _ = rows
    config = ExperimentConfig.from_dict(SMALL)
    assert config.training.posterior_sweeps == 0
    today = StarsTrainer(config).fit(synthetic, train).model.state_dict()
    off = StarsTrainer(config.replace(training={'posterior_sweeps': 0})).fit(synthetic, train).model.state_dict()
    assert today.keys() == off.keys() and all(torch.equal(today[name], off[name]) for name in today)
    sampled = StarsTrainer(config.replace(training=SAMPLED)).fit(synthetic, train).model.state_dict()
    assert not torch.equal(sampled['scene_embedding.weight'], today['scene_embedding.weight'])
    assert all(torch.equal(sampled[name], today[name]) for name in today if name.startswith('encoder.'))  # frozen


def test_it_never_reads_a_test_row(synthetic, rows):
    train, test = rows
    config = ExperimentConfig.from_dict(SMALL).replace(training=SAMPLED)
    low, high = synthetic.scale
    turned = dataclasses.replace(synthetic, scores=synthetic.scores.copy())
    others = np.setdiff1d(np.arange(len(synthetic)), train)
    turned.scores[others] = high + low - turned.scores[others]  # every score but the training rows' turned over
    first = served_rows(StarsTrainer(config).fit(synthetic, train), synthetic, test)
    second = served_rows(StarsTrainer(config).fit(turned, train), turned, test)
    assert np.array_equal(first, second)


def test_parts_a_variant_holds_at_zero_stay_zero_and_base_is_refused(synthetic, rows):
    train, _ = rows
    config = ExperimentConfig.from_dict(SMALL).replace(training=SAMPLED)
    for variant, absent in (('stars_no_q', ('scene_embedding',)),
                            ('base_user_bias', ('user_embedding', 'scene_embedding', 'scene_bias'))):
        model = StarsTrainer(config.replace(model={'variant': variant})).fit(synthetic, train).model
        for name in absent:
            assert getattr(model, name).weight.abs().sum() == 0, (variant, name)
    with pytest.raises(ConfigError, match="'base' variant has no factorisation part"):
        config.replace(model={'variant': 'base'})
    with pytest.raises(ConfigError, match=r'posterior_burn_in \(50\) must be below posterior_sweeps \(50\)'):
        config.replace(training={'posterior_sweeps': 50, 'posterior_burn_in': 50})


def test_a_posterior_head_checkpoint_round_trips_and_old_configs_still_load(synthetic, rows, tmp_path):
    train, test = rows
    fitted = StarsTrainer(ExperimentConfig.from_dict(SMALL).replace(training=SAMPLED)).fit(synthetic, train)
    save_checkpoint(fitted, tmp_path / 'bayes.pt', data={'fingerprint': synthetic.fingerprint})
    loaded, metadata = load_checkpoint(tmp_path / 'bayes.pt')
    assert np.array_equal(served_rows(loaded, synthetic, test), served_rows(fitted, synthetic, test))
    assert metadata['config']['training']['posterior_sweeps'] == 40
    written_before = fitted.config.to_dict()
    for key in ('posterior_sweeps', 'posterior_burn_in'):
        del written_before['training'][key]
    assert ExperimentConfig.from_dict(written_before).training.posterior_sweeps == 0


def test_nested_selection_scores_the_posterior_head_at_every_point_of_its_curves(synthetic, rows):
    """An inner fit scores its curve at each T2 of the grid during one fit: with a posterior
    head each point is the head on that epoch's weights, so the last point is the fit's score
    and posterior_sweeps (searchable) is chosen on what it changes."""
    train, test = rows
    protocol = ProtocolConfig.from_dict({'search': {'stars': {'posterior_sweeps': [0, 100]}}})
    assert protocol.experiment_config(None, 'stars', {'posterior_sweeps': 100}).training.posterior_sweeps == 100
    experiment = ExperimentConfig.from_dict(SMALL).replace(training=SAMPLED)
    scores = run_fit(FitTask('StARS', '0:0', 'inner', experiment.to_dict(), train, test, curve_at=(2, 4)), synthetic)
    assert scores['curve'][-1]['mse'] == scores['mse']
    off = run_fit(FitTask('StARS', '0:0', 'inner', experiment.replace(training={'posterior_sweeps': 0}).to_dict(),
                          train, test, curve_at=(2, 4)), synthetic)
    assert all(on['mse'] != point['mse'] for on, point in zip(scores['curve'], off['curve']))


# -- the math by hand ----------------------------------------------------------------------
USERS, ITEMS, ACTIONS = [0, 0, 0, 0, 1, 1], [0, 0, 1, 2, 1, 2], [0, 1, 0, 1, 1, 0]
PRECISIONS = {'p': [2.0, 3.0], 'q': [4.0, 5.0], 'r': [0.5, 1.5], 'b_u': [6.0], 'b_i': [7.0], 'noise': 8.0}


def tiny_chain(variant: str) -> tuple:
    """2 users, 3 scenes, 2 actions, dim 2, weights and h by hand: the chain, and its numbers in numpy."""
    config = ExperimentConfig.from_dict({'encoder': {'name': 'mlp', 'hidden': 4, 'layers': 1},
                                         'model': {'variant': variant, 'dim': 2}})
    model = build_model(config, 3, 'tabular', 2, 3, 2)
    rng = np.random.default_rng(3)
    w = {'p': rng.normal(size=(2, 2)), 'b_u': rng.normal(size=2), 'q': rng.normal(size=(3, 2)),
         'b_i': rng.normal(size=3), 'r': rng.normal(size=(2, 2)), 'b': 0.3,
         'h': rng.normal(size=(6, 2)), 'y': rng.normal(size=6)}
    with torch.no_grad():
        model.user_embedding.weight.copy_(torch.tensor(w['p']))
        model.user_bias.weight.copy_(torch.tensor(w['b_u'])[:, None])
        model.scene_embedding.weight.copy_(torch.tensor(w['q']))
        model.scene_bias.weight.copy_(torch.tensor(w['b_i'])[:, None])
        model.action_embedding.copy_(torch.tensor(w['r']))
        model.bias.fill_(w['b'])
    w = {k: np.asarray(torch.tensor(v).float().double()) for k, v in w.items()}  # the model's float32 values
    observations = Observations(torch.tensor(USERS), torch.tensor(ITEMS), torch.tensor(ACTIONS),
                                torch.tensor(w['h']), torch.tensor(w['y']))
    chain = Chain(model, observations, seed=0)
    chain.precisions.update({part: torch.tensor(value, dtype=torch.float64) for part, value in PRECISIONS.items()})
    return chain, model, w


def by_hand(features, offsets, y, prior, noise) -> tuple:
    """Bayesian linear regression: y ≈ offsets + features w, w ~ N(0, diag(prior)⁻¹), noise precision ``noise``."""
    covariance = np.linalg.inv(np.diag(prior) + noise * features.T @ features)
    return covariance @ (noise * features.T @ (y - offsets)), covariance


@pytest.mark.parametrize('block', ['users', 'scenes', 'actions'])
def test_a_blocks_conditional_is_the_gaussian_derived_by_hand(block):
    chain, _, w = tiny_chain('stars')
    p, q, r, h = w['p'], w['q'], w['r'], w['h']
    for row in range({'users': 2, 'scenes': 3, 'actions': 2}[block]):
        entries = [j for j in range(6) if {'users': USERS, 'scenes': ITEMS, 'actions': ACTIONS}[block][j] == row]
        features, offsets = [], []
        for j in entries:
            u, i, a = USERS[j], ITEMS[j], ACTIONS[j]
            if block == 'users':  # ŷ = p_u·((q_i + h) ⊙ r_a) + b_u + (h·r_a + b_i + b)
                features.append([*((q[i] + h[j]) * r[a]), 1.0])
                offsets.append(h[j] @ r[a] + w['b_i'][i] + w['b'])
            elif block == 'scenes':  # ŷ = q_i·(p_u ⊙ r_a) + b_i + (p_u·(h ⊙ r_a) + h·r_a + b_u + b)
                features.append([*(p[u] * r[a]), 1.0])
                offsets.append(p[u] @ (h[j] * r[a]) + h[j] @ r[a] + w['b_u'][u] + w['b'])
            else:  # ŷ = r_a·(p_u ⊙ (q_i + h) + h) + (b_u + b_i + b)
                features.append(p[u] * (q[i] + h[j]) + h[j])
                offsets.append(w['b_u'][u] + w['b_i'][i] + w['b'])
        prior = {'users': PRECISIONS['p'] + PRECISIONS['b_u'], 'scenes': PRECISIONS['q'] + PRECISIONS['b_i'],
                 'actions': PRECISIONS['r']}[block]
        mean, covariance = by_hand(np.array(features), np.array(offsets), w['y'][entries], prior, PRECISIONS['noise'])
        found = {'users': chain.user_conditional, 'scenes': chain.scene_conditional,
                 'actions': chain.action_conditional}[block]()
        np.testing.assert_allclose(found.mean[row].numpy(), mean, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(found.covariance[row].numpy(), covariance, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize('most', [2, 6])
def test_draws_have_the_conditionals_mean_and_covariance(most):
    """Both forms (observation form with fewer observations than weights, precision form
    otherwise) draw from the Gaussian they describe."""
    rng = np.random.default_rng(0)
    features, targets = torch.from_numpy(rng.normal(size=(most, 3))), torch.from_numpy(rng.normal(size=most))
    posterior = gaussian_rows(features, targets, Layout.of(torch.zeros(most, dtype=torch.long), 1),
                              torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64),
                              torch.tensor(4.0, dtype=torch.float64))
    draws = torch.stack([posterior.draw(rng)[0] for _ in range(20000)]).numpy()
    np.testing.assert_allclose(draws.mean(0), posterior.mean[0].numpy(), atol=0.03)
    np.testing.assert_allclose(np.cov(draws.T), posterior.covariance[0].numpy(), atol=0.03)


@pytest.mark.parametrize('variant', ['stars', 'stars_no_residual', 'mf'])
def test_the_chain_predicts_what_the_model_predicts(variant):
    chain, model, _ = tiny_chain(variant)
    o = chain.observations
    with torch.no_grad():
        by_model = model(o.users, o.items, o.h.float() * model.uses_content)[torch.arange(6), o.actions]
    chain.observations = o._replace(h=o.h * model.uses_content)
    np.testing.assert_allclose(chain.predict().numpy(), by_model.double().numpy(), rtol=1e-5, atol=1e-5)


# -- data the StARS form generates ---------------------------------------------------------
@pytest.fixture(scope='module')
def stars_form(tmp_path_factory):
    """12 users, 400 scenes rated by 2 users each for 2 actions: ŷ of the StARS form, with
    h_i = tanh(x_i W) and Gaussian noise of sd 0.3."""
    rng = np.random.default_rng(11)
    root = tmp_path_factory.mktemp('stars_form')
    n_users, n_scenes, features, dim = 12, 400, 6, 4
    x = rng.normal(size=(n_scenes, features))
    h = np.tanh(x @ rng.normal(size=(features, dim)) / np.sqrt(features))
    p, q = rng.normal(scale=0.6, size=(n_users, dim)), rng.normal(scale=0.4, size=(n_scenes, dim))
    r, b_u, b_i = rng.normal(size=(2, dim)), rng.normal(scale=0.3, size=n_users), rng.normal(scale=0.3, size=n_scenes)
    ratings = []
    for i in range(n_scenes):
        for u in rng.choice(n_users, size=2, replace=False):
            for a, action in enumerate(('pass', 'wait')):
                score = 3 + (p[u] * (q[i] + h[i]) + h[i]) @ r[a] + b_u[u] + b_i[i] + rng.normal(scale=0.3)
                ratings.append([f'u{u}', f's{i}', action, f'{score:.4f}'])
    write_generic_data(root, x, ratings)
    return load_dataset(root)


def test_on_stars_form_data_the_posterior_means_do_no_worse_than_the_point_estimate(stars_form):
    train, test = split_rows(stars_form, 0.25, 0)
    config = ExperimentConfig.from_dict({
        'encoder': {'name': 'mlp', 'hidden': 32, 'layers': 2}, 'model': {'dim': 4},
        'training': {'pretrain_epochs': 30, 'joint_epochs': 60, 'lr': 1e-2, 'batch_size': 64, 'embedding_l2': 0.01,
                     'weight_decay': 0.0, 'threads': 1}})
    point = StarsTrainer(config).fit(stars_form, train)
    bayes = StarsTrainer(config.replace(training={'posterior_sweeps': 200, 'posterior_burn_in': 50}))
    bayes.fit(stars_form, train)
    point_mse = served_report(point, stars_form, test)['mse']
    bayes_mse = served_report(bayes, stars_form, test)['mse']
    assert bayes_mse <= point_mse, (bayes_mse, point_mse)
    observations = training_observations(bayes.model, stars_form.store, bayes.training_set(stars_form, train))
    assert len(observations.targets) == len(train)  # every training rating is one entry, and nothing else
