"""Short real training runs on SocNav1 (seconds each)."""
import numpy as np
import pytest

from stars_ros.config import ExperimentConfig
from stars_ros.errors import TrainingDivergedError
from stars_ros.training import NotFittedError, StarsRecommender, split_rows

SMALL = {'encoder': {'name': 'gcn', 'hidden': 16, 'layers': 1}, 'model': {'dim': 16},
         'training': {'pretrain_epochs': 2, 'joint_epochs': 4, 'lr': 3e-3, 'batch_size': 128, 'threads': 1}}


@pytest.fixture(scope='module')
def rows(socnav1):
    train, test = split_rows(len(socnav1), 0.2, 0)
    return train[:2000], test[:500]


def test_split_is_seeded_and_disjoint():
    train, test = split_rows(100, 0.2, 7)
    assert len(test) == 20 and not set(train) & set(test) and len(train) + len(test) == 100
    assert np.array_equal(test, split_rows(100, 0.2, 7)[1])
    assert not np.array_equal(test, split_rows(100, 0.2, 8)[1])


@pytest.mark.parametrize('variant', ['stars', 'base', 'mf'])
def test_training_lowers_the_loss_and_beats_the_mean(socnav1, rows, variant):
    train, test = rows
    recommender = StarsRecommender(ExperimentConfig.from_dict(SMALL).replace(model={'variant': variant}))
    recommender.fit(socnav1, train)
    joint = recommender.history['joint']
    assert joint[-1] < joint[0]
    assert len(recommender.history['pretrain']) == (0 if variant == 'mf' else 2)
    metrics = recommender.evaluate(socnav1, test)
    mean_mse = float(np.mean((socnav1.scores[test] - socnav1.scores[train].mean()) ** 2))
    if variant != 'mf':  # content models must beat the global mean already
        assert metrics['mse'] < mean_mse
    assert metrics['n'] == len(test)


def test_training_is_deterministic(socnav1, rows):
    train, test = rows
    config = ExperimentConfig.from_dict(SMALL)
    first = StarsRecommender(config).fit(socnav1, train[:800]).predict_rows(socnav1, test)
    second = StarsRecommender(config).fit(socnav1, train[:800]).predict_rows(socnav1, test)
    assert np.array_equal(first, second)


def test_vocabularies_come_from_training_rows_only(socnav1, rows):
    train, _ = rows
    recommender = StarsRecommender(ExperimentConfig.from_dict(SMALL).replace(
        training={'pretrain_epochs': 0, 'joint_epochs': 1})).fit(socnav1, train[:300])
    assert set(recommender.users) == set(socnav1.users[train[:300]].tolist())
    assert len(recommender.scene_keys) == len(set(socnav1.scenes[train[:300]].tolist()))


def test_divergence_is_reported(socnav1, rows):
    config = ExperimentConfig.from_dict(SMALL).replace(training={'lr': 1e30, 'grad_clip': 1e30,
                                                                 'pretrain_epochs': 1, 'joint_epochs': 1})
    with pytest.raises(TrainingDivergedError, match='lower the learning rate'):
        StarsRecommender(config).fit(socnav1, rows[0][:500])


def test_predict_before_fit():
    with pytest.raises(NotFittedError, match='not fitted'):
        StarsRecommender(ExperimentConfig()).predict_scores(['a'], [None], None)
