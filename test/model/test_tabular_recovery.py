"""StARS recovers a planted user × scene preference that no scene-only model can fit.

Half the users like what the other half dislikes: on a 1-5 scale, user u rates scene i
3 + t_u·s_i for action ``pass`` and 3 − t_u·s_i/2 for ``wait`` (t_u = ±1, s_i the first
scene feature, plus noise). Averaged over users the taste cancels, so the best scene-only
predictor is near the population mean; the per-user factor p_u of StARS can flip the sign.
The data goes through the generic tabular format and the same protocol as SocNav1.
"""
import numpy as np
import pytest

from stars_ros.model.config import ExperimentConfig
from stars_ros.data.ratings import load_dataset
from stars_ros.evaluation.protocol import ProtocolConfig, run_protocol
from stars_ros.evaluation.summaries import by_model
from stars_ros.model.training import StarsTrainer, split_rows
from conftest import served_report

from generic_data import write_generic_data

NOISE = 0.2
EXPERIMENT = {'encoder': {'name': 'mlp', 'hidden': 32, 'layers': 2},
              'model': {'dim': 8},
              'training': {'batch_size': 128, 'lr': 1e-2, 'weight_decay': 0.0, 'threads': 1}}


@pytest.fixture(scope='module')
def planted(tmp_path_factory):
    rng = np.random.default_rng(7)
    root = tmp_path_factory.mktemp('planted')
    n_scenes, n_users, features = 200, 16, 4
    x = rng.normal(size=(n_scenes, features))
    taste = np.repeat([1.0, -1.0], n_users // 2)
    ratings = []
    for u in range(n_users):
        for i in rng.choice(n_scenes, size=60, replace=False):
            for action, slope in (('pass', 1.0), ('wait', -0.5)):
                score = 3 + slope * taste[u] * x[i, 0] + rng.normal(scale=NOISE)
                ratings.append([f'u{u}', f's{i}', action, f'{np.clip(score, 1, 5):.3f}'])
    write_generic_data(root, x, ratings)
    return load_dataset(root)


def test_planted_data_loads_as_tabular(planted):
    assert planted.kind == 'tabular' and planted.action_names == ('pass', 'wait')
    assert len(planted) == 16 * 60 * 2


def test_stars_recovers_what_base_cannot_through_the_protocol(planted):
    config = ProtocolConfig.from_dict({
        'name': 'planted', 'folds': 2, 'grid': [[5, 60]], 'backbones': {'mlp': {}}, 'error': 'rmse',
        'baselines': ['population_mean', 'mf'], 'experiment': EXPERIMENT})
    result = run_protocol(planted, config, 'rows')
    rmse = {label: np.mean([e['rmse'] for e in entries]) for label, entries in by_model(result.final()).items()}
    mean, base, stars = rmse['Population mean'], rmse['MLP base'], rmse['MLP StARS']
    assert base > 0.85 * mean, f'base should not fit the planted taste: {rmse}'
    assert stars < 0.5 * base, f'StARS should recover it: {rmse}'
    assert stars < 3 * NOISE, rmse


@pytest.mark.parametrize('backbone', ['resmlp', 'dcnv2', 'graceae', pytest.param('fttransformer',
                                                                                 marks=pytest.mark.slow)])
def test_every_tabular_backbone_recovers_it(planted, backbone):
    train, test = split_rows(planted, 0.2, 0)
    rmse = {}
    for variant in ('base', 'stars'):
        config = ExperimentConfig.from_dict({**EXPERIMENT, 'encoder': {**EXPERIMENT['encoder'], 'name': backbone},
                                             'model': {'variant': variant, 'dim': 8},
                                             'training': {**EXPERIMENT['training'], 'pretrain_epochs': 5,
                                                          'joint_epochs': 60}})
        rmse[variant] = served_report(StarsTrainer(config).fit(planted, train), planted, test)['rmse']
    assert rmse['stars'] < 0.5 * rmse['base'], rmse
